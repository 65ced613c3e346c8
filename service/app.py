"""The HTTP API (FastAPI): blocks, jobs, results, reports and schedules under ``/v1``.

`create_app(settings)` wires the store, the job runner and the schedule clock into a
FastAPI app; the app package holds wiring only (the work is in `service.store`,
`service.runner`, `service.schedules`, `service.report`). OpenAPI docs are at
``/docs``. Every ``/v1`` request needs ``Authorization: Bearer <token>``; a tenant sees
only its own resources (anything else is 404). Errors are JSON ``{"detail": ...}``
(see `service.errors`).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import os
import shutil
import threading
import uuid
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, FastAPI, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, ConfigDict, Field, StrictBool
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect

from pipeline.errors import ConflictError, InputError, NotFoundError, ParameterError
from pipeline.params import PipelineParams
from pipeline.tiling import check_tiling
from service import report as reports
from service import openapi as api_document
from service import tempfiles
from service import web
from service.downloads import DownloadResponse
from service.errors import ShuttingDownError, StalledUploadError, TooLargeError, api_wording, install_error_handlers
from service.permissions import FILE_MODE, private_dir, tighten
from service.runner import Runner, drop_work, hold_runner_lock, job_block_name, job_dir
from service.schedules import (
    DEFAULT_CRON,
    ScheduleClock,
    check_inbox_use,
    next_run_time,
    printable,
    run_schedule,
    tenant_inbox_root,
    validate_cron,
    validate_inbox,
)
from service.settings import Settings
from service.store import Store, accept_block
from service.web import sessions as web_sessions

log = logging.getLogger("orchard.service")

API_VERSION = "0.1.0"
_UPLOAD_SLACK = 1 << 20  # multipart overhead allowed on top of the file size limit
_DRAIN_LIMIT = 64 << 20  # after a too-large upload, read at most this much more before answering


# -- models --------------------------------------------------------------------------------


class ErrorBody(BaseModel):
    detail: str = Field(description="what was wrong and what to do")
    errors: list[dict[str, Any]] | None = Field(None, description="validation errors per field (422 only)")


class Tiling(BaseModel):
    """Split the block into square tiles processed on the dask workers."""

    model_config = ConfigDict(extra="forbid")
    tile_size: float = Field(ge=1.0, le=100_000.0, allow_inf_nan=False, description="tile edge length [m]")
    buffer: float | None = Field(None, ge=0.0, le=1_000.0, allow_inf_nan=False, description="overlap on every side [m]; default = the parameters' reach")


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


# -- conversions ---------------------------------------------------------------------------


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


def display_filename(name: str | None) -> str | None:
    """A client file name reduced to something safe to show (never used as a path)."""
    if not name:
        return None
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    base = printable(base).strip()
    return base[:200] or None


# -- request body limits -------------------------------------------------------------------


class BodyLimit:
    """ASGI middleware: 413 for request bodies above the limit (uploads get their own, larger one)."""

    def __init__(self, app, *, default: int, upload: int, upload_mb: float, upload_path: str = "/v1/blocks") -> None:
        self.app = app
        self.upload_mb = upload_mb
        self.default = default
        self.upload = upload
        self.upload_path = upload_path

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        is_upload = scope.get("method") == "POST" and scope.get("path", "").rstrip("/") == self.upload_path
        limit = self.upload if is_upload else self.default
        length = None
        for key, value in scope.get("headers", ()):
            if key == b"content-length":
                with contextlib.suppress(ValueError):
                    length = int(value)
        if length is not None and length > limit:
            if is_upload:
                detail = f"upload of {length} bytes is above the upload limit of {self.upload_mb:g} MB (ORCHARD_MAX_UPLOAD_MB)"
            else:
                detail = f"request body of {length} bytes is above the limit of {limit} bytes"
            resp = JSONResponse(
                {"detail": detail},
                status_code=413,
                headers={"Connection": "close"},
            )
            await resp(scope, receive, send)
            return
        total = 0

        async def limited_receive():
            nonlocal total
            message = await receive()
            if message["type"] == "http.request":
                total += len(message.get("body", b""))
                if total > limit:
                    raise TooLargeError(f"request body is above the limit of {limit} bytes")
            return message

        await self.app(scope, limited_receive, send)


# -- dependencies --------------------------------------------------------------------------


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


_bearer = HTTPBearer(auto_error=False, description="a token from `orchard tokens create --tenant NAME`")


def get_tenant(
    request: Request,
    store: Annotated[Store, Depends(get_store)],
    _creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> dict:
    return web_sessions.request_tenant(request, store)  # a bearer token, or a browser's session cookie


StoreDep = Annotated[Store, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
TenantDep = Annotated[dict, Depends(get_tenant)]


# -- upload --------------------------------------------------------------------------------


class _FilePart:
    """Receives the multipart callbacks; writes the ``file`` field to a temporary file, hashing it."""

    def __init__(self, tmp_path: Path, limit: int) -> None:
        self.tmp_path = tmp_path
        self.limit = limit
        self.fh = None
        self.sha = hashlib.sha256()
        self.size = 0
        self.filename: str | None = None
        self.found = False
        self.complete = False  # the file's part ended at a boundary (not cut off)
        self.too_large = False
        self._in_file = False
        self._field = bytearray()
        self._value = bytearray()
        self._headers: dict[bytes, bytes] = {}

    def callbacks(self) -> dict:
        return {
            "on_part_begin": self._part_begin,
            "on_header_field": lambda d, s, e: self._field.extend(d[s:e]),
            "on_header_value": lambda d, s, e: self._value.extend(d[s:e]),
            "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished,
            "on_part_data": self._data,
            "on_part_end": self._part_end,
        }

    def _part_begin(self) -> None:
        self._headers = {}
        self._in_file = False

    def _header_end(self) -> None:
        self._headers[bytes(self._field).lower()] = bytes(self._value)
        self._field.clear()
        self._value.clear()

    def _headers_finished(self) -> None:
        _, opts = parse_options_header(self._headers.get(b"content-disposition", b""))
        if opts.get(b"name") == b"file" and not self.found:
            self.found = True
            self._in_file = True
            raw = opts.get(b"filename")
            self.filename = display_filename(raw.decode("utf-8", "replace")) if raw else None
            self.fh = open(self.tmp_path, "wb")
            os.fchmod(self.fh.fileno(), FILE_MODE)  # a farm's file, whatever the process umask

    def _data(self, data: bytes, start: int, end: int) -> None:
        if not self._in_file or self.too_large:
            return
        n = end - start
        self.size += n
        if self.size > self.limit:
            self.too_large = True
            return
        chunk = data[start:end]
        self.sha.update(chunk)
        self.fh.write(chunk)

    def _part_end(self) -> None:
        if self._in_file and self.fh is not None:
            self.fh.close()
            self.complete = True
        self._in_file = False

    @property
    def header_name(self) -> bytes:
        """The name of the part header being read (empty between headers)."""
        return bytes(self._field)

    def close(self) -> None:
        if self.fh is not None and not self.fh.closed:
            self.fh.close()


async def _receive_upload(request: Request, settings: Settings) -> _FilePart:
    ctype, opts = parse_options_header(request.headers.get("content-type", "").encode("latin-1", "replace"))
    boundary = opts.get(b"boundary")
    if ctype != b"multipart/form-data" or not boundary:
        raise InputError("send the block as multipart/form-data with the file in the field 'file' (curl -F file=@block.laz)")
    part = _FilePart(tempfiles.process_dir(settings.tmp_dir) / f"upload-{uuid.uuid4().hex}.part", settings.max_upload_bytes)
    try:
        parser = MultipartParser(boundary, part.callbacks())
    except Exception:
        raise InputError("the multipart boundary is invalid") from None
    stream = request.stream()
    stopping = getattr(request.app.state, "stopping", None)  # set when the server is told to stop
    stop = asyncio.ensure_future(stopping.wait()) if stopping is not None else None
    try:
        while True:
            # a client that stops sending would hold the request and its partial file for good,
            # and a stopping server waited for it, then cut the connection without a reply
            nxt = asyncio.ensure_future(anext(stream))
            done, _ = await asyncio.wait({nxt} | ({stop} if stop else set()), timeout=settings.upload_idle_s,
                                         return_when=asyncio.FIRST_COMPLETED)
            if nxt not in done:
                nxt.cancel()
                if stop is not None and stop in done:
                    raise ShuttingDownError("the server is stopping and cannot take this upload; send it again "
                                            "once it is back (nothing of it was kept)")
                raise StalledUploadError(
                    f"the upload sent nothing for {settings.upload_idle_s:g} s (ORCHARD_UPLOAD_IDLE_S); send it again"
                )
            try:
                chunk = nxt.result()
            except StopAsyncIteration:
                break
            try:
                parser.write(chunk)
            except OSError:  # writing the file (a full disk): the server's fault, not the body's
                raise
            except Exception:
                if part.header_name.lower() == b"content-disposition":  # (python-multipart's 4,224-byte line limit)
                    raise InputError("the file name of the upload is too long; rename the file (a name is kept "
                                     "to 200 characters) and send it again") from None
                raise InputError("the multipart body is malformed; send the file as field 'file'") from None
            if part.too_large:
                break
        if part.too_large:
            drained = 0
            with contextlib.suppress(TooLargeError, ClientDisconnect):
                async for chunk in stream:
                    drained += len(chunk)
                    if drained > _DRAIN_LIMIT:
                        break
            raise TooLargeError(
                f"the file is larger than the upload limit of {settings.max_upload_mb:g} MB (ORCHARD_MAX_UPLOAD_MB)"
            )
        try:
            parser.finalize()  # (it does not check that the body ended at a boundary)
        except OSError:  # closing the file (a full disk)
            raise
        except Exception:
            raise InputError("the multipart body is incomplete") from None
        if part.found and not part.complete:
            raise InputError("the multipart body is incomplete: the file's part has no closing boundary (upload cut off?)")
    except BaseException:
        with contextlib.suppress(OSError):  # (its last write may fail again: a full disk)
            part.close()
        part.tmp_path.unlink(missing_ok=True)
        raise
    finally:
        if stop is not None:
            stop.cancel()
    part.close()
    if not part.found:
        part.tmp_path.unlink(missing_ok=True)
        raise InputError("no field 'file' in the upload; send the block as multipart field 'file' (curl -F file=@block.laz)")
    return part


_UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {"file": {"type": "string", "format": "binary", "description": "a LAS or LAZ file"}},
                }
            }
        },
    }
}


# -- the app -------------------------------------------------------------------------------


def _results(store: Store, settings: Settings, tenant: dict, job_id: str, name: str) -> tuple[dict, Path]:
    job = store.get_job(tenant["id"], job_id)
    if job["state"] in ("failed", "cancelled"):  # "once it is done" would never come
        raise ConflictError(f"job {job_id} is {job['state']} and has no results; submit its block again "
                            f"with POST /v1/jobs (GET /v1/jobs/{job_id} says why it ended)")
    if job["state"] != "done":
        raise ConflictError(f"job {job_id} is {job['state']}; results are available once it is done (GET /v1/jobs/{job_id})")
    path = job_dir(settings, job_id) / name
    outputs = (job.get("outcome") or {}).get("outputs") or {}
    if not path.exists():
        for value in outputs.values():
            if isinstance(value, str) and Path(value).name == name and Path(value).exists():
                path = Path(value)
                break
    return job, path


def _require(path: Path, what: str) -> Path:
    if not path.exists():
        raise NotFoundError(f"the {what} of this job is missing on the server")
    return path


def ensure_report(store: Store, settings: Settings, job: dict) -> Path:
    """``report.html`` (and ``map.png``) of a finished job, both written again if either is
    missing (a lost ``map.png`` beside its report was a 500 on every request)."""
    out = job_dir(settings, job["id"])
    html_path = out / "report.html"
    if html_path.exists() and (out / "map.png").exists():
        return html_path
    block = store.get_block(None, job["block_id"])
    if not Path(block["path"]).is_file():  # not the farm's fault, and not its file name to show
        raise NotFoundError("the uploaded block of this job is missing on the server, so its report cannot be "
                            "drawn; the per-tree downloads (trees.csv, trees.parquet) still work")
    _, trees = _results(store, settings, {"id": job["tenant_id"]}, job["id"], "trees.parquet")
    _, points = _results(store, settings, {"id": job["tenant_id"]}, job["id"], "points.parquet")
    outcome = job.get("outcome") or {}
    rows_total = outcome.get("n_trees")
    finished = job.get("finished_at")
    summary = {
        "Block": job_block_name(job, block) or block["id"],
        "Job": job["id"],
        # the server's local time, as its schedules' cron times, with the zone said
        "Finished": datetime.fromtimestamp(finished).astimezone().strftime("%Y-%m-%d %H:%M %Z (UTC%z)") if finished else "",
        "Points": str((block.get("info") or {}).get("n_points", "")),
        "Trees": str(rows_total if rows_total is not None else ""),
    }
    warning = None
    if outcome.get("partial"):
        failed = ", ".join(str(t) for t in outcome.get("failed_tiles") or []) or "some"
        warning = (f"Partial result: tile(s) {failed} of this block failed. Trees standing in them are missing "
                   "from this report and the downloads, and their points are in no tree.")
    return reports.write_report(
        block_path=block["path"],
        trees_parquet=_require(trees, "trees.parquet"),
        points_parquet=_require(points, "points.parquet"),
        out_dir=out,
        title=f"Orchard report — {job_block_name(job, block) or block['id']}",
        summary=summary,
        warning=warning,
    )


def create_app(settings: Settings) -> FastAPI:
    """The API app. Starting it (lifespan) re-queues interrupted jobs and starts the runner and the schedule clock."""
    if settings.work_dir and settings.runner:  # the runner's jobs would each fail on it
        from workers.workstore import check_work_url

        try:
            check_work_url(settings.work_dir, shared=True)
        except ParameterError as exc:
            raise ParameterError(f"ORCHARD_WORK_DIR: {exc}") from None
    private_dir(settings.data_dir)
    # the one process that runs this folder's jobs and schedules (a second one is refused)
    runner_lock = hold_runner_lock(settings.data_dir) if settings.runner or settings.scheduling else None
    store = Store(settings.store_path)
    report_lock = threading.Lock()

    def after_done(job: dict) -> None:
        with report_lock:
            ensure_report(store, settings, job)
        tighten(job_dir(settings, job["id"]))  # results are the farm's: whoever wrote them (a remote worker)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        log.info("data folder %s (tokens for this server: orchard tokens create --tenant NAME --data-dir %s)",
                 settings.data_dir, settings.data_dir)
        for d in (settings.blocks_dir, settings.jobs_dir, settings.tmp_dir):
            private_dir(d)
        # a folder written by an earlier version, or copied in: the farms' inboxes stay as they are
        await run_in_threadpool(tighten, settings.data_dir, skip=[settings.http_inbox_root])
        tempfiles.sweep(settings.tmp_dir)  # uploads a crash interrupted (not those of live processes)
        if runner_lock is not None:  # no other process runs jobs here: a "running" job is an orphan
            for job_id in store.cancel_interrupted():  # asked to stop before the last shutdown
                drop_work(settings, job_id)
            n = store.requeue_running(max_crashes=settings.max_crashes)
            if n:
                log.info("re-queued %d job(s) interrupted by the last shutdown", n)
        if settings.runner:
            app.state.runner = Runner(store, settings, after_done=after_done)
            app.state.runner.start()
        if settings.scheduling:
            app.state.clock = ScheduleClock(store, settings, on_jobs=lambda: _wake_runner(app))
            app.state.clock.start()
        loop = asyncio.get_running_loop()
        app.state.stopping = asyncio.Event()
        # called from the server's signal handler: uploads still arriving answer 503 at once
        app.state.begin_shutdown = lambda: loop.call_soon_threadsafe(app.state.stopping.set)
        try:
            yield
        finally:
            if app.state.clock is not None:
                await run_in_threadpool(app.state.clock.stop)
            if app.state.runner is not None:
                await run_in_threadpool(app.state.runner.stop)
            store.close()
            if runner_lock is not None:
                runner_lock.close()

    app = FastAPI(
        title="Orchard service",
        version=API_VERSION,
        description="Upload LiDAR blocks of orchards, run per-tree jobs on dask workers, "
        "schedule overnight processing of capture inboxes, download per-tree results and reports.",
        lifespan=lifespan,
        docs_url=None,  # served by service.web from vendored files: they render offline
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.store = store
    app.state.runner = None
    app.state.clock = None
    install_error_handlers(app)
    api_document.install(app)
    app.add_middleware(
        BodyLimit,
        default=settings.max_request_kb * 1024,
        upload=settings.max_upload_bytes + _UPLOAD_SLACK,
        upload_mb=settings.max_upload_mb,
    )

    errors = {
        401: {"model": ErrorBody, "description": "missing or unknown bearer token"},
        404: {"model": ErrorBody, "description": "no such resource for this tenant"},
        413: {"model": ErrorBody, "description": "request body too large"},
        422: {"model": ErrorBody, "description": "invalid request"},
        503: {"model": ErrorBody, "description": "the job store is busy (Retry-After) or the server is stopping; try again"},
        507: {"model": ErrorBody, "description": "the server's disk is full; nothing of the request was kept"},
    }
    v1 = APIRouter(prefix="/v1", responses=errors)
    json_body = {415: {"model": ErrorBody, "description": "the body was not sent as JSON (Content-Type: application/json)"}}

    @app.get("/", include_in_schema=False)
    def root() -> RedirectResponse:
        return RedirectResponse("/blocks")

    @app.get("/healthz", response_model=Health, tags=["service"],
             responses={503: {"model": Health, "description": "not ok: problems says why"}})
    def healthz(request: Request, response: Response) -> Health:
        runner, clock = request.app.state.runner, request.app.state.clock
        problems, free_mb = [], None
        try:
            free_mb = shutil.disk_usage(settings.data_dir).free / 2**20
        except OSError as exc:
            problems.append(f"the data folder cannot be read ({exc.strerror or exc})")
        if free_mb is not None and free_mb < settings.min_free_mb:
            problems.append(f"the data folder's disk has {free_mb:.0f} MB free, below {settings.min_free_mb:g} MB "
                            "(ORCHARD_MIN_FREE_MB): uploads and jobs will fail until space is freed")
        if problems:
            response.status_code = 503
        return Health(
            status="not ok" if problems else "ok",
            problems=problems,
            disk_free_mb=None if free_mb is None else round(free_mb, 1),
            version=API_VERSION,
            runner="disabled" if runner is None else ("alive" if runner.is_alive() else "stopped"),
            schedules="disabled" if clock is None else ("alive" if clock.is_alive() else "stopped"),
            cluster="disabled" if runner is None else runner.cluster_state(),
        )

    # blocks ------------------------------------------------------------------------------

    @v1.post(
        "/blocks",
        response_model=Block,
        status_code=201,
        tags=["blocks"],
        openapi_extra=_UPLOAD_BODY,
        responses={200: {"model": Block, "description": "this file was uploaded before: the existing block"}},
        summary="Upload a LAS/LAZ block (multipart field 'file')",
    )
    async def upload_block(request: Request, response: Response, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        declared = request.headers.get("content-length", "")  # refused before the body is read; checked again after
        await run_in_threadpool(store.check_storage, tenant["id"], max(int(declared) - _UPLOAD_SLACK if declared.isdigit() else 0, 1))
        part = await _receive_upload(request, settings)
        block, created = await run_in_threadpool(
            accept_block,
            store,
            blocks_dir=settings.blocks_dir,
            tenant_id=tenant["id"],
            tmp_path=part.tmp_path,
            sha256=part.sha.hexdigest(),
            size_bytes=part.size,
            filename=part.filename,
        )
        response.status_code = 201 if created else 200
        response.headers["Location"] = f"/v1/blocks/{block['id']}"
        return block_out(block)

    @v1.get("/blocks", response_model=list[Block], tags=["blocks"])
    def list_blocks(
        tenant: TenantDep,
        store: StoreDep,
        limit: Annotated[int, Query(ge=1, le=1000)] = 100,
        offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
    ):
        return [block_out(b) for b in store.list_blocks(tenant["id"], limit=limit, offset=offset)]

    @v1.get("/blocks/{block_id}", response_model=Block, tags=["blocks"])
    def get_block(block_id: str, tenant: TenantDep, store: StoreDep):
        return block_out(store.get_block(tenant["id"], block_id))

    # jobs --------------------------------------------------------------------------------

    @v1.post("/jobs", response_model=Job, status_code=201, tags=["jobs"], summary="Submit a job for a block",
             responses={429: {"model": ErrorBody, "description": "the tenant has as many jobs queued as its quota allows"},
                        **json_body})
    def create_job(body: JobCreate, request: Request, response: Response, tenant: TenantDep, store: StoreDep):
        block = store.get_block(tenant["id"], body.block_id)
        tiling = _checked_tiling(body.params, body.tiling)
        job = store.create_job(tenant_id=tenant["id"], block_id=block["id"], params=body.params.model_dump(), tiling=tiling)
        _wake_runner(request.app)
        response.headers["Location"] = f"/v1/jobs/{job['id']}"
        return job_out(job)

    @v1.get("/jobs", response_model=JobsPage | list[Job], tags=["jobs"], summary="List jobs, newest first, a page at a time")
    def list_jobs(
        tenant: TenantDep,
        store: StoreDep,
        state: Annotated[Literal["queued", "running", "done", "failed", "cancelled"] | None, Query()] = None,
        block_id: Annotated[str | None, Query(max_length=200)] = None,
        schedule_id: Annotated[str | None, Query(max_length=200)] = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = 100,
        offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
        paged: Annotated[bool, Query(description="false: the page's jobs as a bare list, as before pages (deprecated)")] = True,
    ):
        filters = {"state": state, "block_id": block_id, "schedule_id": schedule_id}
        items = [job_out(j) for j in store.list_jobs(tenant["id"], **filters, limit=limit, offset=offset)]
        if not paged:
            return items
        return JobsPage(items=items, total=store.count_jobs(tenant["id"], **filters), limit=limit, offset=offset)

    @v1.get("/jobs/{job_id}", response_model=Job, tags=["jobs"])
    def get_job(job_id: str, tenant: TenantDep, store: StoreDep):
        return job_out(store.get_job(tenant["id"], job_id))

    @v1.delete(
        "/jobs/{job_id}",
        response_model=Job,
        status_code=202,
        tags=["jobs"],
        summary="Cancel a queued or running job",
        responses={409: {"model": ErrorBody, "description": "the job has already finished"}},
    )
    def cancel_job(job_id: str, request: Request, tenant: TenantDep, store: StoreDep):
        job = store.request_cancel(tenant["id"], job_id)
        runner = request.app.state.runner
        if runner is not None:
            runner.cancel(job_id)
        return job_out(job)

    # results -----------------------------------------------------------------------------

    unfinished = {409: {"model": ErrorBody, "description": "the job is not done (yet)"}}

    @v1.get("/jobs/{job_id}/trees", response_model=TreesPage, tags=["results"], responses=unfinished)
    def job_trees(
        job_id: str,
        tenant: TenantDep,
        store: StoreDep,
        settings: SettingsDep,
        limit: Annotated[int, Query(ge=1, le=1000)] = 100,
        offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
    ):
        _, path = _results(store, settings, tenant, job_id, "trees.parquet")
        rows = reports.trees_records(_require(path, "trees.parquet"))
        return TreesPage(items=rows[offset : offset + limit], total=len(rows), limit=limit, offset=offset)

    def _file(path: Path, media_type: str, filename: str) -> FileResponse:
        return DownloadResponse(path, media_type=media_type, filename=filename)

    parquet = {200: {"content": {"application/vnd.apache.parquet": {}}, "description": "GeoParquet / Parquet file"}}

    @v1.api_route("/jobs/{job_id}/trees.parquet", methods=["GET", "HEAD"], tags=["results"], responses={**parquet, **unfinished}, response_class=FileResponse)
    def job_trees_parquet(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        _, path = _results(store, settings, tenant, job_id, "trees.parquet")
        return _file(_require(path, "trees.parquet"), "application/vnd.apache.parquet", f"trees-{job_id}.parquet")

    @v1.api_route("/jobs/{job_id}/rows.parquet", methods=["GET", "HEAD"], tags=["results"], responses={**parquet, **unfinished}, response_class=FileResponse)
    def job_rows_parquet(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        """The orchard rows found in the block: one row per orchard row with its line (GeoParquet)."""
        _, path = _results(store, settings, tenant, job_id, "rows.parquet")
        return _file(_require(path, "rows.parquet"), "application/vnd.apache.parquet", f"rows-{job_id}.parquet")

    @v1.api_route("/jobs/{job_id}/gaps.parquet", methods=["GET", "HEAD"], tags=["results"], responses={**parquet, **unfinished}, response_class=FileResponse)
    def job_gaps_parquet(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        """The empty planting slots between two trees of a row (GeoParquet points)."""
        _, path = _results(store, settings, tenant, job_id, "gaps.parquet")
        return _file(_require(path, "gaps.parquet"), "application/vnd.apache.parquet", f"gaps-{job_id}.parquet")

    @v1.api_route("/jobs/{job_id}/points.parquet", methods=["GET", "HEAD"], tags=["results"], responses={**parquet, **unfinished}, response_class=FileResponse)
    def job_points_parquet(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        _, path = _results(store, settings, tenant, job_id, "points.parquet")
        return _file(_require(path, "points.parquet"), "application/vnd.apache.parquet", f"points-{job_id}.parquet")

    @v1.api_route(
        "/jobs/{job_id}/trees.csv",
        methods=["GET", "HEAD"],
        tags=["results"],
        responses={200: {"content": {"text/csv": {}}, "description": "one row per tree"}, **unfinished},
        response_class=FileResponse,
    )
    def job_trees_csv(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        _, trees = _results(store, settings, tenant, job_id, "trees.parquet")
        csv_path = job_dir(settings, job_id) / "trees.csv"
        if not csv_path.exists():
            reports.write_trees_csv(_require(trees, "trees.parquet"), csv_path)
        return _file(csv_path, "text/csv", f"trees-{job_id}.csv")

    @v1.get(
        "/jobs/{job_id}/report",
        tags=["results"],
        response_class=HTMLResponse,
        responses={200: {"content": {"text/html": {}}, "description": "per-tree report with a map"}, **unfinished},
    )
    def job_report(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        job, _ = _results(store, settings, tenant, job_id, "trees.parquet")
        with report_lock:
            path = ensure_report(store, settings, job)
        return HTMLResponse(path.read_text(encoding="utf-8"))

    @v1.api_route(
        "/jobs/{job_id}/map.png",
        methods=["GET", "HEAD"],
        tags=["results"],
        response_class=FileResponse,
        responses={200: {"content": {"image/png": {}}, "description": "map of the block with numbered trees"}, **unfinished},
    )
    def job_map(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        job, _ = _results(store, settings, tenant, job_id, "trees.parquet")
        with report_lock:
            ensure_report(store, settings, job)
        return _file(_require(job_dir(settings, job_id) / "map.png", "map"), "image/png", f"map-{job_id}.png")

    # schedules ---------------------------------------------------------------------------

    @v1.post("/schedules", response_model=Schedule, status_code=201, tags=["schedules"], summary="Register an inbox and a cron schedule",
             responses=json_body)
    def create_schedule(body: ScheduleCreate, request: Request, response: Response, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        cron = validate_cron(body.cron)
        # a tenant's inboxes lie in its own folder: no other farm's captures, no server files
        inbox = validate_inbox(body.inbox, root=tenant_inbox_root(settings, tenant["name"]), root_label="this tenant's inbox folder")
        check_inbox_use(inbox, settings=settings, store=store, tenant_id=tenant["id"])
        tiling = _checked_tiling(body.params, body.tiling)  # as a job would: refused now, not every night
        rec = store.create_schedule(
            tenant_id=tenant["id"],
            inbox=str(inbox),
            cron=cron,
            params=body.params.model_dump(),
            tiling=tiling,
            next_run_at=next_run_time(cron, datetime.now().astimezone()).timestamp(),
        )
        clock = request.app.state.clock
        if clock is not None:
            clock.wake()
        response.headers["Location"] = f"/v1/schedules/{rec['id']}"
        return schedule_out(rec)

    @v1.get("/schedules", response_model=list[Schedule], tags=["schedules"])
    def list_schedules(tenant: TenantDep, store: StoreDep):
        return [schedule_out(s) for s in store.list_schedules(tenant["id"])]

    @v1.get("/schedules/{schedule_id}", response_model=Schedule, tags=["schedules"])
    def get_schedule(schedule_id: str, tenant: TenantDep, store: StoreDep):
        return schedule_out(store.get_schedule(tenant["id"], schedule_id))

    @v1.patch("/schedules/{schedule_id}", response_model=Schedule, tags=["schedules"], summary="Pause, resume or change a schedule",
              responses=json_body)
    def update_schedule(schedule_id: str, body: ScheduleUpdate, request: Request, tenant: TenantDep, store: StoreDep):
        rec = store.update_schedule(tenant["id"], schedule_id, lambda current: schedule_changes(current, body))
        clock = request.app.state.clock
        if clock is not None:
            clock.wake()
        return schedule_out(rec)

    @v1.delete("/schedules/{schedule_id}", status_code=204, tags=["schedules"], response_class=Response)
    def delete_schedule(schedule_id: str, tenant: TenantDep, store: StoreDep):
        store.delete_schedule(tenant["id"], schedule_id)
        return Response(status_code=204)

    @v1.post("/schedules/{schedule_id}/run", response_model=ScheduleRun, tags=["schedules"], summary="Scan the inbox now")
    def run_schedule_now(schedule_id: str, request: Request, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
        sched = store.get_schedule(tenant["id"], schedule_id)
        result = run_schedule(store, settings, sched)
        if result["jobs"]:
            _wake_runner(request.app)
        if result["waiting"] and request.app.state.clock is not None:
            request.app.state.clock.wake()  # the schedule now runs once they have settled
        return ScheduleRun(**result)

    app.include_router(v1)
    web.install(app)
    return app


def _checked_tiling(params: PipelineParams, tiling: Tiling | None, *, api: bool = True) -> dict | None:
    """The tiling of a job or schedule as stored; ParameterError (422) when its buffer is
    below the parameters' reach or its tiles so small that each point would be copied
    into too many of them (the command line's check, in the request's words unless
    ``api`` is False)."""
    if tiling is None:
        return None
    try:
        check_tiling(tiling.tile_size, tiling.buffer, params.reach())
    except ParameterError as exc:
        if not api:
            raise
        raise ParameterError(api_wording(str(exc))) from None
    return tiling.model_dump()


def schedule_changes(sched: dict, body: ScheduleUpdate, *, now: datetime | None = None, api: bool = True) -> dict[str, Any]:
    """The store changes of a PATCH of ``sched``, checked as at creation (ParameterError:
    422; in the command line's words unless ``api``). A new cron, or a resume, starts
    from the next cron time after ``now``: runs missed while paused are not made up."""
    given = body.model_fields_set
    changes: dict[str, Any] = {}
    cron = sched["cron"]
    if "cron" in given:
        cron = changes["cron"] = validate_cron(body.cron)
    params = PipelineParams(**sched["params"])
    if "params" in given:
        params = body.params
        changes["params"] = params.model_dump()
    if "tiling" in given or "params" in given:
        tiling = body.tiling if "tiling" in given else (Tiling(**sched["tiling"]) if sched["tiling"] else None)
        changes["tiling"] = _checked_tiling(params, tiling, api=api)
    if "paused" in given:
        changes["paused"] = body.paused
    paused = changes.get("paused", bool(sched["paused"]))
    if paused:
        changes["next_run_at"] = None
    elif "cron" in changes or bool(sched["paused"]):
        changes["next_run_at"] = next_run_time(cron, now or datetime.now().astimezone()).timestamp()
    return changes


def _wake_runner(app: FastAPI) -> None:
    runner = getattr(app.state, "runner", None)
    if runner is not None:
        runner.wake()
