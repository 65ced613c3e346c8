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
import time
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


#: how the edges of the service word a job's failure that is no domain error, by its
#: kind (`service.failures.classify`): the message, from the failure's fields
_FAILURES = {
    "cancelled": "cancelled on request",
    "crashed": "the service stopped {crashes} times while running this job; it is not retried (it may be what stops "
               "the service: see the service log; submit it again to retry)",
    "cluster_unavailable": "cannot start or reach the dask cluster ({where}): {detail}",
    "disk_full": "the server ran out of disk space during the job",
    "scheduler_lost": "lost the connection to the dask scheduler during the job",
    "internal": "internal error ({exception}): {detail}",
    "unrecorded": "internal error ({exception}) while recording the job's outcome; see the service log",
}

#: what to do after a retried job's last attempt failed, by kind
_LAST_ADVICE = {
    "cluster_lost": "; start dask workers and submit the job again",
    "disk_full": "; free disk space on the server and submit it again",
    "scheduler_lost": "; submit it again once the cluster is back",
}


def failure_words(kind: str, fields: dict, *, name=api_name) -> str:
    """A job's failure, kept by the store as its ``kind`` and ``fields``
    (`service.failures`), as an edge says it: ``name`` words a parameter (`api_name`,
    `cli_name`).

    A domain error's message is rendered with its parameters worded, the block's stored
    file named by the name it arrived as (``block_path``, ``block_name``), and without
    the command line's advice of a stopped run (the service never resumes a job). A
    retried failure says its attempt: ``retry_at`` (epoch seconds) when it is queued
    again, else the last attempt's advice."""
    if kind in _FAILURES:
        if kind == "cancelled" and fields.get("before_start"):
            return "cancelled before it started"
        text = _FAILURES[kind].format_map({k: fields.get(k, "") for k in ("where", "detail", "exception", "crashes")})
    else:
        exc = OrchardError(fields.get("message", ""), hint=fields.get("hint", ""))
        text = exc.render(name, hint=not fields.get("stopped")) or fields.get("class", kind)
        if fields.get("block_path"):
            block_name = fields.get("block_name") or "the block"
            text = text.replace(fields["block_path"], block_name).replace(Path(fields["block_path"]).name, block_name)
    attempt = fields.get("attempt")
    if attempt is None:
        return text
    if fields.get("retry_at") is not None:
        when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(fields["retry_at"]))
        return f"attempt {attempt} of {fields.get('attempts', attempt)} failed: {text}; trying again from {when}"
    tries = f" (attempt {attempt}, the last)" if attempt > 1 else ""
    return text + tries + _LAST_ADVICE.get(kind, "")


def job_error(rec: dict, *, name=api_name, prefix: str = "") -> str | None:
    """A stored job's error as an edge says it: its failure (``error_kind`` and
    ``error_fields``, `failure_words`), else the note the store keeps as text (a
    running job waiting for workers, a job cancelled before it started), else None.
    ``prefix``: the columns' prefix in a joined record (``job_``)."""
    kind = rec.get(prefix + "error_kind")
    if kind:
        return failure_words(kind, rec.get(prefix + "error_fields") or {}, name=name)
    return rec.get(prefix + "error")


#: errno values of a full disk or an exhausted quota
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


def disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` says the disk (or the quota) is full: an OSError's errno, or
    SQLite's "database or disk is full" (the machine's trouble, not the user's)."""
    if isinstance(exc, sqlite3.OperationalError):
        return "disk is full" in str(exc)
    return isinstance(exc, OSError) and exc.errno in DISK_FULL
