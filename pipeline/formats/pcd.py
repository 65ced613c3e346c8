"""PCD point files (PCL's format, as ROS's ``pcl_ros`` and most SLAM tools write it):
``DATA ascii``, ``binary`` and ``binary_compressed``, read with ``pypcd4``.

pypcd4 parses the header and gives the row type; a ``binary`` body is then
memory-mapped and an ``ascii`` one read a chunk of lines at a time. A
``binary_compressed`` body (LZF, stored field by field) cannot be streamed: pypcd4
decompresses it whole, after its sizes are checked against the header and
:data:`~pipeline.formats.source.MAX_WHOLE_BYTES`. Organized clouds keep a NaN row for
every beam without a return; the converter drops non-finite rows.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator

import numpy as np

from pipeline.blockinfo import one_line
from pipeline.formats.source import MAX_HEADER_LINES, MAX_WHOLE_BYTES, PointSource, ascii_rows, bad, read_line, xyz_columns

#: values a point may have over all its fields (PCL's widest descriptors have a few hundred)
MAX_VALUES = 4096


def _header(path):
    """pypcd4's MetaData of the file's header, and the offset of the body."""
    from pydantic import ValidationError
    from pypcd4.pypcd4 import MetaData

    lines = []
    with open(path, "rb") as fh:
        for n in range(1, MAX_HEADER_LINES + 1):
            raw = read_line(fh, path, n)
            if not raw:
                raise bad(path, "the PCD header has no DATA line (a truncated or corrupt file)")
            try:
                line = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                raise bad(path, f"line {n} of the PCD header is not text") from None
            if line and not line.startswith("#"):
                lines.append(line)
            if line.startswith("DATA"):
                break
        else:
            raise bad(path, f"the PCD header is longer than {MAX_HEADER_LINES} lines")
        body = fh.tell()
    try:
        meta = MetaData.parse_header(lines)
    except (ValidationError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise bad(path, f"not a valid PCD header ({one_line(exc)})") from None
    if not (len(meta.fields) == len(meta.size) == len(meta.type) == len(meta.count)):
        raise bad(path, "the PCD header's FIELDS, SIZE, TYPE and COUNT lines differ in length")
    # pypcd4 names every value of a field (a COUNT of 10^8 is 10^8 Python strings): the
    # claim is checked before it builds them
    values = sum(int(c) for c in meta.count)
    if values > MAX_VALUES:
        raise bad(path, f"the PCD header's COUNT line claims {values} values a point (more than {MAX_VALUES}; "
                        "a corrupt header)")
    try:
        dtype = meta.build_dtype()
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise bad(path, f"not a valid PCD header ({one_line(exc)})") from None
    return meta, dtype, body


def open_pcd(path) -> PointSource:
    """A PCD file's points as a :class:`PointSource`.

    Raises
    ------
    InputError
        A bad header, no x/y/z field, a point count the file cannot hold, a
        truncated or corrupt body.
    """
    meta, dtype, body = _header(path)
    names = list(dtype.names)
    cols = xyz_columns(names, path, "the PCD FIELDS line")
    xyz = tuple(names[c] for c in cols)
    size = os.path.getsize(path)
    n, data = int(meta.points), meta.data.value
    if data == "binary":
        if n * dtype.itemsize > size - body:
            raise bad(path, f"the PCD header claims {n} points of {dtype.itemsize} bytes, more than its "
                            f"{size - body} bytes of data hold (a truncated or corrupt file)")
        return PointSource("pcd", lambda chunk_points: _binary(path, body, n, dtype, xyz, chunk_points))
    if data == "ascii":
        if n * 2 * len(names) > size - body:
            raise bad(path, f"the PCD header claims {n} points, more than its {size - body} bytes of text hold "
                            "(a truncated or corrupt file)")
        return PointSource("pcd", lambda chunk_points: ascii_rows(path, body, n, cols, chunk_points, fmt="PCD", item="point", items="points"))
    with open(path, "rb") as fh:
        fh.seek(body)
        sizes = fh.read(8)
    if len(sizes) < 8:
        raise bad(path, "the PCD file ends before its compressed data (truncated)")
    packed, unpacked = struct.unpack("<II", sizes)
    if unpacked != n * dtype.itemsize or packed > size - body - 8:
        raise bad(path, f"the PCD compressed data ({packed} bytes, {unpacked} unpacked) does not match its header "
                        f"({n} points of {dtype.itemsize} bytes) or the file's size (truncated or corrupt)")
    if unpacked > MAX_WHOLE_BYTES:
        raise bad(path, f"a binary_compressed PCD is unpacked whole, and this one holds {unpacked >> 20} MB "
                        f"(more than {MAX_WHOLE_BYTES >> 20} MB); save it as binary")
    return PointSource("pcd", lambda chunk_points: _compressed(path, xyz))


def _binary(path, body: int, n: int, dtype, xyz, chunk_points: int) -> Iterator[np.ndarray]:
    if n == 0:
        return
    rows = np.memmap(path, dtype=dtype, mode="r", offset=body, shape=(n,))
    for a in range(0, n, chunk_points):
        part = rows[a : a + chunk_points]
        yield np.column_stack([part[f] for f in xyz]).astype(np.float64)
    del rows


def _compressed(path, xyz) -> Iterator[np.ndarray]:
    from pypcd4 import PointCloud

    try:
        pc = PointCloud.from_path(path)
        data = pc.pc_data
        out = np.column_stack([data[f] for f in xyz]).astype(np.float64)
    except (ValueError, RuntimeError, KeyError, TypeError, struct.error, MemoryError) as exc:
        raise bad(path, f"the PCD compressed data could not be unpacked ({one_line(exc)})") from None
    yield out
