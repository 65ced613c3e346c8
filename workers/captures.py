"""Which capture of an orchard block a job processes: its id, date and where the date
came from, and the previous capture's output folder (:mod:`workers.seasons` registers
onto it); the checks made when a job is specified, and the record a finished capture
leaves in its ``trees.parquet``. Light to import: no scipy, no pyarrow until a record is read.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from datetime import date, datetime, timezone
from pathlib import Path

from pipeline.blockinfo import creation_date
from pipeline.errors import InputError, ParameterError

#: trees.parquet metadata: the capture's record (JSON)
CAPTURE_KEY = "orchard:capture"


@dataclass(frozen=True)
class Capture:
    """Which capture a job processes: its id, its date and where the date came from
    (``file``: the LAS header's creation day; ``given``; ``upload``: the caller's
    fallback, else the file's modification day), and the previous capture's output folder."""

    capture_id: str
    captured_at: str
    captured_at_source: str
    previous: str | None = None

    @classmethod
    def of(cls, input_path: str) -> Capture:
        """A first capture named after its file (a job given no capture)."""
        return resolve_capture(input_path)


def resolve_capture(input_path: str, *, capture_id: str | None = None, captured_at: str | None = None,
                    captured_at_fallback: str | None = None, previous: str | None = None) -> Capture:
    """The capture of a job (its id defaults to the input's file stem)."""
    cid = capture_id or Path(input_path).stem
    found = creation_date(input_path)
    if found is not None:
        return Capture(cid, found, "file", previous)
    if captured_at is not None:
        return Capture(cid, check_date(captured_at, "job.captured_at"), "given", previous)
    if captured_at_fallback is not None:
        return Capture(cid, check_date(captured_at_fallback, "job.captured_at_fallback"), "upload", previous)
    mtime = datetime.fromtimestamp(os.path.getmtime(input_path), tz=timezone.utc).date().isoformat()
    return Capture(cid, mtime, "upload", previous)


def capture_of(spec) -> Capture:
    """The capture a :class:`workers.jobspec.JobSpec` processes."""
    return resolve_capture(spec.input_path, capture_id=spec.capture_id, captured_at=spec.captured_at,
                           captured_at_fallback=spec.captured_at_fallback, previous=spec.previous)


def check_date(value: str, param: str) -> str:
    """``value`` as an ISO date ``YYYY-MM-DD`` (ParameterError otherwise)."""
    try:
        return date.fromisoformat(str(value)[:10]).isoformat()
    except ValueError:
        raise ParameterError(f"{{{param}}} {value!r} is not a date (YYYY-MM-DD)", param=param, value=value) from None


def check_previous(previous: str) -> str:
    """The absolute path of a previous capture's output folder (ParameterError unless it holds ``trees.parquet``)."""
    path = os.path.abspath(os.fspath(previous))
    if not os.path.isfile(os.path.join(path, "trees.parquet")):
        raise ParameterError(f"{{job.previous}} {previous} is no output folder of a processed capture (no trees.parquet)",
                             param="job.previous", value=str(previous))
    return path


def capture_record(out_dir) -> dict:
    """The ``orchard:capture`` record of a finished job's outputs in ``out_dir``.

    Raises InputError when the folder holds no trees.parquet with a capture record.
    """
    from pipeline.parquet import read_parquet_columns  # pyarrow: only when a record is read

    _, meta = read_parquet_columns(Path(out_dir) / "trees.parquet", [], what=f"trees.parquet of {out_dir}")
    raw = meta.get(CAPTURE_KEY.encode())
    if raw is None:
        raise InputError(f"trees.parquet of {out_dir} holds no capture record (written before captures were recorded)")
    return json.loads(raw)
