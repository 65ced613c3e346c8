"""A capture of an orchard block as a job: what its job is told, and what is kept of it.

A capture's job is an ordinary job plus the output folder of the block's latest capture
processed before it (``previous``), looked up when the job starts (not when it was
queued: a capture before it may have failed meanwhile); the job registers its trees to
that capture's and writes the block's cumulative ``history.parquet`` (see
docs/orchard-blocks.md). After it is done, `capture_record` reads what its outputs say of the
capture (date, registration, counts), which the store keeps with the capture.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq

from service.db.jobstore import Store
from service.db.orchard_blocks import arrival_date
from service.jobfolders import job_dir
from service.settings import Settings
from workers.jobspec import JobSpec

log = logging.getLogger("orchard.runner")

#: the outputs' file with a block's history (one row per tree per capture)
HISTORY = "history.parquet"
#: the schema metadata key of ``trees.parquet`` that holds a capture's record
CAPTURE_METADATA = b"orchard:capture"


def capture_job_fields(store: Store, settings: Settings, job: dict[str, Any]) -> dict[str, Any]:
    """The `workers.jobspec.JobSpec` fields of a capture's job (empty for any other job):
    ``previous`` (the output folder of the block's latest capture done before this one,
    or None for its first), ``capture_id``, ``captured_at`` (the date its sender gave)
    and ``captured_at_fallback`` (the day its file arrived)."""
    capture = store.orchard_blocks.capture_of_job(job["tenant_id"], job["id"])
    if capture is None:
        return {}
    before = store.orchard_blocks.latest_done_capture(capture["tenant_id"], capture["orchard_block_id"], before_seq=capture["seq"])
    return {
        "previous": str(job_dir(settings, before["job_id"]).absolute()) if before is not None else None,
        "capture_id": capture["id"],
        "captured_at": capture["given_captured_at"],
        "captured_at_fallback": arrival_date(capture["arrived_at"]),
    }


def spec_fields(fields: dict[str, Any]) -> dict[str, Any]:
    """``fields`` that `JobSpec` has; the others are left out with a warning (a worker
    package from before captures: the capture is processed as a job of its own)."""
    known = {f.name for f in dataclasses.fields(JobSpec)}
    missing = sorted(set(fields) - known)
    if missing:
        log.warning("this version of workers.jobspec.JobSpec has no %s: the capture is processed without its previous one",
                    ", ".join(missing))
    return {k: v for k, v in fields.items() if k in known}


def capture_record(out_dir: Path) -> dict[str, Any] | None:
    """What a finished capture job's outputs say of the capture: the ``orchard:capture``
    record (``capture_id``, ``captured_at`` and its source, ``previous_capture_id``,
    ``registration``, ``counts``, ``next_tree_key``); None when they say nothing.

    The one call of `workers.seasons.capture_record`; before that module exists, the
    record is read from ``trees.parquet``'s schema metadata, where it writes it.
    """
    try:  # here: workers.seasons costs the server's start ~0.5 s, and may be missing from an older worker package
        from workers.seasons import capture_record as read_record
    except ImportError:
        read_record = _metadata_record
    try:
        return read_record(out_dir) or None
    except Exception as exc:  # noqa: BLE001 - the job's results stand without the record
        log.warning("capture outputs in %s have no readable record: %s", out_dir, exc)
        return None


def _metadata_record(out_dir: Path) -> dict[str, Any] | None:
    path = Path(out_dir) / "trees.parquet"
    if not path.is_file():
        return None
    raw = (pq.read_schema(str(path)).metadata or {}).get(CAPTURE_METADATA)
    return json.loads(raw) if raw else None
