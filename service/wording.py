"""Domain errors worded at the two edges: the command line and the API.

A domain error (`pipeline.errors.OrchardError`) names parameters by their path in the
job's parameters (``tiling.tile_size``, ``trunks.cluster_radius``, ``job.work_dir``), and
how to list a kind of resource as ``list.<kind>`` (``list.schedules``).
The command line words a path as its option (``--tile-size``,
``--trunks-cluster-radius``, ``--work``), the API as its request field
(``tiling.tile_size``, ``params.trunks.cluster_radius``) and, for the response's
``errors``, as its location in the body (``["body", "tiling", "tile_size"]``).
Neither edge reads the other's words. This module imports no HTTP framework: the job
runner and the command line use it.
"""

from __future__ import annotations

import errno
import math
import sqlite3
from collections.abc import Sequence
from pathlib import Path

from pipeline.errors import OrchardError

#: settings of a run that are not parameters: their option, and the service setting
#: that stands for them (None: the service has none, the path is said as it is)
_RUN = {
    "input_path": ("INPUT", None),
    "out_dir": ("--out", None),
    "work_dir": ("--work", "ORCHARD_WORK_DIR"),
    "resume": ("--resume", None),
    "rerun_tile": ("--rerun-tile", None),
    "scheduler": ("--scheduler", "ORCHARD_SCHEDULER"),
    "previous": ("--previous", None),
    "captured_at": ("--captured-on", None),
    "captured_at_fallback": ("the file's modification day", None),
}

#: how to list a kind of resource, said by each edge: (command line, API)
_LISTS = {
    "blocks": ("list yours with GET /v1/blocks", "list yours with GET /v1/blocks"),  # the API alone lists them
    "jobs": ("list yours with GET /v1/jobs", "list yours with GET /v1/jobs"),
    "schedules": ("list them with 'orchard schedules list'", "list yours with GET /v1/schedules"),
    "webhooks": ("list yours with GET /v1/webhooks", "list yours with GET /v1/webhooks"),  # the API alone lists them
    "orchard_blocks": ("list them with 'orchard blocks list'", "list yours with GET /v1/orchard-blocks"),
}

#: tiling fields that are no option of the command line
_NOT_OPTIONS = {"chunk_points"}

#: the fields of `TilingParams` that a job or schedule request sets (the service's
#: settings give the others)
REQUEST_TILING = ("tile_size", "buffer")

#: tiling fields the service takes from its settings
_TILING_SETTINGS = {"workers": "ORCHARD_N_WORKERS", "worker_memory": "ORCHARD_WORKER_MEMORY_GB"}


def _split(path: str | Sequence) -> tuple[str, ...]:
    parts = tuple(str(p) for p in (path.split(".") if isinstance(path, str) else path))
    parts = tuple(p for p in parts if p != "__root__")
    while parts[:1] in (("body",), ("pipeline",), ("params",)):
        parts = parts[1:]  # a request body's, or a job model's, nesting
    return parts


def _groups() -> set[str]:
    from pipeline.params import GROUPS  # here: pydantic (~0.3 s) would be a cost of every `orchard --help`

    return set(GROUPS)


def cli_name(path: str | Sequence) -> str | None:
    """The command line's option for a parameter path (``tiling.tile_size`` →
    ``--tile-size``, ``trunks.cluster_radius`` → ``--trunks-cluster-radius``,
    ``job.work_dir`` → ``--work``); None for a path that is no option."""
    parts = _split(path)
    if len(parts) == 2 and parts[0] == "job" and parts[1] in _RUN:
        return _RUN[parts[1]][0]
    if len(parts) == 2 and parts[0] == "list" and parts[1] in _LISTS:
        return _LISTS[parts[1]][0]
    if len(parts) == 2 and parts[0] == "tiling" and parts[1] not in _NOT_OPTIONS:
        return "--" + parts[1].replace("_", "-")
    if len(parts) == 2 and parts[0] in _groups():
        return f"--{parts[0]}-{parts[1]}".replace("_", "-")
    if len(parts) == 1 and parts[0] not in _groups() and parts[0] != "tiling":
        return "--" + parts[0].replace("_", "-")  # a top-level option (a schedule's --cron)
    return None


def api_location(path: str | Sequence) -> list[str] | None:
    """Where a parameter lies in a request body (``["body", "tiling", "tile_size"]``,
    ``["body", "params", "trunks", "cluster_radius"]``); None when it is none of the
    body's fields."""
    parts = _split(path)
    if len(parts) == 2 and parts[0] == "tiling" and parts[1] in REQUEST_TILING:
        return ["body", *parts]
    if len(parts) == 2 and parts[0] in _groups():
        return ["body", "params", *parts]
    return None


def api_name(path: str | Sequence) -> str | None:
    """The API's words for a parameter path: its request field (``tiling.buffer``,
    ``params.segment.max_crown_radius``), or the service setting that stands for a
    run's setting (``ORCHARD_WORK_DIR``); None for a path said as it is."""
    loc = api_location(path)
    if loc is not None:
        return ".".join(loc[1:])
    parts = _split(path)
    if len(parts) == 2 and parts[0] == "job" and parts[1] in _RUN:
        return _RUN[parts[1]][1]
    if len(parts) == 2 and parts[0] == "list" and parts[1] in _LISTS:
        return _LISTS[parts[1]][1]
    if len(parts) == 2 and parts[0] == "tiling":
        return _TILING_SETTINGS.get(parts[1])
    return None


def cli_words(exc: OrchardError) -> str:
    """A domain error as the command line says it."""
    return exc.render(cli_name)


def api_words(exc: OrchardError, *, hint: bool = True, block_path: str | None = None, filename: str | None = None) -> str:
    """A domain error as the API says it; with ``block_path``, the block is named by the
    file name it was uploaded as (``filename``), not by the server's stored file.
    ``hint`` False leaves out the command line's advice of a stopped run (the service
    never resumes a job)."""
    message = exc.render(api_name, hint=hint)
    if block_path:
        name = filename or "the block"
        message = message.replace(str(block_path), name).replace(Path(block_path).name, name)
    return message


def api_errors(exc: OrchardError) -> list[dict] | None:
    """The ``errors`` of an API response to ``exc``: the field at fault with its
    location in the body, value and limit (None when it names no body field)."""
    loc = api_location(exc.param) if exc.param else None
    if loc is None:
        return None
    error = {"loc": loc, "msg": api_words(exc), "type": "parameter"}
    for key, value in (("input", exc.value), ("limit", exc.limit)):
        if isinstance(value, (int, float)) and math.isfinite(value):
            error[key] = value
    return [error]


def validation_words(errors: list[dict], name=cli_name) -> list[str]:
    """pydantic validation errors as ``<option>: <message>`` (``name`` words a
    location; one it does not know is said dotted)."""
    parts = []
    for e in errors:
        loc = tuple(str(p) for p in e.get("loc", ()) if p != "__root__")
        where = (name(loc) if loc else None) or ".".join(loc)
        msg = e.get("msg", "invalid value")
        parts.append(f"{where}: {msg}" if where else msg)
    return parts


#: errno values of a full disk or an exhausted quota
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


def disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` says the disk (or the quota) is full: an OSError's errno, or
    SQLite's "database or disk is full" (the machine's trouble, not the user's)."""
    if isinstance(exc, sqlite3.OperationalError):
        return "disk is full" in str(exc)
    return isinstance(exc, OSError) and exc.errno in DISK_FULL
