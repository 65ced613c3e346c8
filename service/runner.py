"""The background job runner of ``orchard serve``.

One thread takes queued jobs from the store one at a time (`JobQueue.claim_next`: fair
share between tenants, oldest first within one), and runs
each with `workers.job.run_job` on a dask client it owns (an embedded `LocalCluster`,
or the cluster at ``settings.scheduler``; created when the first job arrives). Tiles
done / total go to the store through the progress callback; a cancel request sets the
job's `threading.Event`. The outcome of every job is one store transaction: ``done``
with its outcome and timings, ``failed`` with its failure's kind and fields
(:func:`service.failures.classify` sorts what the run raised; each edge words them; the
traceback of anything unexpected goes only to the log), queued again after a failure of
the cluster, or ``cancelled``. `Runner.run_job` takes these steps one method each. A capture of an orchard block is told its previous capture when it
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

from pipeline.errors import ParameterError
from pipeline.jobparams import JobParams
from service import seasons
from service.background import Background
from service.db.errors import NotFoundError
from service.db.jobstore import Store
from service.failures import ClusterUnavailable, Outcome, classify, short_text
from service.jobfolders import job_dir, work_dir_of
from service.reports.outputs import job_block_name
from service.settings import Settings
from service.wording import failure_words
from workers.runoptions import RunOptions
from workers.workstore import WorkStore

log = logging.getLogger("orchard.runner")


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


def _on_worker(client) -> Callable[..., Any] | None:
    """``draw(fn, **kwargs)``: ``fn`` as a task on a worker of ``client`` (None without one),
    so that the service process never holds what a report reads and draws."""
    if client is None:
        return None
    from workers.dispatch import run_task  # here: dask (~1 s) loads with the first cluster

    return lambda fn, **kwargs: run_task(client, fn, key="orchard-report", **kwargs)


class Runner(Background):
    """Runs queued jobs one at a time on a dask client owned by this thread."""

    def __init__(
        self,
        store: Store,
        settings: Settings,
        *,
        client_factory: Callable[[], Any] | None = None,
        after_done: Callable[..., None] | None = None,  # (job, sample=..., draw=...): ensure_report's
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
                raise ClusterUnavailable(where, short_text(exc, 600)) from exc
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
                        left = self.store.jobs.finish(job["id"], "failed", error_kind="unrecorded",
                                                     error_fields={"exception": type(exc).__name__})
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


    # -- one job, step by step --------------------------------------------------------

    def run_job(self, job: dict[str, Any]) -> dict[str, Any]:
        """Run one claimed (``running``) job to a final state; returns the stored job."""
        cancel, watching = self._watch(job["id"])
        block = None
        try:
            block = self.store.blocks.get(job["tenant_id"], job["block_id"])
            return self._run_to_done(job, block, cancel)
        except BaseException as exc:  # noqa: BLE001 - every outcome is recorded
            return self._record_failure(job, block, exc, cancel)
        finally:
            watching.set()
            with self._lock:
                self._current, self._cancel = None, None

    def _watch(self, job_id: str) -> tuple[threading.Event, threading.Event]:
        """The running job's cancel event (set by `cancel`, or by a cancel the store holds)
        and the event that ends its watch (`_watch_cancel`, on a thread of its own)."""
        cancel, watching = threading.Event(), threading.Event()
        with self._lock:
            self._current, self._cancel = job_id, cancel
        if self.store.jobs.cancel_requested(job_id):
            cancel.set()
        threading.Thread(target=self._watch_cancel, args=(job_id, cancel, watching), daemon=True,
                         name=f"orchard-cancel-{job_id[:8]}").start()
        return cancel, watching

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

    def _progress(self, job_id: str, cancel: threading.Event) -> Callable[[int, int], None]:
        """The job's progress callback: tiles done / total to the store, and a look at its
        cancel flag at most every half second."""
        last_check = [0.0]

        def progress(done: int, total: int) -> None:
            self.store.jobs.set_progress(job_id, int(done), int(total))
            now = time.monotonic()
            if now - last_check[0] > 0.5:
                last_check[0] = now
                if self.store.jobs.cancel_requested(job_id):
                    cancel.set()

        return progress

    def _spec(self, job: dict[str, Any], block: dict[str, Any]):
        """The job's `JobSpec`: its parameters as stored, how the service runs jobs (its
        settings), and for a capture of an orchard block, its previous capture (looked up
        now: the one before may have finished meanwhile)."""
        from workers.jobspec import JobSpec

        return JobSpec(
            input_path=block["path"],
            out_dir=str(job_dir(self.settings, job["id"])),
            job=JobParams.model_validate(job["job"]),
            run=RunOptions(workers=self.settings.n_workers, worker_memory=self.settings.worker_memory_gb),
            work_dir=work_dir_of(self.settings, job["id"]),
            **seasons.spec_fields(seasons.capture_job_fields(self.store, self.settings, job)),
        )

    def _run_to_done(self, job: dict[str, Any], block: dict[str, Any], cancel: threading.Event) -> dict[str, Any]:
        """Run the job on the cluster and record it done (raises what the run raised)."""
        from workers.job import run_job

        t0 = time.perf_counter()
        spec = self._spec(job, block)
        Path(spec.out_dir).mkdir(parents=True, exist_ok=True)
        client = self._get_client()
        outcome = run_job(spec, client=client, progress=self._progress(job["id"], cancel), cancel=cancel)
        return self._record_done(job, outcome, t0, client)

    def _record_done(self, job: dict[str, Any], outcome, t0: float, client=None) -> dict[str, Any]:
        """Keep a finished job's outcome and timings (and a capture's record), delete its
        tiles, and run the post-processing (the report: drawn by a task on ``client``'s
        workers, from the job's sample of its points), whose failure fails no job."""
        # the per-tree table is in trees.parquet; the sample is points for a report's map, not a record
        record = _jsonable(dataclasses.replace(outcome, trees=None, sample=None))
        record.pop("trees", None)
        record.pop("sample", None)
        timings = dict(record.get("timings") or {})
        timings.setdefault("total", round(time.perf_counter() - t0, 3))
        drop_work(self.settings, job["id"])  # tiles of a finished job are not needed again
        if self.store.orchard_blocks.capture_of_job(job["tenant_id"], job["id"]) is not None:
            self.store.orchard_blocks.set_capture_record(job["id"], seasons.capture_record(job_dir(self.settings, job["id"])))
        done = self.store.jobs.finish(job["id"], "done", outcome=record, timings=timings)
        if self._after_done is not None:
            try:
                self._after_done(done, sample=outcome.sample, draw=_on_worker(client))
            except Exception as exc:  # noqa: BLE001 - a report problem does not fail the job
                log.warning("job %s: post-processing failed: %s", job["id"], exc)
        return done

    def _record_failure(self, job: dict[str, Any], block: dict[str, Any] | None, exc: BaseException,
                        cancel: threading.Event) -> dict[str, Any]:
        """Record what a failed run means (:func:`service.failures.classify`): cancelled,
        released at shutdown, queued again after a failure of the cluster, or failed."""
        outcome = classify(exc, cancelled=cancel.is_set())
        if outcome.kind == "exit":
            raise exc
        if outcome.kind == "cancelled":
            return self._record_cancel(job)
        if outcome.log == "traceback":
            log.error("job %s failed unexpectedly", job["id"], exc_info=exc)
        elif outcome.log == "line":
            log.error("job %s: %s (%s)", job["id"], failure_words(outcome.kind, outcome.fields), exc)
        if outcome.reconnect:
            self._close_client()  # the next job connects afresh
        fields = dict(outcome.fields)
        if block is not None and "message" in fields:  # a domain error names the block's file by its name
            fields.update(block_path=block["path"], block_name=job_block_name(job, block))
        drop_work(self.settings, job["id"])  # the service never resumes a job: its tiles are not needed
        if outcome.retry:
            return self._after_cluster_failure(job, Outcome(outcome.kind, fields))
        return self.store.jobs.finish(job["id"], "failed", error_kind=outcome.kind, error_fields=fields)

    def _record_cancel(self, job: dict[str, Any]) -> dict[str, Any]:
        """A cancelled job: cancelled for good, or, when the service is stopping and no
        one asked for the cancel, put back in the queue for its next start."""
        if self._stopping.is_set() and not self.store.jobs.cancel_requested(job["id"]):
            log.info("job %s interrupted by shutdown; it runs again at the next start", job["id"])
            self.store.jobs.release(job["id"])
            return self.store.jobs.get(job["tenant_id"], job["id"])
        drop_work(self.settings, job["id"])  # the service never resumes a cancelled job
        return self.store.jobs.finish(job["id"], "cancelled", error_kind="cancelled", error_fields={})

    def _after_cluster_failure(self, job: dict[str, Any], outcome: Outcome) -> dict[str, Any]:
        """A job the cluster (or the server) failed: queued again after ``retry_delay_s``
        while it has attempts left (``job_retries``), failed for good after the last."""
        attempts = int(job.get("attempts") or 1)
        fields = {**outcome.fields, "attempt": attempts}
        if attempts > self.settings.job_retries:
            return self.store.jobs.finish(job["id"], "failed", error_kind=outcome.kind, error_fields=fields)
        fields.update(attempts=self.settings.job_retries + 1, retry_at=time.time() + self.settings.retry_delay_s)
        log.warning("job %s: %s", job["id"], failure_words(outcome.kind, fields))
        return self.store.jobs.retry(job["id"], error_kind=outcome.kind, error_fields=fields, retry_at=fields["retry_at"])
