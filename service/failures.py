"""What a job's failure means, sorted by the exception's class: :func:`classify`.

Exceptions in, outcomes out: `classify` is told what a run raised and answers what
kind of failure it is, whether the job is worth another attempt, whether the dask
client is to be replaced and whether the traceback belongs in the log. It runs
nothing and touches no store; the runner (:mod:`service.runner`) acts on its answer,
and the job store keeps the outcome's ``kind`` and ``fields`` as they are. Each edge
words them (:func:`service.wording.failure_words`): nothing here is a sentence.

Classes, most specific first (a cancel wins over everything but a domain error, which
the job raised itself):

- ``cancelled``: `workers.stops.JobCancelled`, a plain future's `CancelledError`, or
  anything but a domain error once the job's cancel was set;
- ``exit``: `KeyboardInterrupt` and `SystemExit` go on up (the process is stopping);
- a domain error (`pipeline.errors.OrchardError`) by its class: ``tile_failed``,
  ``cluster_lost`` (retried: the cluster failed, not the job), ``no_trees``, ``input``,
  ``parameter``, else ``error``; its fields are the error's own;
- ``cluster_unavailable`` (`ClusterUnavailable`; retried);
- ``disk_full``: an OSError of a full disk or quota, SQLite's full database (retried);
- ``scheduler_lost``: distributed's `CommClosedError` and its cancelled futures
  (retried; the client is replaced);
- ``internal``: anything else (logged with its traceback).
"""

from __future__ import annotations

import math
import numbers
from asyncio import CancelledError as TaskCancelled
from concurrent.futures import CancelledError as FutureCancelled
from dataclasses import dataclass, field
from typing import Any

from pipeline.errors import InputError, NoTreesError, OrchardError, ParameterError
from service.wording import disk_full
from workers.stops import ClusterLost, JobCancelled, Stopped, TileFailed

#: longest ``detail`` an outcome keeps of an exception's own text [characters]
DETAIL_CHARS = 300


class ClusterUnavailable(RuntimeError):
    """The dask cluster could not be started or reached (the job fails; the next one
    tries again): ``where`` it was looked for, ``why`` it could not be reached."""

    def __init__(self, where: str, why: str) -> None:
        super().__init__(f"cannot start or reach the dask cluster ({where}): {why}")
        self.where, self.why = where, why


@dataclass(frozen=True)
class Outcome:
    """What a failure means to the runner.

    Attributes
    ----------
    kind : str
        The failure's kind (the module's list), kept by the store.
    fields : dict
        JSON-safe structured fields the edges word it from.
    retry : bool
        The cluster or the server failed, not the job: worth another attempt.
    reconnect : bool
        The dask client lost its scheduler: the next job starts a new one.
    log : {None, "line", "traceback"}
        What the service's log says of it: nothing, one line (the operator must act),
        or the traceback (unexpected).
    """

    kind: str
    fields: dict[str, Any] = field(default_factory=dict)
    retry: bool = False
    reconnect: bool = False
    log: str | None = None


#: a domain error's kind by its class, most specific first
DOMAIN_KINDS: tuple[tuple[type[OrchardError], str], ...] = (
    (TileFailed, "tile_failed"),
    (ClusterLost, "cluster_lost"),
    (JobCancelled, "cancelled"),
    (NoTreesError, "no_trees"),
    (InputError, "input"),
    (ParameterError, "parameter"),
    (OrchardError, "error"),
)

#: the kinds whose job is queued again while it has attempts left
RETRIED = frozenset({"cluster_lost", "cluster_unavailable", "disk_full", "scheduler_lost"})


def classify(exc: BaseException, *, cancelled: bool = False) -> Outcome:
    """The outcome of a job whose run raised ``exc``; ``cancelled``: its cancel was set
    meanwhile (then anything but a domain error is the cancel's doing)."""
    if isinstance(exc, JobCancelled) or (cancelled and not isinstance(exc, OrchardError)):
        return Outcome("cancelled")
    if isinstance(exc, (KeyboardInterrupt, SystemExit)):
        return Outcome("exit")
    if isinstance(exc, OrchardError):
        kind = next(k for cls, k in DOMAIN_KINDS if isinstance(exc, cls))
        return Outcome(kind, domain_fields(exc), retry=kind in RETRIED)
    if isinstance(exc, ClusterUnavailable):
        return Outcome("cluster_unavailable", {"where": exc.where, "detail": exc.why}, retry=True)
    if disk_full(exc):
        return Outcome("disk_full", {"detail": short_text(exc)}, retry=True, log="line")
    if isinstance(exc, _scheduler_lost()):
        return Outcome("scheduler_lost", {"exception": type(exc).__name__}, retry=True, reconnect=True)
    if isinstance(exc, (FutureCancelled, TaskCancelled)):
        return Outcome("cancelled")
    return Outcome("internal", {"exception": type(exc).__name__, "detail": short_text(exc)}, log="traceback")


def _scheduler_lost() -> tuple[type[BaseException], ...]:
    """distributed's classes of a lost scheduler: the connection closed under a gather,
    and the futures it cancelled then."""
    # imported at a failure, not with this module: distributed adds 1.5-2.6 s (python -X
    # importtime, on the shared two-core machine) to every process importing the runner,
    # the API's too, which otherwise never imports it
    from distributed.client import FutureCancelledError, FuturesCancelledError
    from distributed.comm.core import CommClosedError

    return CommClosedError, FuturesCancelledError, FutureCancelledError


def domain_fields(exc: OrchardError) -> dict[str, Any]:
    """A domain error's fields as the store keeps them: its message and hint with their
    ``{path}`` placeholders unworded, the parameter, value and limit, the tile of a
    failed tile, and whether the run stopped with a work store to resume (``stopped``:
    the hint is then the command line's advice, which no service job can follow)."""
    fields: dict[str, Any] = {"class": type(exc).__name__, "message": exc.message, "hint": exc.hint}
    for key in ("param", "value", "limit"):
        value = _json_safe(getattr(exc, key))
        if value is not None:
            fields[key] = value
    if isinstance(exc, TileFailed):
        fields["tile_id"] = int(exc.tile_id)
    if isinstance(exc, Stopped):
        fields["stopped"] = True
    return fields


def _json_safe(value: Any) -> Any:
    """``value`` as JSON keeps it exactly: finite numbers, strings, lists of them; else None."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, (tuple, list)):
        items = [_json_safe(v) for v in value]
        return None if any(v is None for v in items) else items
    return None


def short_text(text: object, limit: int = DETAIL_CHARS) -> str:
    """``text`` on one line, cut to ``limit`` characters (an error's detail)."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."
