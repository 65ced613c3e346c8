"""The HTTP service's app: `create_app(settings)` wires the job store, the job runner and
the schedule clock into a FastAPI app.

This module holds wiring only: the routes are in `service.api` (one module per
resource) and `service.web` (the browser's pages), the work in `service.db`,
`service.runner`, `service.schedules` and `service.reports`. OpenAPI docs are at
``/docs``. Every ``/v1`` request needs ``Authorization: Bearer <token>``; a tenant sees
only its own resources (anything else is 404). Errors are JSON ``{"detail": ...}``
(see `service.errors`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading

from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool

from pipeline.errors import ParameterError
from service import tempfiles, web
from service.api import openapi, routes_health, v1_router
from service.api.bodies import JsonShape
from service.api.deps import wake_runner
from service.api.uploads import UPLOAD_SLACK, BodyLimit
from service.db.jobstore import Store
from service.errors import install_error_handlers
from service.headers import SecurityHeaders
from service.jobfolders import job_dir
from service.permissions import private_dir, tighten
from service.reports.outputs import ensure_report
from service.runner import Runner, drop_work, hold_runner_lock, sweep_work
from service.schedules import ScheduleClock
from service.settings import Settings
from service.webhooks import WebhookSender, job_event
from workers.workstore import check_work_url

log = logging.getLogger("orchard.service")


def create_app(settings: Settings) -> FastAPI:
    """The API app. Starting it (lifespan) re-queues interrupted jobs and starts the runner and the schedule clock."""
    _check_work_dir(settings)
    private_dir(settings.data_dir)
    # the one process that runs this folder's jobs and schedules (a second one is refused)
    runner_lock = hold_runner_lock(settings.data_dir) if settings.runner or settings.scheduling else None
    store = Store(settings.store_path)
    report_lock = threading.Lock()  # a report is drawn once, whether a request or the runner asks first

    def after_done(job: dict, **drawing) -> None:  # drawing: the runner's sample and where it draws (ensure_report)
        with report_lock:
            ensure_report(store, settings, job, **drawing)
        tighten(job_dir(settings, job["id"]))  # results are the farm's: whoever wrote them (a remote worker)

    app = FastAPI(
        title="Orchard service",
        version=routes_health.API_VERSION,
        description="Upload LiDAR blocks of orchards, run per-tree jobs on dask workers, "
        "schedule overnight processing of capture inboxes, download per-tree results and reports.",
        lifespan=_lifespan(settings, store, runner_lock, after_done),
        docs_url=None,  # served by service.web from vendored files: they render offline
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.store = store
    app.state.runner = None
    app.state.clock = None
    app.state.webhooks = None

    def notify_job(job: dict) -> None:
        if job_event(store, job) and app.state.webhooks is not None:
            app.state.webhooks.wake()

    app.state.notify_job = notify_job
    app.state.report_lock = report_lock
    install_error_handlers(app)
    openapi.install(app)
    _add_middleware(app, settings)
    app.include_router(routes_health.router)
    app.include_router(v1_router())
    web.install(app)
    return app


def warm_routes(app: FastAPI) -> None:
    """Match a path no route has against every route of ``app``.

    FastAPI builds a router's request models when a request first reaches it: 0.7-1.4 s on
    the first request after a start (measured on this machine), longer than a 1 s health
    probe waits. ``orchard serve`` calls this before it listens, so no user pays it.
    """
    scope = {"type": "http", "path": "/\x00warm-up", "method": "GET", "root_path": "", "headers": [], "query_string": b""}
    for route in app.router.routes:
        route.matches(scope)


def _check_work_dir(settings: Settings) -> None:
    """ParameterError naming ``ORCHARD_WORK_DIR`` when this process runs jobs and the
    work store is not one its workers share."""
    if settings.work_dir and settings.runner:  # the runner's jobs would each fail on it
        try:
            check_work_url(settings.work_dir, shared=True)
        except ParameterError as exc:
            raise ParameterError("ORCHARD_WORK_DIR: " + exc.message, hint=exc.hint, param=exc.param, value=exc.value) from None


def _lifespan(settings: Settings, store: Store, runner_lock, after_done):
    """The app's lifespan: the data folder made ready, then the runner, the webhook sender
    and the schedule clock started (those ``settings`` asks for); all stopped at the end."""

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        await _prepare_data_dir(settings, store, runner_lock)
        _start_threads(app, settings, store, after_done)
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
            if app.state.webhooks is not None:
                await run_in_threadpool(app.state.webhooks.stop)
            store.close()
            if runner_lock is not None:
                runner_lock.close()

    return lifespan


async def _prepare_data_dir(settings: Settings, store: Store, runner_lock) -> None:
    """The data folder's sub-folders private, a crash's leftovers swept and, in the process
    that runs its jobs, the jobs a shutdown interrupted re-queued."""
    log.info("data folder %s (tokens for this server: orchard tokens create --tenant NAME --data-dir %s)",
             settings.data_dir, settings.data_dir)
    for d in (settings.blocks_dir, settings.jobs_dir, settings.tmp_dir):
        private_dir(d)
    # a folder written by an earlier version, or copied in: the farms' inboxes stay as they are
    await run_in_threadpool(tighten, settings.data_dir, skip=[settings.http_inbox_root])
    tempfiles.sweep(settings.tmp_dir)  # uploads a crash interrupted (not those of live processes)
    if runner_lock is not None:  # no other process runs jobs here: a "running" job is an orphan
        for job_id in store.jobs.cancel_interrupted():  # asked to stop before the last shutdown
            drop_work(settings, job_id)
        n = store.jobs.requeue_running(max_crashes=settings.max_crashes)
        if n:
            log.info("re-queued %d job(s) interrupted by the last shutdown", n)
        await run_in_threadpool(sweep_work, settings, store)  # failed just now, or a crash cut the deletion short


def _start_threads(app: FastAPI, settings: Settings, store: Store, after_done) -> None:
    """The runner, the webhook sender and the schedule clock this process runs, started."""
    if settings.runner:
        app.state.runner = Runner(store, settings, after_done=after_done, on_final=app.state.notify_job)
        app.state.runner.start()
    if settings.runner or settings.scheduling:  # the process whose threads make the events delivers them
        app.state.webhooks = WebhookSender(store, settings)
        app.state.webhooks.start()
    if settings.scheduling:
        app.state.clock = ScheduleClock(store, settings, on_jobs=lambda: wake_runner(app))
        app.state.clock.start()


def _add_middleware(app: FastAPI, settings: Settings) -> None:
    """The request middleware; the last added is the outermost."""
    app.add_middleware(JsonShape)  # inside BodyLimit: it reads a body already bounded in size
    app.add_middleware(
        BodyLimit,
        default=settings.max_request_kb * 1024,
        upload=settings.max_upload_bytes + UPLOAD_SLACK,
        upload_mb=settings.max_upload_mb,
    )
    app.add_middleware(SecurityHeaders)  # outermost: on every response, the errors of the others too
