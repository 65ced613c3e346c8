"""PDAL's readers of the same formats, as an alternative to the project's own
(``orchard convert --reader pdal``): ``readers.ply``, ``readers.pcd`` (ascii and binary:
PDAL 2.8 refuses binary_compressed), ``readers.text`` and ``readers.e57`` when PDAL was
built with that plugin. For a site whose captures already go through PDAL pipelines;
the points are the same (tests/pipeline/test_formats.py checks it where PDAL is).
Streamed through python-pdal's ``Pipeline.iterator``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import numpy as np

from pipeline.blockinfo import one_line
from pipeline.errors import ParameterError
from pipeline.formats.source import PointSource, bad

READERS = {"ply": "readers.ply", "pcd": "readers.pcd", "e57": "readers.e57", "text": "readers.text"}


def open_with_pdal(path, fmt: str, *, columns: str | None = None) -> PointSource:
    """A point file read by PDAL's reader of ``fmt``, as a :class:`PointSource`.

    Raises
    ------
    ParameterError
        PDAL's Python bindings do not import, or PDAL has no reader of the format.
    """
    try:
        import pdal
    except Exception:  # noqa: BLE001 - any failure to load the bindings
        raise ParameterError("the PDAL readers need PDAL's Python bindings (import pdal failed); "
                             "use the project's own readers") from None
    stage = {"type": READERS[fmt], "filename": str(path)}
    if fmt == "text" and columns is not None:
        names = [c.strip().upper() if c.strip().lower() in "xyz" else c.strip() or f"skip{i}" for i, c in enumerate(columns.split(","))]
        with open(path, "rb") as fh:
            first = fh.readline(1 << 16).decode("utf-8", "replace")
        sep = next((d for d in (",", ";", "\t") if d in first), " ")
        stage.update(header=sep.join(names), separator=sep)
    try:
        pipeline = pdal.Pipeline(json.dumps({"pipeline": [stage]}))
    except RuntimeError as exc:
        raise ParameterError(f"PDAL cannot read {fmt.upper()} here ({one_line(exc)})") from None

    def chunks(chunk_points: int) -> Iterator[np.ndarray]:
        try:
            for arr in pipeline.iterator(chunk_size=int(chunk_points)):
                yield np.column_stack([arr["X"], arr["Y"], arr["Z"]]).astype(np.float64)
        except RuntimeError as exc:
            raise bad(path, f"PDAL's {READERS[fmt]} could not read it ({one_line(exc)})") from None

    return PointSource(fmt, chunks)
