"""The background job runner of ``orchard serve``.

One thread takes queued jobs from the store one at a time (`JobQueue.claim_next`: fair
share between tenants, oldest first within one), and runs
each with `workers.job.run_job` on a dask client it owns (an embedded `LocalCluster`,
or the cluster at ``settings.scheduler``; created when the first job arrives). Tiles
done / total go to the store through the progress callback; a cancel request sets the
job's `threading.Event`. The outcome of every job is one store transaction: ``done``
with its outcome and timings, ``failed`` with a one-line error (a domain error's own
message; for anything unexpected a short message, the traceback only in the log), or
``cancelled``. A capture of an orchard block is told its previous capture when it
starts, and its record is kept before it is done (`service.seasons`). A job left
``running`` when the process dies is re-queued by `JobQueue.requeue_running` at the next
start, as a crash (not an attempt); one during which the process has died
``settings.max_crashes`` times is failed there instead.

One process per data folder runs jobs and schedules: it holds `hold_runner_lock`'s
lock for as long as it lives, and only it re-queues ``running`` jobs at its start
(a second service on the folder, started as the runner too, is refused; started as API
only, it leaves the other's running job alone).
"""

from __future__ import annotations

import dataclasses
import fcntl
import logging
import os
import threading
import time
from pathlib import Path
from typing import IO, Any, Callable

import numpy as np

from pipeline.errors import OrchardError, ParameterError
from pipeline.jobparams import TilingParams
from pipeline.params import PipelineParams
from service import seasons
from service.background import Background
from service.db.errors import NotFoundError
from service.db.jobstore import Store
from service.jobfolders import job_dir, work_dir_of
from service.reports.outputs import job_block_name
from service.settings import Settings
from service.wording import api_words, disk_full
from workers.workstore import WorkStore

log = logging.getLogger("orchard.runner")


class ClusterUnavailable(RuntimeError):
    """The dask cluster could not be started or reached (the job fails; the next one tries again)."""


RUNNER_LOCK = "runner.lock"
#: how often [s] a running job looks in the store for a cancel made by another process
CANCEL_POLL_S = 1.0
#: how often [s] the runner looks at the dask cluster's workers (and replaces lost ones)
DOCTOR_POLL_S = 2.0


def hold_runner_lock(data_dir: Path) -> IO:
    """Take the data folder's runner lock (flock on ``<data dir>/runner.lock``) for this
    process; keep the returned file open for as long as it runs jobs and schedules.

    Raises
    ------
    ParameterError
        Another live process holds it.
    """
    path = Path(data_dir) / RUNNER_LOCK
    fh = open(path, "a+")  # noqa: SIM115 - the open file is the lock
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fh.seek(0)
        holder = fh.read().strip() or "another process"
        fh.close()
        raise ParameterError(
            f"{holder} already runs the jobs and schedules of data folder {Path(data_dir)}; give this service "
            "another --data-dir, or start it to serve the API only (ORCHARD_RUNNER=false ORCHARD_SCHEDULING=false)"
        ) from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"orchard service pid {os.getpid()}\n")
    fh.flush()
    return fh


def drop_work(settings: Settings, job_id: str) -> None:
    """Delete a job's work store, and its result folder if that is left empty."""
    out_dir = job_dir(settings, job_id)
    try:
        WorkStore(work_dir_of(settings, job_id)).remove()
        if out_dir.is_dir() and not any(out_dir.iterdir()):
            out_dir.rmdir()
    except Exception as exc:  # noqa: BLE001 - leftover tiles must not change the job's outcome
        log.warning("job %s: could not delete its tiles: %s", job_id, exc)


def sweep_work(settings: Settings, store: Store) -> list[str]:
    """Delete the work stores (tiles) left by jobs that have ended: failed at start-up
    after too many crashes (`JobQueue.requeue_running`), or whose deletion a crash cut
    short. Only jobs this store knows as done, failed or cancelled are touched (a shared
    work folder may hold other services' jobs). Returns the ids swept."""
    if settings.work_dir:
        try:
            candidates = WorkStore(settings.work_dir).entries()
        except Exception as exc:  # noqa: BLE001 - an unreachable work store: the next start looks again
            log.warning("cannot list the work store %s: %s", settings.work_dir, exc)
            return []
    else:
        candidates = sorted(p.parent.name for p in settings.jobs_dir.glob("*/_work"))
    swept = []
    for job_id in candidates:
        try:
            state = store.jobs.get_any_tenant(job_id)["state"]
        except NotFoundError:
            continue
        if state in ("done", "failed", "cancelled"):
            drop_work(settings, job_id)
            swept.append(job_id)
    if swept:
        log.info("deleted the tiles of %d ended job(s)", len(swept))
    return swept


def _is_cancel(exc: BaseException) -> bool:
    return type(exc).__name__ in ("JobCancelled", "CancelledError")


def _lost_scheduler(exc: BaseException) -> bool:
    """Whether ``exc`` says the dask scheduler went away during the job: its futures
    cancelled, or the connection closed while results were fetched (CommClosedError
    from a gather)."""
    from distributed.comm.core import CommClosedError

    return (isinstance(exc, CommClosedError) or type(exc).__name__ == "FuturesCancelledError"
            or "scheduler-connection-lost" in str(exc))


def _short(exc: BaseException, limit: int = 300) -> str:
    text = " ".join((api_words(exc) if isinstance(exc, OrchardError) else str(exc)).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _jsonable(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


class Runner(Background):
    """Runs queued jobs one at a time on a dask client owned by this thread."""

    def __init__(
        self,
        store: Store,
        settings: Settings,
        *,
        client_factory: Callable[[], Any] | None = None,
        after_done: Callable[[dict], None] | None = None,
        on_final: Callable[[dict], None] | None = None,
    ) -> None:
        super().__init__("orchard-runner")
        self.store = store
        self.settings = settings
        self._client_factory = client_factory or self._default_client
        self._after_done = after_done
        self._on_final = on_final  # told every job the runner took, as it left it (webhooks)
        self._client = None
        self._unreachable = False  # the last attempt to start or reach the cluster failed
        self._lock = threading.Lock()
        self._current: str | None = None
        self._cancel: threading.Event | None = None
        self.dashboard_link: str | None = None

    # -- control, from other threads ----------------------------------------------

    def cancel(self, job_id: str) -> None:
        """Ask the job ``job_id`` to stop if it is the one running."""
        with self._lock:
            if self._current == job_id and self._cancel is not None:
                self._cancel.set()

    def stop(self, timeout: float | None = 30.0) -> None:
        """Stop taking jobs; interrupt the running one (it stays ``running`` and is re-queued at the next start)."""
        super().stop(timeout)

    def _before_join(self) -> None:
        with self._lock:
            if self._cancel is not None:
                self._cancel.set()

    def cluster_state(self) -> str:
        """'connected', 'not started', 'unreachable' (the last attempt to reach it failed;
        the next job tries again), or the dask client's own status (e.g. 'connecting'
        while it has lost its scheduler)."""
        client = self._client
        if client is None:
            return "unreachable" if self._unreachable else "not started"
        status = str(getattr(client, "status", "running"))
        return "connected" if status == "running" else status

    def cluster_workers(self) -> tuple[int, int | None] | None:
        """(workers connected, workers the cluster should have: None for an external
        one), or None while there is no cluster."""
        client = self._client
        if client is None:
            return None
        from workers.cluster import cluster_workers  # here: dask (~1 s) loads with the first cluster

        try:
            return cluster_workers(client)
        except Exception:  # noqa: BLE001 - a cluster closing meanwhile
            return None

    @property
    def current_job(self) -> str | None:
        return self._current

    def _doctor(self) -> None:
        """Every `DOCTOR_POLL_S`: replace the embedded cluster's lost workers (without a
        restart of the service), and say on the running job when it waits for workers."""
        from workers.cluster import heal_cluster  # here: dask (~1 s) loads with the first cluster

        noted: tuple[str, str | None] | None = None  # (job id, its error before the note)
        while not self._stopping.wait(DOCTOR_POLL_S):
            client = self._client
            try:
                if client is not None and self.settings.scheduler is None:
                    heal_cluster(client, self.settings.n_workers)
                counts, job_id = self.cluster_workers(), self._current
                if noted is not None and (noted[0] != job_id or not counts or counts[0] > 0):
                    self.store.jobs.set_note(noted[0], noted[1])
                    noted = None
                if noted is None and job_id is not None and counts is not None and counts[0] == 0:
                    before = self.store.jobs.get_any_tenant(job_id).get("error")
                    want = f" (it should have {counts[1]}; new ones are starting)" if counts[1] else ""
                    self.store.jobs.set_note(job_id, f"waiting for dask workers: the cluster has none{want}")
                    noted = (job_id, before)
            except Exception as exc:  # noqa: BLE001 - look again next time
                log.warning("runner: cannot look after the dask cluster: %s", exc)

    # -- the thread ------------------------------------------------------------------

    def _default_client(self):
        from workers.cluster import make_client  # here: dask (~1 s) loads with the first cluster

        return make_client(
            self.settings.scheduler,
            n_workers=self.settings.n_workers,
            threads_per_worker=self.settings.threads_per_worker,
            dashboard=self.settings.dashboard,
            timeout=f"{self.settings.scheduler_timeout_s}s",
            host=self.settings.dask_host,
        )

    def _get_client(self):
        client = self._client
        # a client still "connecting" has lost its scheduler: start afresh, so that a job
        # finds out at once (and clearly) whether the cluster is back
        if client is not None and getattr(client, "status", "running") != "running":
            self._close_client()
            client = None
        if client is None:
            where = self.settings.scheduler or f"an embedded LocalCluster of {self.settings.n_workers} worker(s)"
            log.info("starting the dask client (%s)", where)
            try:
                client = self._client_factory()
            except Exception as exc:  # noqa: BLE001 - becomes the job's error; the next job tries again
                self._unreachable = True
                why = _short(exc, 600)
                raise ClusterUnavailable(f"cannot start or reach the dask cluster ({where}): {why}") from exc
            self._client = client
            self._unreachable = False
            if self.settings.dashboard:
                self.dashboard_link = getattr(client, "dashboard_link", None)
                log.info("dask dashboard: %s", self.dashboard_link)
        return client

    def _close_client(self) -> None:
        client, self._client = self._client, None
        if client is None:
            return
        try:
            if self.settings.scheduler is None:
                from workers.cluster import close_client  # here: dask (~1 s) loads with the first cluster

                close_client(client)  # the embedded LocalCluster goes too
            else:
                client.close()
        except Exception as exc:  # noqa: BLE001 - shutting down anyway
            log.debug("closing dask client: %s", exc)

    def run(self) -> None:
        threading.Thread(target=self._doctor, name="orchard-cluster-doctor", daemon=True).start()
        try:
            while not self._stopping.is_set():
                try:
                    job = self.store.jobs.claim_next()
                except Exception as exc:  # noqa: BLE001 - e.g. the store briefly locked; try again
                    log.warning("runner: cannot read the queue: %s", exc)
                    job = None
                if job is None:
                    self._wake.wait(self.settings.runner_poll_s)
                    self._wake.clear()
                    continue
                try:
                    left = self.run_job(job)
                except Exception as exc:  # e.g. the store failed while recording (logged); keep running
                    log.error("runner: job %s could not be recorded", job["id"], exc_info=exc)
                    try:  # not left "running" (and waited on) for good
                        left = self.store.jobs.finish(job["id"], "failed", error=f"internal error ({type(exc).__name__}) "
                                              "while recording the job's outcome; see the service log")
                    except Exception as again:  # noqa: BLE001 - the store itself is failing; the next start re-queues it
                        log.error("runner: job %s stays running: %s", job["id"], again)
                    continue
                if self._on_final is not None:
                    try:
                        self._on_final(left)
                    except Exception as exc:  # noqa: BLE001 - a webhook's bookkeeping does not stop the runner
                        log.warning("runner: job %s: its webhooks could not be queued: %s", job["id"], exc)
        finally:
            self._close_client()


    def _after_cluster_failure(self, job: dict[str, Any], message: str, *, advice: str) -> dict[str, Any]:
        """A job the dask cluster failed: queued again after ``retry_delay_s`` while it
        has attempts left (``job_retries``), failed for good (with ``advice``) after the last."""
        attempts = int(job.get("attempts") or 1)
        if attempts > self.settings.job_retries:
            tries = f" (attempt {attempts}, the last)" if attempts > 1 else ""
            return self.store.jobs.finish(job["id"], "failed", error=message + tries + advice)
        at = time.time() + self.settings.retry_delay_s
        when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(at))
        log.warning("job %s: attempt %d failed (%s); queued again from %s", job["id"], attempts, message, when)
        note = f"attempt {attempts} of {self.settings.job_retries + 1} failed: {message}; trying again from {when}"
        return self.store.jobs.retry(job["id"], error=note, retry_at=at)

    def _watch_cancel(self, job_id: str, cancel: threading.Event, done: threading.Event) -> None:
        """Set ``cancel`` once the store says the job is to be cancelled: a cancel made
        through another API process reached the job only when a tile finished (minutes
        while the cluster waited for workers)."""
        while not done.wait(CANCEL_POLL_S) and not cancel.is_set():
            try:
                if self.store.jobs.cancel_requested(job_id):
                    cancel.set()
            except Exception as exc:  # noqa: BLE001 - the store briefly locked: look again
                log.debug("job %s: cannot read its cancel flag: %s", job_id, exc)

    def run_job(self, job: dict[str, Any]) -> dict[str, Any]:
        """Run one claimed (``running``) job to a final state; returns the stored job."""
        cancel = threading.Event()
        with self._lock:
            self._current, self._cancel = job["id"], cancel
        if self.store.jobs.cancel_requested(job["id"]):
            cancel.set()
        watching = threading.Event()
        threading.Thread(target=self._watch_cancel, args=(job["id"], cancel, watching), daemon=True,
                         name=f"orchard-cancel-{job['id'][:8]}").start()
        last_check = [0.0]

        def progress(done: int, total: int) -> None:
            self.store.jobs.set_progress(job["id"], int(done), int(total))
            now = time.monotonic()
            if now - last_check[0] > 0.5:
                last_check[0] = now
                if self.store.jobs.cancel_requested(job["id"]):
                    cancel.set()

        out_dir = job_dir(self.settings, job["id"])
        t0 = time.perf_counter()
        block = None
        try:
            from workers.job import run_job
            from workers.jobspec import JobSpec

            block = self.store.blocks.get(job["tenant_id"], job["block_id"])
            spec = JobSpec(
                input_path=block["path"],
                out_dir=str(out_dir),
                params=PipelineParams.model_validate(job["params"]),
                # the request's tiling; the service's settings give the rest
                tiling=TilingParams(**(job.get("tiling") or {}), worker_memory=self.settings.worker_memory_gb),
                work_dir=work_dir_of(self.settings, job["id"]),
                # a capture of an orchard block: its previous capture, looked up now
                **seasons.spec_fields(seasons.capture_job_fields(self.store, self.settings, job)),
            )
            out_dir.mkdir(parents=True, exist_ok=True)
            client = self._get_client()
            outcome = run_job(spec, client=client, progress=progress, cancel=cancel)
            record = _jsonable(outcome)
            record.pop("trees", None)  # the per-tree table is in trees.parquet
            record.pop("sample", None)  # points for a report's map, not a record
            timings = dict(record.get("timings") or {})
            timings.setdefault("total", round(time.perf_counter() - t0, 3))
            drop_work(self.settings, job["id"])  # tiles of a finished job are not needed again
            if self.store.orchard_blocks.capture_of_job(job["tenant_id"], job["id"]) is not None:
                self.store.orchard_blocks.set_capture_record(job["id"], seasons.capture_record(out_dir))
            done = self.store.jobs.finish(job["id"], "done", outcome=record, timings=timings)
            if self._after_done is not None:
                try:
                    self._after_done(done)
                except Exception as exc:  # noqa: BLE001 - a report problem does not fail the job
                    log.warning("job %s: post-processing failed: %s", job["id"], exc)
            return done
        except BaseException as exc:  # noqa: BLE001 - every outcome is recorded
            if _is_cancel(exc) or (cancel.is_set() and not isinstance(exc, OrchardError)):
                if self._stopping.is_set() and not self.store.jobs.cancel_requested(job["id"]):
                    log.info("job %s interrupted by shutdown; it runs again at the next start", job["id"])
                    self.store.jobs.release(job["id"])
                    return self.store.jobs.get(job["tenant_id"], job["id"])
                drop_work(self.settings, job["id"])  # the service never resumes a cancelled job
                return self.store.jobs.finish(job["id"], "cancelled", error="cancelled on request")
            # the cluster failed the job, not the job itself: worth another attempt, and
            # this advice after the last
            retry_advice: str | None = None
            if isinstance(exc, OrchardError):
                # without the command line's advice to resume from the work store: the
                # service deletes a failed job's work store and never resumes it
                named = {} if block is None else {"block_path": block["path"], "filename": job_block_name(job, block)}
                message = api_words(exc, hint=not hasattr(exc, "reason"), **named) or type(exc).__name__
                if type(exc).__name__ == "ClusterLost":
                    retry_advice = "; start dask workers and submit the job again"
            elif isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            elif isinstance(exc, ClusterUnavailable):
                retry_advice = ""
                message = str(exc)
            elif disk_full(exc):
                log.error("job %s: the disk is full (%s)", job["id"], exc)
                retry_advice = "; free disk space on the server and submit it again"
                message = "the server ran out of disk space during the job"
            elif _lost_scheduler(exc):
                self._close_client()  # the next job connects afresh
                retry_advice = "; submit it again once the cluster is back"
                message = "lost the connection to the dask scheduler during the job"
            else:
                log.error("job %s failed unexpectedly", job["id"], exc_info=exc)
                message = f"internal error ({type(exc).__name__}): {_short(exc)}"
            drop_work(self.settings, job["id"])  # the service never resumes a job: its tiles are not needed
            if retry_advice is not None:
                return self._after_cluster_failure(job, message, advice=retry_advice)
            return self.store.jobs.finish(job["id"], "failed", error=message)
        finally:
            watching.set()
            with self._lock:
                self._current, self._cancel = None, None
