"""The API's request and response bodies, and how they meet the job store's records.

Request bodies (`JobCreate`, `ScheduleCreate`, `ScheduleUpdate` with their `Tiling`) are
checked into the records the store keeps by `service.jobrequests`; store records become response bodies (`Block`, `Job`, `Schedule`) through `block_out`,
`job_out` and `schedule_out`. `ERRORS` documents the error answers every ``/v1`` route
may give.
"""

from __future__ import annotations

import copy
from datetime import datetime, timezone
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, create_model
from pydantic_core import PydanticUndefined

from pipeline.jobparams import TilingParams
from pipeline.params import PipelineParams
from service.schedules import DEFAULT_CRON
from service.wording import REQUEST_TILING

# -- bodies --------------------------------------------------------------------------------


class ErrorBody(BaseModel):
    detail: str = Field(description="what was wrong and what to do")
    errors: list[dict[str, Any]] | None = Field(None, description="validation errors per field (422 only)")


def _tiling_body() -> type[BaseModel]:
    """The tiling of a request: `TilingParams`' fields that a client sets (its tile size
    required), with the model's bounds, defaults and descriptions; the service's settings
    give the others."""
    fields = {}
    for name in REQUEST_TILING:
        field = copy.copy(TilingParams.model_fields[name])
        annotation = field.annotation
        if name == "tile_size":  # a body that tiles names its tile size
            field.default, annotation = PydanticUndefined, float
        fields[name] = (annotation, field)
    config = ConfigDict(extra="forbid", allow_inf_nan=False)
    return create_model("Tiling", __config__=config, __doc__=TilingParams.__doc__, __module__=__name__, **fields)


Tiling = _tiling_body()


class JobCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    block_id: str = Field(max_length=200, description="id of an uploaded block")
    params: PipelineParams = Field(default_factory=PipelineParams, description="pipeline parameters (defaults if omitted)")
    tiling: Tiling | None = Field(None, description="tiled processing on the dask workers; omit for one tile")


class Block(BaseModel):
    id: str
    sha256: str
    filename: str | None
    size_bytes: int
    n_points: int | None = None
    version: str | None = None
    point_format: int | None = None
    compressed: bool | None = None
    mins: list[float] | None = None
    maxs: list[float] | None = None
    scales: list[float] | None = None
    offsets: list[float] | None = None
    crs_wkt: str | None = None
    created_at: str | None


class Job(BaseModel):
    id: str
    block_id: str
    schedule_id: str | None
    capture: str | None = Field(None, description="name of the inbox file its schedule took the block from (the block's own "
                                "filename is that of its first upload or capture)")
    state: Literal["queued", "running", "done", "failed", "cancelled"]
    tiles_done: int
    tiles_total: int
    timings: dict[str, Any]
    error: str | None
    cancel_requested: bool
    attempts: int = 0
    crashes: int = Field(0, description="times the service died while running this job (not attempts; at ORCHARD_MAX_CRASHES it fails)")
    retry_at: str | None = None
    params: dict[str, Any]
    tiling: dict[str, Any] | None
    n_points: int | None = None
    n_trees: int | None = None
    partial: bool | None = None
    failed_tiles: list[int] = []
    created_at: str | None
    started_at: str | None
    finished_at: str | None
    links: dict[str, str]


class TreesPage(BaseModel):
    items: list[dict[str, Any]]
    total: int
    limit: int
    offset: int


class JobsPage(BaseModel):
    """A page of jobs, newest first (as `TreesPage`: ``offset`` + ``limit`` < ``total`` means more)."""

    items: list[Job]
    total: int = Field(description="jobs matching the filters, on every page")
    limit: int
    offset: int


class ScheduleCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    inbox: str = Field(max_length=4096, description="absolute path of the folder on the server where captures land")
    cron: str = Field(DEFAULT_CRON, max_length=200, description="cron expression, local time (default 01:00 every night)")
    params: PipelineParams = Field(default_factory=PipelineParams)
    tiling: Tiling | None = None


class ScheduleUpdate(BaseModel):
    """The settings to change; those left out stay as they are."""

    model_config = ConfigDict(extra="forbid")
    # (not nullable: a field left out stays as it is; None is only the "not given" default)
    paused: StrictBool = Field(None, description="true: the clock skips the schedule (a scan by hand still runs); false: it runs again from its next cron time")
    cron: str = Field(None, max_length=200, description="cron expression, local time")
    params: PipelineParams = Field(None, description="parameters of the jobs it queues from now on (all of them: left-out fields take their defaults)")
    tiling: Tiling | None = Field(None, description="tiling of the jobs it queues from now on; null: one tile")


class Schedule(BaseModel):
    id: str
    inbox: str
    cron: str
    params: dict[str, Any]
    tiling: dict[str, Any] | None
    paused: bool = Field(description="the clock skips a paused schedule (PATCH it with paused false to resume)")
    created_at: str | None
    last_run_at: str | None
    next_run_at: str | None = Field(description="the next scan by the clock; null while paused")


class RejectedFile(BaseModel):
    file: str
    error: str


class ScheduleRun(BaseModel):
    schedule_id: str
    jobs: list[str]
    skipped: int
    rejected: list[RejectedFile]
    waiting: list[str] = Field(
        default_factory=list,
        description="captures still being copied in (written to within ORCHARD_CAPTURE_SETTLE_S): the schedule looks at them again once they have settled",
    )


class Health(BaseModel):
    status: Literal["ok", "not ok"] = Field(description="'not ok' (HTTP 503) says why in problems")
    problems: list[str] = Field(default_factory=list, description="what is wrong, one line each")
    disk_free_mb: float | None = Field(None, description="free space on the data folder's disk [MB]")
    version: str
    runner: str
    schedules: str
    cluster: str = Field(
        description="the runner's dask client: 'connected', 'not started' (until the first job), "
        "'unreachable' (the last attempt to reach the cluster failed; the next job tries again), "
        "or distributed's state of a client that lost its scheduler (e.g. 'connecting')"
    )
    workers: int | None = Field(None, description="dask workers connected to the cluster's scheduler (none while "
                                "the cluster is not started); 0 is 'not ok'")
    workers_expected: int | None = Field(None, description="workers the embedded cluster should have (lost ones are "
                                         "replaced); none for an external cluster")


#: error answers of every ``/v1`` route (the router's default responses)
ERRORS = {
    401: {"model": ErrorBody, "description": "missing or unknown bearer token"},
    404: {"model": ErrorBody, "description": "no such resource for this tenant"},
    413: {"model": ErrorBody, "description": "request body too large"},
    422: {"model": ErrorBody, "description": "invalid request"},
    503: {"model": ErrorBody, "description": "the job store is busy (Retry-After) or the server is stopping; try again"},
    507: {"model": ErrorBody, "description": "the server's disk is full; nothing of the request was kept"},
}
#: the answer of a route taking a JSON body sent as something else
JSON_BODY = {415: {"model": ErrorBody, "description": "the body was not sent as JSON (Content-Type: application/json)"}}
#: the answer of a result route while its job is not done
UNFINISHED = {409: {"model": ErrorBody, "description": "the job is not done (yet)"}}


# -- store records to response bodies ------------------------------------------------------


def _iso(ts: float | None, local: bool = False) -> str | None:
    if ts is None:
        return None
    if local:
        return datetime.fromtimestamp(ts).astimezone().isoformat()
    return datetime.fromtimestamp(ts, timezone.utc).isoformat()


def block_out(rec: dict) -> Block:
    info = rec.get("info") or {}
    return Block(
        id=rec["id"],
        sha256=rec["sha256"],
        filename=rec.get("filename"),
        size_bytes=rec["size_bytes"],
        n_points=info.get("n_points"),
        version=info.get("version"),
        point_format=info.get("point_format"),
        compressed=info.get("compressed"),
        mins=info.get("mins"),
        maxs=info.get("maxs"),
        scales=info.get("scales"),
        offsets=info.get("offsets"),
        crs_wkt=info.get("crs_wkt"),
        created_at=_iso(rec.get("created_at")),
    )


def job_out(rec: dict) -> Job:
    outcome = rec.get("outcome") or {}
    base = f"/v1/jobs/{rec['id']}"
    links = {"self": base, "page": f"/jobs/{rec['id']}"}
    if rec["state"] == "done":
        for name in ("trees", "trees.parquet", "trees.csv", "points.parquet", "rows.parquet", "gaps.parquet", "report", "map.png"):
            links[name] = f"{base}/{name}"
    return Job(
        id=rec["id"],
        block_id=rec["block_id"],
        schedule_id=rec.get("schedule_id"),
        capture=rec.get("capture"),
        state=rec["state"],
        tiles_done=rec["tiles_done"],
        tiles_total=rec["tiles_total"],
        timings=rec.get("timings") or {},
        error=rec.get("error"),
        cancel_requested=bool(rec.get("cancel_requested")),
        attempts=int(rec.get("attempts") or 0),
        crashes=int(rec.get("crashes") or 0),
        retry_at=_iso(rec.get("retry_at")),
        params=rec.get("params") or {},
        tiling=rec.get("tiling"),
        n_points=outcome.get("n_points"),
        n_trees=outcome.get("n_trees"),
        partial=outcome.get("partial"),
        failed_tiles=outcome.get("failed_tiles") or [],
        created_at=_iso(rec.get("created_at")),
        started_at=_iso(rec.get("started_at")),
        finished_at=_iso(rec.get("finished_at")),
        links=links,
    )


def schedule_out(rec: dict) -> Schedule:
    return Schedule(
        id=rec["id"],
        inbox=rec["inbox"],
        cron=rec["cron"],
        params=rec.get("params") or {},
        tiling=rec.get("tiling"),
        paused=bool(rec.get("paused")),
        created_at=_iso(rec.get("created_at")),
        last_run_at=_iso(rec.get("last_run_at"), local=True),
        next_run_at=None if rec.get("paused") else _iso(rec.get("next_run_at"), local=True),
    )
