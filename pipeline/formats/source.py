"""What every reader of a non-LAS format gives: a :class:`PointSource` (the points in
chunks, a CRS if the file has one), and the limits a reader checks before it allocates.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import InputError

#: points per chunk a reader yields (bounds memory: a few tens of MB a chunk)
CHUNK_POINTS = 1_000_000
#: longest line of a text file or of a text header [bytes]; a line longer than this is
#: refused rather than read whole
MAX_LINE = 1 << 16
#: most header lines of a PLY or PCD file
MAX_HEADER_LINES = 1000
#: most bytes a reader may hold whole when its format cannot be streamed (a PCD's
#: binary_compressed body, a PLY element of list properties)
MAX_WHOLE_BYTES = 2 << 30


@dataclass
class PointSource:
    """Points of a file, read in chunks.

    Attributes
    ----------
    format : str
        ``"ply"``, ``"pcd"``, ``"e57"`` or ``"text"``.
    chunks : callable
        ``chunks(chunk_points)`` yields (m, 3) float64 arrays of x, y, z [file units],
        in file order; non-finite rows are passed on (the converter drops them).
    crs_wkt : str or None
        The CRS the file states, if any.
    """

    format: str
    chunks: Callable[[int], Iterator[np.ndarray]]
    crs_wkt: str | None = None


def bad(path, what: str) -> InputError:
    """An InputError naming the file (its base name) and what is wrong."""
    return InputError(f"{Path(str(path)).name}: {what}")


def read_line(fh, path, n: int) -> bytes:
    """Line ``n`` (counted from 1, for the message) of a binary file, at most
    :data:`MAX_LINE` bytes; b"" at the end of the file."""
    line = fh.readline(MAX_LINE + 1)
    if len(line) > MAX_LINE:
        raise bad(path, f"line {n} is longer than {MAX_LINE} bytes: not a point file of this format, or corrupt")
    return line


def xyz_columns(names: list[str], path, where: str) -> tuple[int, int, int]:
    """Positions of x, y and z in ``names`` (any case)."""
    low = [n.strip().lower() for n in names]
    missing = [c for c in "xyz" if c not in low]
    if missing:
        raise bad(path, f"{where} has no {', '.join(missing)} (it has {', '.join(names[:12]) or 'nothing'})")
    return low.index("x"), low.index("y"), low.index("z")


def ascii_rows(path, body: int, n: int, cols, chunk_points: int, *, fmt: str, item: str, items: str) -> Iterator[np.ndarray]:
    """(m, 3) float64 chunks of the ``n`` text rows from byte ``body`` on, columns ``cols``
    (an ascii PLY's vertices, an ascii PCD's points); InputError naming ``fmt`` and
    ``item`` for a file that ends early, a row that is not numbers, or a blank row."""
    with open(path, "rb") as fh:
        fh.seek(body)
        done = 0
        while done < n:
            lines = []
            for _ in range(min(chunk_points, n - done)):
                line = read_line(fh, path, done + len(lines) + 1)
                if not line:
                    raise bad(path, f"the {fmt} file ends after {done + len(lines)} of its {n} {items} (truncated)")
                lines.append(line)
            try:
                xyz = np.loadtxt([ln.decode("ascii") for ln in lines], usecols=cols, dtype=np.float64, ndmin=2)
            except (ValueError, UnicodeDecodeError):
                raise bad(path, f"a {fmt} {item} among rows {done + 1}-{done + len(lines)} is not a row of numbers") from None
            if len(xyz) != len(lines):  # (loadtxt passes over blank lines)
                raise bad(path, f"a {fmt} {item} among rows {done + 1}-{done + len(lines)} is a blank line (a corrupt file)")
            done += len(lines)
            yield xyz
