"""The API's request and response bodies, and how they meet the job store's records.

Request bodies (`JobCreate`, `ScheduleCreate`, `ScheduleUpdate` with their `Tiling`) are
checked into the records the store keeps by `service.jobrequests`; store records become response bodies (`Block`, `Job`, `Schedule`) through `block_out`,
`job_out` and `schedule_out`. `ERRORS` documents the error answers every ``/v1`` route
may give.
"""

from __future__ import annotations

import copy
from datetime import date, datetime, timezone
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, create_model
from pydantic_core import PydanticUndefined

from pipeline.jobparams import TilingParams
from pipeline.params import PipelineParams
from service.jobrequests import request_tiling
from service.schedules import DEFAULT_CRON
from service.wording import REQUEST_TILING, job_error

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
    error_kind: str | None = Field(None, description="what kind of failure ``error`` says, for a client to act on: "
                                   "parameter, input, no_trees, tile_failed, cluster_lost, cluster_unavailable, "
                                   "disk_full, scheduler_lost, internal, cancelled, ... (null: none, or a note)")
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
    orchard_block: dict[str, Any] | None = Field(None, description="a capture of an orchard block (GET /v1/jobs/ID only): "
                                                 "the block's id and name, the capture's id, seq and date")


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
    orchard_block_id: str | None = Field(None, max_length=200, description="the inbox of this orchard block: each file "
                                         "landing in it is one more capture of the block (GET /v1/orchard-blocks)")


class ScheduleUpdate(BaseModel):
    """The settings to change; those left out stay as they are."""

    model_config = ConfigDict(extra="forbid")
    # (not nullable: a field left out stays as it is; None is only the "not given" default)
    paused: StrictBool = Field(None, description="true: the clock skips the schedule (a scan by hand still runs); false: it runs again from its next cron time")
    cron: str = Field(None, max_length=200, description="cron expression, local time")
    params: PipelineParams = Field(None, description="parameters of the jobs it queues from now on (all of them: left-out fields take their defaults)")
    tiling: Tiling | None = Field(None, description="tiling of the jobs it queues from now on; null: one tile")


class Capture(BaseModel):
    """A file of a schedule's inbox and what became of it."""

    file: str = Field(description="the file's name in the inbox")
    fate: Literal["arriving", "new", "rejected", "processed", "ignored"] = Field(
        description="processed: a job was queued (job_id); rejected: unusable (reason); arriving: still being "
        "written to; new: settled, taken at the next scan; ignored: not a capture (another file type, a folder, a link: reason)"
    )
    job_id: str | None = Field(None, description="the job of a processed capture")
    job_state: str | None = Field(None, description="that job's state ('deleted' if the job was deleted)")
    reason: str | None = Field(None, description="why it was rejected or ignored; a failed job's error")
    seen_at: str | None = Field(None, description="when a scan handled it")


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
    orchard_block_id: str | None = Field(None, description="the orchard block whose captures land in the inbox")
    captures: list[Capture] | None = Field(
        None, description="every capture's fate, files in the inbox now first, then those handled, newest first "
        "(at most 200; only on GET /v1/schedules/ID)")
    capture_counts: dict[str, int] | None = Field(None, description="how many captures have each fate (all of them)")


class IgnoredFile(BaseModel):
    file: str
    reason: str


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
    ignored: list[IgnoredFile] = Field(default_factory=list, description="files in the inbox that are not captures, and why")


class OrchardBlockCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True)
    name: str = Field(min_length=1, max_length=200, pattern=r"^[^\x00-\x1f\x7f]+$",
                      description="the block's name, unique within the farm (e.g. 'North 12 Gala')")


class OrchardBlock(BaseModel):
    """A named orchard block: the captures of the same piece of orchard, over the seasons."""

    id: str
    name: str
    n_captures: int = Field(description="captures added, whatever their state")
    n_done: int = Field(description="captures processed")
    last_captured_at: str | None = Field(None, description="date of the latest processed capture (ISO)")
    created_at: str | None
    links: dict[str, str]


class OrchardCaptureCreate(BaseModel):
    """A capture of an already uploaded block (POST /v1/blocks); a file may instead be
    sent as multipart field 'file' with ``captured_at`` as a query parameter."""

    model_config = ConfigDict(extra="forbid")
    block_id: str = Field(max_length=200, description="id of an uploaded block")
    captured_at: date | None = Field(None, description="the day of the capture (YYYY-MM-DD), used when the file has no "
                                     "date of its own; neither: the day it arrived")
    params: PipelineParams = Field(default_factory=PipelineParams, description="pipeline parameters (defaults if omitted)")
    tiling: Tiling | None = Field(None, description="tiled processing on the dask workers; omit for one tile")


class OrchardCapture(BaseModel):
    """One capture of an orchard block: its file, its job and what the job found."""

    id: str
    orchard_block_id: str
    seq: int = Field(description="its place in the block's arrival order (1 first); captures are processed in it")
    block_id: str = Field(description="the uploaded file (GET /v1/blocks/ID)")
    job_id: str = Field(description="the job that processes it (GET /v1/jobs/ID)")
    state: Literal["queued", "running", "done", "failed", "cancelled"]
    error: str | None = None
    captured_at: str | None = Field(description="the capture's day (ISO date)")
    captured_at_source: Literal["file", "given", "upload"] | None = Field(
        description="where the day comes from: the file's header, the sender (captured_at), or the day it arrived")
    previous_capture_id: str | None = Field(None, description="the capture it was registered to (null: the block's first)")
    registration: dict[str, Any] | None = Field(None, description="the transform onto the previous capture: dx, dy [m], "
                                                "rotation_deg, residual_m, n_matched")
    counts: dict[str, int] | None = Field(None, description="trees same, new, replanted and removed")
    arrived_at: str | None
    links: dict[str, str]


class TreeHistory(BaseModel):
    """One tree of an orchard block over its captures (from the block's history.parquet)."""

    orchard_block_id: str
    tree_key: int
    items: list[dict[str, Any]] = Field(description="one row per capture, oldest first: capture, captured_at, row, "
                                        "position, height_m, crown_volume_m3, trunk_diameter_m, status")


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


def job_out(rec: dict, *, capture: dict | None = None) -> Job:
    """The job's body; ``capture``: its capture of an orchard block, when it is one."""
    outcome = rec.get("outcome") or {}
    base = f"/v1/jobs/{rec['id']}"
    links = {"self": base, "page": f"/jobs/{rec['id']}"}
    if rec["state"] == "done":
        for name in ("trees", "trees.parquet", "trees.csv", "points.parquet", "rows.parquet", "gaps.parquet", "report", "map.png"):
            links[name] = f"{base}/{name}"
        if any(str(v).endswith("/history.parquet") for v in (outcome.get("outputs") or {}).values()):
            links["history.parquet"] = f"{base}/history.parquet"  # a capture of an orchard block
    return Job(
        id=rec["id"],
        block_id=rec["block_id"],
        schedule_id=rec.get("schedule_id"),
        capture=rec.get("capture"),
        state=rec["state"],
        tiles_done=rec["tiles_done"],
        tiles_total=rec["tiles_total"],
        timings=rec.get("timings") or {},
        error=job_error(rec),
        error_kind=rec.get("error_kind"),
        cancel_requested=bool(rec.get("cancel_requested")),
        attempts=int(rec.get("attempts") or 0),
        crashes=int(rec.get("crashes") or 0),
        retry_at=_iso(rec.get("retry_at")),
        params=rec["job"].get("pipeline") or {},
        tiling=request_tiling(rec["job"]),
        n_points=outcome.get("n_points"),
        n_trees=outcome.get("n_trees"),
        partial=outcome.get("partial"),
        failed_tiles=outcome.get("failed_tiles") or [],
        created_at=_iso(rec.get("created_at")),
        started_at=_iso(rec.get("started_at")),
        finished_at=_iso(rec.get("finished_at")),
        links=links,
        orchard_block=None if capture is None else {
            "id": capture["orchard_block_id"], "name": capture.get("orchard_block_name"), "capture_id": capture["id"],
            "seq": capture["seq"], "captured_at": capture.get("captured_at")},
    )


def schedule_out(rec: dict, fates: dict | None = None) -> Schedule:
    """A stored schedule as a response body; ``fates`` (`service.capturefates.capture_fates`)
    adds its captures."""
    captures = None
    if fates is not None:
        captures = [Capture(**{**c, "seen_at": _iso(c["seen_at"])}) for c in fates["captures"]]
    return Schedule(
        captures=captures,
        capture_counts=None if fates is None else fates["counts"],
        id=rec["id"],
        inbox=rec["inbox"],
        cron=rec["cron"],
        params=rec["job"].get("pipeline") or {},
        tiling=request_tiling(rec["job"]),
        paused=bool(rec.get("paused")),
        created_at=_iso(rec.get("created_at")),
        last_run_at=_iso(rec.get("last_run_at"), local=True),
        next_run_at=None if rec.get("paused") else _iso(rec.get("next_run_at"), local=True),
        orchard_block_id=rec.get("orchard_block_id"),
    )


def orchard_block_out(rec: dict) -> OrchardBlock:
    base = f"/v1/orchard-blocks/{rec['id']}"
    links = {"self": base, "captures": f"{base}/captures"}
    if rec.get("n_done"):
        links["history.parquet"] = f"{base}/history.parquet"
    return OrchardBlock(id=rec["id"], name=rec["name"], n_captures=int(rec.get("n_captures") or 0),
                        n_done=int(rec.get("n_done") or 0), last_captured_at=rec.get("last_captured_at"),
                        created_at=_iso(rec.get("created_at")), links=links)


def orchard_capture_out(rec: dict) -> OrchardCapture:
    record = rec.get("record") or {}
    links = {"self": f"/v1/orchard-blocks/{rec['orchard_block_id']}/captures/{rec['id']}",
             "job": f"/v1/jobs/{rec['job_id']}", "block": f"/v1/blocks/{rec['block_id']}", "page": f"/jobs/{rec['job_id']}"}
    return OrchardCapture(id=rec["id"], orchard_block_id=rec["orchard_block_id"], seq=rec["seq"], block_id=rec["block_id"],
                   job_id=rec["job_id"], state=rec["state"], error=job_error(rec), captured_at=rec.get("captured_at"),
                   captured_at_source=rec.get("captured_at_source"), previous_capture_id=record.get("previous_capture_id"),
                   registration=record.get("registration"), counts=record.get("counts"),
                   arrived_at=_iso(rec.get("arrived_at")), links=links)
