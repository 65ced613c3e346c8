"""PLY point files (binary little/big endian and ascii), read with ``plyfile``.

plyfile parses the header; the ``vertex`` element's x, y, z are then read in chunks: a
binary body memory-mapped (``numpy.memmap`` of plyfile's row type), an ascii body a
chunk of lines at a time. Elements of list properties before the vertices, or lists
among the vertex properties, cannot be streamed: such a file is read whole by plyfile,
up to :data:`~pipeline.formats.source.MAX_WHOLE_BYTES`. Every element count the header
claims is checked against the file's size before anything is allocated.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np

from pipeline.blockinfo import one_line
from pipeline.formats.source import MAX_HEADER_LINES, MAX_WHOLE_BYTES, PointSource, ascii_rows, bad, read_line, xyz_columns


def _header(path):
    """plyfile's parsed header (elements, no data) and the offset of the body."""
    from plyfile import PlyData, PlyParseError

    with open(path, "rb") as fh:
        for n in range(1, MAX_HEADER_LINES + 1):  # plyfile reads header lines unbounded: look first
            line = read_line(fh, path, n)
            if not line:
                raise bad(path, "the PLY header has no end_header line (a truncated or corrupt file)")
            if line.strip() == b"end_header":
                break
        else:
            raise bad(path, f"the PLY header is longer than {MAX_HEADER_LINES} lines")
        fh.seek(0)
        try:
            # plyfile's own first step of PlyData.read: the header alone, nothing allocated
            meta = PlyData._parse_header(fh)
        except (PlyParseError, ValueError, UnicodeDecodeError) as exc:
            raise bad(path, f"not a valid PLY header ({one_line(exc)})") from None
        return meta, fh.tell()


def _min_row_bytes(element, text: bool) -> int:
    """Fewest bytes a row of ``element`` takes in the file."""
    from plyfile import PlyListProperty

    if text:
        return 2 * max(len(element.properties), 1)  # a digit and a separator per property
    total = 0
    for p in element.properties:
        total += np.dtype(p.list_dtype()[0]).itemsize if isinstance(p, PlyListProperty) else np.dtype(p.dtype()).itemsize
    return max(total, 1)


def open_ply(path) -> PointSource:
    """A PLY file's vertices as a :class:`PointSource`.

    Raises
    ------
    InputError
        A bad header, no vertex element or no x/y/z, counts the file's size cannot
        hold, a truncated body.
    """
    from plyfile import PlyListProperty

    meta, body = _header(path)
    size = os.path.getsize(path)
    names = [e.name for e in meta.elements]
    if "vertex" not in names:
        raise bad(path, f"the PLY file has no vertex element (it has {', '.join(names) or 'none'})")
    need = 0
    for e in meta.elements:
        need += e.count * _min_row_bytes(e, meta.text)
        if need > size - body:
            raise bad(path, f"the PLY header claims {e.count} {e.name} rows, more than its {size - body} bytes of data hold "
                            "(a truncated or corrupt file)")
    vertex = meta["vertex"]
    props = [p.name for p in vertex.properties]
    cols = xyz_columns(props, path, "the PLY vertex element")
    first = names.index("vertex") == 0
    lists = any(isinstance(p, PlyListProperty) for p in vertex.properties)
    if not first or lists:
        xyz = tuple(props[c] for c in cols)
        return PointSource("ply", lambda chunk_points: _whole(path, size, xyz))
    count = vertex.count
    if meta.text:
        return PointSource("ply", lambda chunk_points: ascii_rows(path, body, count, cols, chunk_points, fmt="PLY", item="vertex", items="vertices"))
    dtype = vertex.dtype(meta.byte_order)
    return PointSource("ply", lambda chunk_points: _binary(path, body, count, dtype, props, cols, chunk_points))


def _binary(path, body: int, count: int, dtype: np.dtype, props, cols, chunk_points: int) -> Iterator[np.ndarray]:
    if count == 0:
        return
    rows = np.memmap(path, dtype=dtype, mode="r", offset=body, shape=(count,))
    x, y, z = (props[c] for c in cols)
    for a in range(0, count, chunk_points):
        part = rows[a : a + chunk_points]
        yield np.column_stack([part[x], part[y], part[z]]).astype(np.float64)
    del rows


def _whole(path, size: int, names: tuple[str, str, str]) -> Iterator[np.ndarray]:
    from plyfile import PlyData, PlyParseError

    if size > MAX_WHOLE_BYTES:
        raise bad(path, f"a PLY file of other elements before its vertices, or of list properties among them, is read "
                        f"whole, and this one is larger than {MAX_WHOLE_BYTES >> 20} MB; write the vertices alone")
    try:
        data = PlyData.read(str(path))
        v = data["vertex"].data
        xyz = np.column_stack([v[n] for n in names]).astype(np.float64)
    except (PlyParseError, ValueError, KeyError, IndexError, UnicodeDecodeError, MemoryError) as exc:
        raise bad(path, f"the PLY data could not be read ({one_line(exc)})") from None
    yield xyz
