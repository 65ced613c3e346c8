"""What a job or schedule request sets, checked by the job model into what the job store
keeps. The API's bodies and the command line's options both come here: no HTTP."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pipeline.jobparams import JobParams, TilingParams
from pipeline.params import PipelineParams
from service.schedules import next_run_time, validate_cron
from service.wording import REQUEST_TILING


def stored_tiling(params: PipelineParams, tiling: dict | None) -> dict | None:
    """A request's ``tiling`` (its `REQUEST_TILING` fields; None: one tile) as the store
    keeps it, checked by the job model with ``params``: pydantic's ValidationError for a
    field out of its bounds, ParameterError for a buffer below the parameters' reach or
    tiles so small that each point would be copied into too many of them."""
    if tiling is None:
        return None
    model = TilingParams(**tiling)
    JobParams(pipeline=params, tiling=model)
    return model.model_dump(include=set(REQUEST_TILING))


def schedule_changes(sched: dict, given: dict[str, Any], *, now: datetime | None = None) -> dict[str, Any]:
    """The store changes that set ``given`` on the schedule ``sched``, checked as at its
    creation (ParameterError).

    ``given`` holds some of ``cron``, ``params`` (a `PipelineParams` or its fields),
    ``tiling`` (a request's tiling, or None: one tile) and ``paused``. A new cron, or a
    resume, starts from the next cron time after ``now``: runs missed while paused are
    not made up.
    """
    changes: dict[str, Any] = {}
    cron = sched["cron"]
    if "cron" in given:
        cron = changes["cron"] = validate_cron(given["cron"])
    params = PipelineParams(**sched["params"])
    if "params" in given:
        params = PipelineParams.model_validate(given["params"])
        changes["params"] = params.model_dump()
    if "tiling" in given or "params" in given:
        changes["tiling"] = stored_tiling(params, given["tiling"] if "tiling" in given else sched["tiling"])
    if "paused" in given:
        changes["paused"] = given["paused"]
    paused = changes.get("paused", bool(sched["paused"]))
    if paused:
        changes["next_run_at"] = None
    elif "cron" in changes or bool(sched["paused"]):
        changes["next_run_at"] = next_run_time(cron, now or datetime.now().astimezone()).timestamp()
    return changes
