"""What a job or schedule request sets, checked once into the `JobParams` the job store
keeps whole. The API's bodies and the command line's options both come here: no HTTP."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pipeline.jobparams import JobParams, TilingParams
from pipeline.params import PipelineParams
from service.schedules import next_run_time, validate_cron
from service.wording import REQUEST_TILING


def request_job(params: PipelineParams, tiling: dict | None) -> JobParams:
    """A request's pipeline ``params`` and ``tiling`` (its `REQUEST_TILING` fields;
    None: one tile) as the job's parameters: pydantic's ValidationError for a field out
    of its bounds, ParameterError for a buffer below the parameters' reach. The limits
    that depend on the block are checked when the job plans its tiles."""
    return JobParams(pipeline=params, tiling=TilingParams(**(tiling or {})))


def stored(job: JobParams) -> dict:
    """``job`` as the job store keeps it (JSON, every field)."""
    return job.model_dump(mode="json")


def request_tiling(job: dict) -> dict | None:
    """The tiling of a stored job as a request gave it (its `REQUEST_TILING` fields),
    None for one tile: what the API shows as a job's or a schedule's ``tiling``."""
    tiling = {k: (job.get("tiling") or {}).get(k) for k in REQUEST_TILING}
    return None if all(v is None for v in tiling.values()) else tiling


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
    if "tiling" in given or "params" in given:
        job = JobParams.model_validate(sched["job"])
        params = PipelineParams.model_validate(given["params"]) if "params" in given else job.pipeline
        tiling = given["tiling"] if "tiling" in given else request_tiling(sched["job"])
        changes["job"] = stored(request_job(params, tiling))
    if "paused" in given:
        changes["paused"] = given["paused"]
    paused = changes.get("paused", bool(sched["paused"]))
    if paused:
        changes["next_run_at"] = None
    elif "cron" in changes or bool(sched["paused"]):
        changes["next_run_at"] = next_run_time(cron, now or datetime.now().astimezone()).timestamp()
    return changes
