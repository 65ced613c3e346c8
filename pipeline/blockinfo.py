"""The header of a LAS/LAZ block, read and checked: :class:`BlockInfo` and :func:`read_info`.

The structure of the file (sizes, counts, offsets) is checked first by
:mod:`pipeline.lasheader`; this module then reads the header with laspy and checks its
values (point count, scales, offsets, bounds, CRS units). Every problem becomes an
:class:`~pipeline.errors.InputError` whose message is one line naming the file and what
is wrong.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path

from pipeline import lasheader
from pipeline.crs import crs_units_problem, parse_crs
from pipeline.errors import InputError
from pipeline.laspyload import laspy

#: Largest absolute coordinate accepted [m] (UTM northings are < 1e7).
MAX_ABS_COORD = 1e8
#: Largest extent of a block accepted along any axis [m].
MAX_EXTENT = 1e5
#: LAS point formats read.
SUPPORTED_FORMATS = tuple(range(11))


@dataclass(frozen=True)
class BlockInfo:
    """What the header of a LAS/LAZ block says, checked.

    Attributes
    ----------
    path : str
    n_points : int
    version : str
        ``"1.2"``, ``"1.3"`` or ``"1.4"`` (``"1.0"``/``"1.1"`` are read too).
    point_format : int
        0–10.
    compressed : bool
        True for LAZ.
    scales, offsets : (3,) float
        The header's scale factors and offsets.
    mins, maxs : (3,) float
        The header's bounds [m], input CRS.
    crs_wkt : str or None
        From the WKT VLR or the GeoTIFF keys; None when absent or not understood.
    origin : (3,) float
        Local origin = ``floor(mins)``; local coordinates are ``xyz - origin``.
    seekable : bool
        Whether a range of points can be read without decoding the points before it
        (:func:`read_raw_range`): LAS, and LAZ with fixed-size chunks and a chunk table.
        lazrs 0.8 decodes wrong points after a seek in a LAZ file of variable-size
        chunks (as COPC files are stored), so those are read from the start.
    copc : bool
        A COPC file (its first VLR is the COPC info): its tiles read their own octree
        nodes (:mod:`pipeline.formats.copc`), with no pass over the whole file.
    """

    path: str
    n_points: int
    version: str
    point_format: int
    compressed: bool
    scales: tuple[float, float, float]
    offsets: tuple[float, float, float]
    mins: tuple[float, float, float]
    maxs: tuple[float, float, float]
    crs_wkt: str | None
    origin: tuple[float, float, float]
    seekable: bool = True
    copc: bool = False


def input_error(path, what: str) -> InputError:
    """An InputError whose message names the file (its base name) and what is wrong."""
    return InputError(f"{Path(str(path)).name}: {what}")


def one_line(exc: BaseException) -> str:
    """A library's error message on one line of at most about 200 characters."""
    text = " ".join(str(exc).split())
    return (text[:200] + "...") if len(text) > 200 else (text or type(exc).__name__)


#: no LAZ file holds more points per byte of compressed data than this (identical
#: points compress to about 140 per byte); the bound for files without a chunk table
MAX_LAZ_POINTS_PER_BYTE = 1000


def _laz_points_held(p: Path, header, table: int, n_bytes: int) -> tuple[int, bool]:
    """The most points the compressed data of a LAZ file can hold: from its chunk table
    (fixed-size chunks: each holds at most the chunk size), or for a file without one,
    a bound from its size, so that a forged point count cannot have the tiler plan work
    for points that are not there. Also whether the file is seekable (see
    :class:`BlockInfo`)."""
    import lazrs

    vlr = next((v for v in header.vlrs if v.user_id == "laszip encoded" and v.record_id == 22204), None)
    if table == -1 or vlr is None:
        return max(1, n_bytes) * MAX_LAZ_POINTS_PER_BYTE, False
    try:
        laz_vlr = lazrs.LazVlr(vlr.record_data)
        with open(p, "rb") as f:
            f.seek(table)
            chunks = lazrs.read_chunk_table_only(f, laz_vlr)
    except Exception as exc:  # lazrs raises its own error types for a broken table
        raise input_error(p, f"corrupt: its LAZ chunk table cannot be read ({one_line(exc)})") from None
    # lazrs allocates each chunk's byte count when it reads the chunk: bound them by the data
    data_bytes = table - int(header.offset_to_point_data) - 8
    if sum(int(c[1]) for c in chunks) > data_bytes:
        raise input_error(p, f"corrupt: its LAZ chunk table gives {sum(int(c[1]) for c in chunks):,} bytes of chunks "
                             f"but its compressed data holds {data_bytes:,}")
    if laz_vlr.uses_variable_size_chunks():
        return sum(int(c[0]) for c in chunks), False
    return len(chunks) * int(laz_vlr.chunk_size()), True


def _projection_evlrs(p: Path, layout: lasheader.HeaderLayout):
    """The EVLRs that may hold the CRS (LAS 1.4 may keep it there), and only those: a
    waveform EVLR can take gigabytes, and laspy would read every EVLR whole."""
    if not layout.evlrs:
        return None
    data, count = lasheader.read_records(p, layout.evlrs, user_id="LASF_Projection", extended=True)
    return laspy.vlrs.vlrlist.VLRList.read_from(BytesIO(data), count, extended=True)


def read_info(path) -> BlockInfo:
    """Read and check the header of a LAS/LAZ file.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    BlockInfo

    Raises
    ------
    InputError
        Not a LAS/LAZ file, truncated, no points, NaN/infinite/zero scales or offsets,
        absurd bounds (``|coord| > 1e8 m`` or extent ``> 1e5 m``), unsupported version
        or point format, a CRS whose unit is not the metre (feet, degrees).
    """
    p = Path(str(path))
    # every size, count and offset is checked against the file before laspy walks them
    layout = lasheader.check_file(p)
    size, version = layout.file_size, layout.version
    try:  # the header and VLRs only: no EVLRs, no LAZ decompressor (it reads the chunk table)
        with open(p, "rb") as f:
            header = laspy.LasHeader.read_from(f, read_evlrs=False)
        header.evlrs = _projection_evlrs(p, layout)
    except Exception as exc:  # laspy raises many types for a broken header
        raise input_error(p, f"not a readable LAS/LAZ file ({one_line(exc)})") from None
    fmt = int(header.point_format.id)
    if fmt not in SUPPORTED_FORMATS:
        raise input_error(p, f"unsupported point format {fmt}; formats 0 to 10 are read")
    n = int(header.point_count)
    if n == 0:
        raise input_error(p, "empty: the header says it holds no points")
    compressed = bool(header.are_points_compressed)
    seekable = True
    start = int(header.offset_to_point_data)
    if compressed:  # a LAS file's points were checked to fit by check_header
        most, seekable = _laz_points_held(p, header, layout.chunk_table, size - start)
        if n > most:
            raise input_error(p, f"corrupt: the header announces {n:,} points but its compressed data holds at most {most:,}")
    scales = tuple(float(s) for s in header.scales)
    offsets = tuple(float(o) for o in header.offsets)
    if not all(math.isfinite(s) and s > 0 for s in scales):
        raise input_error(p, f"invalid scale factors {scales}: they must be finite and positive")
    if not all(math.isfinite(o) and abs(o) <= MAX_ABS_COORD for o in offsets):
        raise input_error(p, f"absurd offsets {offsets}: coordinates must be finite and within 1e8 m")
    mins = tuple(float(v) for v in header.mins)
    maxs = tuple(float(v) for v in header.maxs)
    if not all(math.isfinite(v) for v in mins + maxs):
        raise input_error(p, "the header's bounds are NaN or infinite")
    if any(abs(v) > MAX_ABS_COORD for v in mins + maxs):
        raise input_error(p, f"absurd coordinates (bounds {mins} to {maxs}): |coordinate| above 1e8 m")
    if any(hi - lo > MAX_EXTENT or hi < lo for lo, hi in zip(mins, maxs)):
        raise input_error(p, f"absurd bounds {mins} to {maxs}: a block must span at most 1e5 m; split the file")
    crs, problem = parse_crs(header)
    crs_wkt = crs.to_wkt() if crs is not None else None
    problem = problem or crs_units_problem(crs)
    if problem:
        raise input_error(p, problem)
    origin = tuple(float(math.floor(v)) for v in mins)
    return BlockInfo(
        path=str(p),
        n_points=n,
        version=version,
        point_format=fmt,
        compressed=compressed,
        scales=scales,
        offsets=offsets,
        mins=mins,
        maxs=maxs,
        crs_wkt=crs_wkt,
        origin=origin,
        seekable=seekable,
        copc=compressed and len(header.vlrs) > 0 and header.vlrs[0].user_id == "copc" and header.vlrs[0].record_id == 1,
    )



def creation_date(path) -> str | None:
    """The file creation day of a LAS/LAZ header as an ISO date (``YYYY-MM-DD``); None
    when the header leaves it unset (day or year 0) or cannot be read."""
    try:
        with laspy.open(str(path)) as reader:
            day = reader.header.creation_date
    except Exception:  # noqa: BLE001 - a date is optional; read_info says what is wrong with the file
        return None
    return None if day is None else day.isoformat()
