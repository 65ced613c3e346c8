"""A PLY, PCD, E57 or text point file written as LAZ: how every non-LAS input enters,
so that everything after it reads LAS/LAZ only.

The points keep their order (rows with a non-finite x, y or z, which organized clouds
and some exports hold for beams without a return, are left out and counted), at
millimetre precision (scale 0.001, offsets the first point rounded down to 1 km), in a
LAS 1.4 file of point format 6 with the CRS given or the file's own.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from pipeline.errors import ParameterError
from pipeline.formats import open_points, sniff
from pipeline.formats.source import CHUNK_POINTS, bad

#: millimetres: the precision of a converted file's coordinates [m]
SCALE = 0.001


@dataclass(frozen=True)
class Converted:
    """What :func:`to_laz` wrote: the source's format, points written, rows left out
    (non-finite), and whether a CRS was stored."""

    format: str
    n_points: int
    n_dropped: int
    has_crs: bool


def parse_crs_option(text: str | None) -> int | None:
    """The EPSG code of a ``--crs`` value (``EPSG:28356`` or ``28356``); None for None.

    Raises
    ------
    ParameterError
        Not of that form, an unknown code, or a CRS whose unit is not the metre.
    """
    if text is None:
        return None
    m = re.fullmatch(r"\s*(?:epsg:)?(\d{4,6})\s*", str(text), re.IGNORECASE)
    if m is None:
        raise ParameterError(f"CRS {text!r} is not of the form EPSG:NNNN (e.g. EPSG:28356)", param="job.crs", value=text)
    import pyproj

    from pipeline.crs import crs_units_problem

    try:
        crs = pyproj.CRS.from_epsg(int(m.group(1)))
    except pyproj.exceptions.CRSError:
        raise ParameterError(f"CRS {text!r}: no such EPSG code", param="job.crs", value=text) from None
    problem = crs_units_problem(crs)
    if problem:
        raise ParameterError(f"CRS {text!r}: {problem}", param="job.crs", value=text)
    return int(m.group(1))


def to_laz(src, dst, *, fmt: str | None = None, crs_epsg: int | None = None, columns: str | None = None,
           chunk_points: int = CHUNK_POINTS, reader: str = "own") -> Converted:
    """Write the points of a PLY, PCD, E57 or text file ``src`` as the LAZ file ``dst``.

    Parameters
    ----------
    src, dst : str or Path
        ``dst`` appears only when the whole file was written (nothing half-written).
    fmt : str, optional
        The format (:func:`pipeline.formats.sniff` when None).
    crs_epsg : int, optional
        The CRS of the points (wins over one the file states).
    columns : str, optional
        A text file's column names (:func:`pipeline.formats.text.open_text`).
    chunk_points : int
        Points read at a time (bounds memory).
    reader : "own" or "pdal"
        The project's readers (:mod:`pipeline.formats`) or PDAL's
        (:mod:`pipeline.formats.pdalreaders`).

    Raises
    ------
    InputError
        A file of none of these formats, a corrupt or hostile one, no finite point,
        coordinates that do not fit a LAS file at millimetres.
    """
    from pipeline.laswriting import LasBlockWriter

    fmt = fmt or sniff(src)
    if fmt == "las":
        raise bad(src, "is a LAS/LAZ file already")
    if reader == "pdal":
        from pipeline.formats.pdalreaders import open_with_pdal

        source = open_with_pdal(src, fmt, columns=columns)
    else:
        source = open_points(src, fmt, columns=columns)
    written = dropped = 0
    with LasBlockWriter(dst, crs_epsg=crs_epsg, crs_wkt=None if crs_epsg else source.crs_wkt,
                        scales=(SCALE, SCALE, SCALE), creation_date="unset") as w:
        for xyz in source.chunks(int(chunk_points)):
            keep = np.isfinite(xyz).all(axis=1)
            if not keep.all():
                dropped += int((~keep).sum())
                xyz = xyz[keep]
            if len(xyz) and float(np.abs(xyz).max()) > 1e8:
                raise bad(src, "a coordinate is larger than 100,000 km: not metres of a projected CRS, or corrupt")
            try:
                w.write(xyz)
            except ValueError:
                raise bad(src, "the points span more than 2,000 km: not metres of a projected CRS, or corrupt") from None
            written += len(xyz)
        if written == 0:
            raise bad(src, "holds no points" + (f" with finite coordinates ({dropped} rows of NaN or infinity)" if dropped else ""))
    return Converted(fmt, written, dropped, bool(crs_epsg or source.crs_wkt))


__all__ = ["Converted", "parse_crs_option", "to_laz"]
