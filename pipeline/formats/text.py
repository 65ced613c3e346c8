"""Text point files (``.xyz``, ``.txt``, ``.csv``, ``.pts``): one point a line, x y z
in columns separated by spaces, tabs, commas or semicolons.

The columns are named by a header line (``x y z intensity``, CloudCompare's
``//X,Y,Z,R,G,B``), or by the caller (``columns="id,x,y,z"``); without either, the first
three columns are x, y and z. Lines starting with ``#`` are comments. A file whose
first data line holds a single number is taken for a PTS count line and skipped. Read
in chunks of lines (``numpy.loadtxt`` on each), so memory is bounded by the chunk.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from pipeline.formats.source import PointSource, bad, read_line, xyz_columns


def _delimiter(line: str) -> str | None:
    for d in (",", ";", "\t"):
        if d in line:
            return d
    return None  # any run of white space


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _content(fh, path, n: int) -> tuple[str | None, int]:
    """The next line that is not blank or a ``#`` comment (its text, and its number),
    (None, n) at the end of the file."""
    while True:
        raw = read_line(fh, path, n + 1)
        if not raw:
            return None, n
        n += 1
        try:
            line = raw.decode("utf-8").strip()
        except UnicodeDecodeError:
            raise bad(path, f"line {n} is not text (not a LAS, PLY, PCD, E57 or text point file)") from None
        if line and not line.startswith("#"):
            return line, n


def open_text(path, *, columns: str | None = None) -> PointSource:
    """A text point file as a :class:`PointSource`.

    Parameters
    ----------
    path : str or Path
    columns : str, optional
        Comma-separated names of the columns in order (``"x,y,z"``, ``"id,x,y,z,i"``);
        x, y and z must be among them. Overrides a header line.

    Raises
    ------
    InputError
        Not text, no x/y/z columns, a line too long.
    """
    with open(path, "rb") as fh:
        first, n = _content(fh, path, 0)
        if first is None:
            raise bad(path, "holds no points (an empty text file)")
        delim = _delimiter(first.lstrip("/"))
        tokens = first.lstrip("/").split(delim) if delim else first.lstrip("/").split()
        header = not all(_is_number(t) for t in tokens if t.strip())
        start = fh.tell() if header else None
    if columns is not None:
        names = columns.split(",")
        where = "--columns"
    elif header:
        names, where = tokens, "its header line"
    else:
        names, where = ["x", "y", "z"], "the first three columns"
    cols = xyz_columns(names, path, where)
    if not header and len(tokens) < 3 and not (len(tokens) == 1 and columns is None):
        raise bad(path, f"line {n} has {len(tokens)} column(s), not x y z")

    def chunks(chunk_points: int) -> Iterator[np.ndarray]:
        with open(path, "rb") as fh:
            k = 0
            if start is not None:
                fh.seek(start)
                k = n
            pts_count = not header  # a PTS file's first line: the point count alone
            while True:
                lines, first_n = [], None
                while len(lines) < chunk_points:
                    line, k = _content(fh, path, k)
                    if line is None:
                        break
                    if pts_count:
                        pts_count = False
                        if len(line.split()) == 1 and _is_number(line):
                            continue
                    if first_n is None:
                        first_n = k
                    lines.append(line)
                if not lines:
                    return
                yield _parse(lines, path, delim, cols, first_n)
                if len(lines) < chunk_points:
                    return

    return PointSource("text", chunks)


def _parse(lines: list[str], path, delim: str | None, cols: tuple[int, int, int], first_n: int) -> np.ndarray:
    try:
        return np.loadtxt(lines, delimiter=delim, usecols=cols, dtype=np.float64, ndmin=2, comments="#")
    except ValueError:
        pass
    for i, line in enumerate(lines):  # the first bad line, for the message
        try:
            np.loadtxt([line], delimiter=delim, usecols=cols, dtype=np.float64, ndmin=2, comments="#")
        except ValueError:
            shown = line if len(line) <= 60 else line[:60] + "..."
            width = len(line.split(delim) if delim else line.split())
            need = max(cols) + 1
            why = f"it has {width} column(s), x y z need {need}" if width < need else "x, y or z is not a number"
            raise bad(path, f"line {first_n + i} ({shown!r}): {why}") from None
    raise bad(path, f"lines {first_n}-{first_n + len(lines) - 1} could not be read as numbers")

