"""The structure of a LAS/LAZ file, checked with ``struct`` before any library parses it.

laspy and lazrs trust the counts and offsets a header gives, so a small forged file can
make them allocate without bound (docs/hostile-input.md). This module
reads the public header (LAS 1.0–1.4, ASPRS LAS 1.4 R15 §2.4), walks the VLR and EVLR
headers itself and reads the LAZ chunk table's header, and checks every size, count and
offset against the file's size and against each other. It reads a bounded number of
bytes (at most :data:`MAX_VLRS` VLR headers, :data:`MAX_EVLRS` EVLR headers and the
LASzip record) and allocates nothing in proportion to a claimed count, so whatever a
header claims, the check answers at once.

Every failure is an :class:`~pipeline.errors.InputError` whose message is one line
naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from pipeline.errors import InputError

#: Size of the public header [bytes] by minor version (1.0–1.2 share one layout).
HEADER_SIZES = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
#: Size of a point record [bytes] by point format, without extra bytes.
POINT_SIZES = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
VLR_HEADER_SIZE = 54
EVLR_HEADER_SIZE = 60
#: Most VLRs / EVLRs read; real files hold a handful (projection, extra bytes, LASzip).
MAX_VLRS = 10_000
MAX_EVLRS = 10_000
#: Most bytes of header and VLRs before the point data; laspy reads all of them at once.
MAX_VLR_AREA = 16 << 20
#: Most LAZ chunks read (lazrs keeps 16 bytes per chunk): 2^20 chunks of 50,000 points
#: are 5e10 points.
MAX_LAZ_CHUNKS = 1 << 20
LASZIP_USER_ID, LASZIP_RECORD_ID = "laszip encoded", 22204
#: ``chunk_size`` of a LASzip record whose chunks each say how many points they hold.
VARIABLE_CHUNK_SIZE = 0xFFFFFFFF

_PUBLIC = struct.Struct("<4sHH16sBB32s32sHHHIIBHI5I3d3d6d")  # the 227 bytes every version has
_EXTENDED = struct.Struct("<QQIQ15Q")  # 1.4: waveform start, EVLR start, EVLR count, point count, by return
_VLR = struct.Struct("<H16sHH32s")
_EVLR = struct.Struct("<H16sHQ32s")
_LASZIP = struct.Struct("<HHBBHIIqqH")  # the LASzip record up to its item count (34 bytes)


@dataclass(frozen=True)
class Record:
    """One VLR or EVLR as its header describes it.

    Attributes
    ----------
    user_id : str
    record_id : int
    start : int
        File offset of the record's header [bytes].
    length : int
        Length of the record's data after its header [bytes].
    """

    user_id: str
    record_id: int
    start: int
    length: int


@dataclass(frozen=True)
class HeaderLayout:
    """What a checked LAS/LAZ header says about the file's structure.

    Attributes
    ----------
    version : str
        ``"1.0"`` to ``"1.4"``.
    file_size : int
        [bytes].
    header_size, offset_to_point_data : int
        [bytes].
    point_format : int
        0–10 (the compression bits removed).
    compressed : bool
    point_record_length : int
        [bytes], at least :data:`POINT_SIZES` of the format.
    point_count : int
        The 64-bit count of LAS 1.4, else the legacy 32-bit count.
    vlrs, evlrs : tuple of Record
        Every one fits in the file (``evlrs`` is empty before LAS 1.4).
    chunk_table : int or None
        LAZ only: the offset of the chunk table lazrs will read [bytes], -1 when there is
        none. It is stored at the start of the point data or, when that says -1 (the
        writer could not seek back), in the file's last 8 bytes.
    chunk_size : int or None
        LAZ only: points per chunk, :data:`VARIABLE_CHUNK_SIZE` for variable-size chunks.
    """

    version: str
    file_size: int
    header_size: int
    offset_to_point_data: int
    point_format: int
    compressed: bool
    point_record_length: int
    point_count: int
    vlrs: tuple[Record, ...]
    evlrs: tuple[Record, ...]
    chunk_table: int | None = None
    chunk_size: int | None = None


def _fail(path: Path, what: str) -> InputError:
    return InputError(f"{path.name}: {what}")


def _corrupt(path: Path, what: str) -> InputError:
    return _fail(path, f"corrupt header: {what}")


def _read(f: BinaryIO, offset: int, n: int) -> bytes:
    f.seek(offset)
    return f.read(n)


def _user_id(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1")


def check_file(path) -> HeaderLayout:
    """:func:`check_header` of ``path`` once it is named and is a regular file.

    Raises
    ------
    InputError
        No path, a folder, a device or pipe, no such file, or a header
        :func:`check_header` refuses.
    """
    p = Path(str(path))
    if not str(path):
        raise InputError("no input file given")
    if not p.is_file():
        if p.is_dir():
            raise _fail(p, "is a folder; give a .las or .laz file")
        raise _fail(p, "not a regular file (a device or pipe)" if p.exists() else "no such file")
    return check_header(p)


def check_header(path) -> HeaderLayout:
    """Check the structure of a LAS/LAZ file before any library parses it.

    Parameters
    ----------
    path : str or Path
        An existing regular file.

    Returns
    -------
    HeaderLayout

    Raises
    ------
    InputError
        Not a LAS/LAZ file, an unsupported version or point format, or a header whose
        sizes, counts or offsets do not fit the file or each other: header size,
        offset to the point data, VLR count and lengths, EVLR start, count and lengths,
        point record length, legacy and 64-bit point counts, the points themselves
        (LAS) and the LAZ chunk table's offset and chunk count.
    """
    p = Path(str(path))
    size = p.stat().st_size
    with open(p, "rb") as f:
        head = f.read(HEADER_SIZES[4])
        if head[:4] != b"LASF":
            raise _fail(p, "not a LAS/LAZ file (it does not start with 'LASF'); give a .las or .laz point cloud")
        if len(head) < 26:
            raise _fail(p, "truncated: the file ends inside the LAS header")
        major, minor = head[24], head[25]
        if major != 1 or minor not in HEADER_SIZES:
            raise _fail(p, f"unsupported LAS version {major}.{minor}; versions 1.0 to 1.4 are read")
        need = HEADER_SIZES[minor]
        if len(head) < need:
            raise _fail(p, f"truncated: the file ends inside the LAS {major}.{minor} header ({size:,} of {need} bytes)")
        layout = _check_public(p, f, head, minor, size)
    return layout


def _check_public(p: Path, f: BinaryIO, head: bytes, minor: int, size: int) -> HeaderLayout:
    """The layout of a file whose signature, version and header length were checked."""
    fields = _PUBLIC.unpack_from(head)
    header_size, offset, n_vlrs, raw_format, record_length, legacy_count = fields[10:16]
    if header_size < HEADER_SIZES[minor]:
        raise _corrupt(p, f"header size {header_size} is below the {HEADER_SIZES[minor]} bytes of a LAS 1.{minor} header")
    if offset > size:
        raise _corrupt(p, f"its point data starts at byte {offset:,}, beyond the end of the file ({size:,} bytes)")
    if offset < header_size:
        raise _corrupt(p, f"its point data starts at byte {offset:,}, inside its {header_size}-byte header")
    if offset > MAX_VLR_AREA:
        raise _corrupt(p, f"its header and VLRs take {offset:,} bytes; at most {MAX_VLR_AREA:,} are read")
    fmt, compressed = raw_format & 0x3F, (raw_format & 0xC0) == 0x80
    if fmt not in POINT_SIZES or raw_format & 0x40:
        raise _fail(p, f"unsupported point format {raw_format}; formats 0 to 10 are read")
    if record_length < POINT_SIZES[fmt]:
        raise _corrupt(p, f"point record length {record_length} is below the {POINT_SIZES[fmt]} bytes of point format {fmt}")
    count, evlrs = legacy_count, ()
    if minor >= 4:
        _, evlr_start, n_evlrs, count = _EXTENDED.unpack_from(head, _PUBLIC.size)[:4]
        saturated = 2**32 - 1 if count >= 2**32 else 0  # what some writers store for a count above 32 bits
        if legacy_count not in (0, count, saturated):
            raise _corrupt(p, f"its legacy point count {legacy_count:,} differs from its point count {count:,}")
        evlrs = _walk_evlrs(p, f, evlr_start, n_evlrs, offset, size)
    vlrs = _walk_vlrs(p, f, header_size, n_vlrs, offset)
    points_end = min((r.start for r in evlrs), default=size)
    layout = HeaderLayout(
        version=f"1.{minor}", file_size=size, header_size=header_size, offset_to_point_data=offset,
        point_format=fmt, compressed=compressed, point_record_length=record_length, point_count=count,
        vlrs=vlrs, evlrs=evlrs,
    )
    if not compressed:
        if offset + count * record_length > points_end:
            have = max(0, (points_end - offset) // record_length)
            raise _fail(p, f"truncated: the header announces {count:,} points but the file holds only {have:,}")
        return layout
    table, chunk_size = _check_laz(p, f, layout, points_end)
    return dataclasses.replace(layout, chunk_table=table, chunk_size=chunk_size)


def _walk_vlrs(p: Path, f: BinaryIO, header_size: int, n: int, offset: int) -> tuple[Record, ...]:
    """Every VLR header between the public header and the point data, each checked to fit."""
    fit = (offset - header_size) // VLR_HEADER_SIZE
    if n > fit:
        raise _corrupt(p, f"it claims {n:,} VLRs but only {fit:,} fit before the point data")
    if n > MAX_VLRS:
        raise _corrupt(p, f"it claims {n:,} VLRs; at most {MAX_VLRS:,} are read")
    records, at = [], header_size
    for i in range(n):
        raw = _read(f, at, VLR_HEADER_SIZE)
        if len(raw) < VLR_HEADER_SIZE or at + VLR_HEADER_SIZE > offset:
            raise _corrupt(p, f"VLR {i + 1} of {n:,} starts at byte {at:,}, past the start of the point data ({offset:,})")
        _, user_id, record_id, length, _ = _VLR.unpack(raw)
        if at + VLR_HEADER_SIZE + length > offset:
            raise _corrupt(p, f"VLR {i + 1} of {n:,} (record length {length:,} bytes) runs past the start of the "
                              f"point data ({offset:,})")
        records.append(Record(_user_id(user_id), record_id, at, length))
        at += VLR_HEADER_SIZE + length
    return tuple(records)


def _walk_evlrs(p: Path, f: BinaryIO, start: int, n: int, offset: int, size: int) -> tuple[Record, ...]:
    """Every EVLR header from ``start`` on (LAS 1.4), each checked to fit in the file."""
    if n == 0:
        return ()  # the start of no EVLRs is often left as 0 or garbage
    if not offset <= start <= size:
        where = "beyond the end of the file" if start > size else "before the point data"
        raise _corrupt(p, f"its EVLRs start at byte {start:,}, {where} (point data at {offset:,}, file {size:,} bytes)")
    fit = (size - start) // EVLR_HEADER_SIZE
    if n > fit:
        raise _corrupt(p, f"it claims {n:,} EVLRs but only {fit:,} fit after byte {start:,}")
    if n > MAX_EVLRS:
        raise _corrupt(p, f"it claims {n:,} EVLRs; at most {MAX_EVLRS:,} are read")
    records, at = [], start
    for i in range(n):
        raw = _read(f, at, EVLR_HEADER_SIZE)
        if len(raw) < EVLR_HEADER_SIZE:
            raise _corrupt(p, f"EVLR {i + 1} of {n:,} starts at byte {at:,}, past the end of the file ({size:,} bytes)")
        _, user_id, record_id, length, _ = _EVLR.unpack(raw)
        if at + EVLR_HEADER_SIZE + length > size:
            raise _corrupt(p, f"EVLR {i + 1} of {n:,} (record length {length:,} bytes) runs past the end of the file "
                              f"({size:,} bytes)")
        records.append(Record(_user_id(user_id), record_id, at, length))
        at += EVLR_HEADER_SIZE + length
    return tuple(records)


def _check_laz(p: Path, f: BinaryIO, layout: HeaderLayout, points_end: int) -> tuple[int, int]:
    """The offset of the chunk table lazrs will read (-1 for none) and the chunk size of
    a LAZ file, after checking its LASzip record and the table's chunk count."""
    laszip = next((r for r in layout.vlrs if (r.user_id, r.record_id) == (LASZIP_USER_ID, LASZIP_RECORD_ID)), None)
    if laszip is None:
        raise _corrupt(p, "its point format says LAZ (compressed) but it has no LASzip record")
    data = _read(f, laszip.start + VLR_HEADER_SIZE, laszip.length)
    if len(data) < _LASZIP.size or len(data) < _LASZIP.size + 6 * _LASZIP.unpack_from(data)[-1]:
        raise _corrupt(p, f"its LASzip record is {len(data)} bytes, too short for what it describes")
    chunk_size, n_items = _LASZIP.unpack_from(data)[6], _LASZIP.unpack_from(data)[-1]
    if chunk_size == 0:
        raise _corrupt(p, "its LASzip record gives a chunk size of 0 points")
    # the items are the parts of a point record; lazrs panics (divides by zero) on none
    item_bytes = sum(struct.unpack_from("<H", data, _LASZIP.size + 6 * i + 2)[0] for i in range(n_items))
    if item_bytes != layout.point_record_length:
        raise _corrupt(p, f"its LASzip record's {n_items} items take {item_bytes} bytes a point, but its point "
                          f"records take {layout.point_record_length}")
    start, size = layout.offset_to_point_data, layout.file_size
    raw = _read(f, start, 8)
    if len(raw) < 8:
        raise _fail(p, "truncated: the file ends before the compressed points")
    (table,) = struct.unpack("<q", raw)
    if table > size - 8:
        raise _fail(p, f"truncated: the LAZ chunk table lies beyond the end of the file (offset {table:,}, "
                       f"file {size:,} bytes)")
    if table != -1 and table < start + 8:
        raise _corrupt(p, f"its LAZ chunk table offset {table:,} lies before its compressed data (byte {start + 8:,})")
    # lazrs takes an offset at or below the data start as "look in the last 8
    # bytes of the file", then allocates what the table there claims; bound that too.
    found = table
    if table == -1 and size >= start + 16:
        (found,) = struct.unpack("<q", _read(f, size - 8, 8))
        if not start < found <= size - 8:
            return table, chunk_size  # none there (lazrs fails to read one): the chunks are read in order
    if found == -1:
        return table, chunk_size
    _, n_chunks = struct.unpack("<II", _read(f, found, 8))  # the table's version, then its count
    n = layout.point_count
    by_points = n + 1 if chunk_size == VARIABLE_CHUNK_SIZE else math.ceil(n / chunk_size) + 1
    most = min(MAX_LAZ_CHUNKS, max(0, found - start - 8), by_points)
    if n_chunks > most:
        raise _corrupt(p, f"its LAZ chunk table claims {n_chunks:,} chunks but at most {most:,} fit its "
                          f"{n:,} points and {max(0, found - start - 8):,} bytes of compressed data")
    if found > points_end:
        raise _corrupt(p, f"its LAZ chunk table at byte {found:,} lies among its EVLRs (from byte {points_end:,})")
    return found, chunk_size


def read_records(path, records, *, user_id: str, extended: bool, budget: int = MAX_VLR_AREA) -> tuple[bytes, int]:
    """The raw bytes (header and data) of the records of one ``user_id``, for a library
    to parse without seeing the others.

    Parameters
    ----------
    path : str or Path
    records : iterable of Record
        From a :class:`HeaderLayout` (already checked to fit the file).
    user_id : str
    extended : bool
        EVLRs (60-byte headers) rather than VLRs (54-byte headers).
    budget : int
        Most bytes read [bytes]; records past it are left out.

    Returns
    -------
    data : bytes
        The records one after the other, as stored.
    count : int
        How many records ``data`` holds.
    """
    head = EVLR_HEADER_SIZE if extended else VLR_HEADER_SIZE
    chunks, used = [], 0
    with open(Path(str(path)), "rb") as f:
        for rec in records:
            if rec.user_id != user_id or used + head + rec.length > budget:
                continue
            chunks.append(_read(f, rec.start, head + rec.length))
            used += head + rec.length
    return b"".join(chunks), len(chunks)
