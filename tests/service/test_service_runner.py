"""The job runner's bookkeeping, with `run_job` replaced by fakes (no dask, no pipeline)."""

from __future__ import annotations

import threading
import time

import pytest
from distributed.client import CancelledFuturesGroup, FutureCancelledError, FuturesCancelledError
from distributed.comm.core import CommClosedError

from pipeline.errors import InputError, NoTreesError
from service.db.database import SCHEMA
from service.db.jobstore import Store
from service.runner import Runner
from service.wording import job_error
from service.settings import Settings

import workers.job as workers_job
import workers.jobspec as workers_jobspec
import workers.workstore as workers_workstore


@pytest.fixture()
def env(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", runner_poll_s=0.05, job_retries=0)
    store = Store(settings.store_path)
    tenant = store.accounts.ensure_tenant("farm")
    block, _ = store.blocks.insert(tenant_id=tenant["id"], sha256="ab" * 32, path=str(tmp_path / "b.laz"),
                                  filename="b.laz", size_bytes=1, info={})
    yield settings, store, tenant, block
    store.close()


def _queue(store, tenant, block, tiling=None):
    store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={"tiling": tiling or {}})
    return store.jobs.claim_next()


def test_done_records_outcome_and_progress(env, monkeypatch):
    settings, store, tenant, block = env
    seen = []

    def fake(spec, *, client, progress, cancel):
        assert spec.tiling.tile_size == 20.0 and spec.input_path == block["path"]
        for i in range(4):
            progress(i, 3)
            seen.append(store.jobs.get_any_tenant(job["id"])["tiles_done"])
        return workers_jobspec.JobOutcome(100, 3, 3, [], False, {"process": 1.0}, {"trees": "t"}, trees={"x": [1]})

    monkeypatch.setattr(workers_job, "run_job", fake)
    job = _queue(store, tenant, block, {"tile_size": 20.0, "buffer": None})
    after = []
    done = Runner(store, settings, client_factory=lambda: None, after_done=lambda job, **_: after.append(job)).run_job(job)
    assert done["state"] == "done" and done["tiles_done"] == 3 and done["tiles_total"] == 3
    assert seen == [0, 1, 2, 3]
    assert done["outcome"]["n_trees"] == 3 and "trees" not in done["outcome"]
    assert done["timings"]["process"] == 1.0 and after and after[0]["id"] == job["id"]


@pytest.mark.parametrize(
    "exc, expected",
    [
        (InputError("b.laz: truncated"), "b.laz: truncated"),
        (NoTreesError("no trees found"), "no trees found"),
        (ZeroDivisionError("division by zero"), "internal error (ZeroDivisionError): division by zero"),
        # the command line's advice to resume from the work store does not apply: the
        # service deletes a failed job's work store
        (workers_jobspec.ClusterLost("no dask worker for 120 s with 6 tiles to go",
                                 hint="; start workers and resume with --work /srv/work/abc --resume"),
         "no dask worker for 120 s with 6 tiles to go; start dask workers and submit the job again"),
        (workers_jobspec.TileFailed("tile 3 (core x 0.00..10.00, y 0.00..10.00, 99 points) failed after 3 attempts: "
                                "MemoryError: ", 3, hint="; its data is kept in /srv/work/abc (run the job's tiles "
                                "again with --work /srv/work/abc --resume)"),
         "tile 3 (core x 0.00..10.00, y 0.00..10.00, 99 points) failed after 3 attempts: MemoryError: "),
        (FuturesCancelledError([CancelledFuturesGroup([FutureCancelledError("k", "scheduler-connection-lost")],
                                                     reason="scheduler-connection-lost")]),
         "lost the connection to the dask scheduler during the job; submit it again once the cluster is back"),
        # a full disk is the server's to fix, not the job's: "internal error (OSError)" before
        (OSError(28, "No space left on device"),
         "the server ran out of disk space during the job; free disk space on the server and submit it again"),
        # the scheduler killed while results were fetched: a final "internal error" before
        (CommClosedError("in <TCP (closed) ConnectionPool.gather local=tcp://127.0.0.1:1>: Stream is closed"),
         "lost the connection to the dask scheduler during the job; submit it again once the cluster is back"),
    ],
)
def test_failures_keep_a_one_line_message(env, monkeypatch, exc, expected):
    settings, store, tenant, block = env

    def fake(spec, **kw):
        raise exc

    monkeypatch.setattr(workers_job, "run_job", fake)
    job = _queue(store, tenant, block)
    work = settings.jobs_dir / job["id"] / "_work"  # what a tiled job leaves when it stops
    workers_workstore.WorkStore(str(work)).claim()
    (work / "tiles").mkdir(parents=True)
    (work / "job.json").write_text("{}")
    failed = Runner(store, settings, client_factory=lambda: None).run_job(job)
    assert failed["state"] == "failed" and job_error(failed) == expected
    assert "Traceback" not in job_error(failed)
    assert not (settings.jobs_dir / job["id"]).exists()  # nothing left: the service never resumes a job


def test_a_client_that_lost_its_scheduler_is_replaced(env, monkeypatch):
    settings, store, tenant, block = env
    made = []

    class Client:
        def __init__(self):
            self.status = "running"
            made.append(self)

        def close(self):
            self.status = "closed"

    monkeypatch.setattr(workers_job, "run_job", lambda spec, *, client, progress, cancel: pytest.fail("x")
                        if client is not made[-1] else workers_jobspec.JobOutcome(1, 1, 1, [], False, {}, {}))
    runner = Runner(store, Settings(data_dir=settings.data_dir, scheduler="tcp://127.0.0.1:1"), client_factory=Client)
    assert runner.cluster_state() == "not started"
    assert runner.run_job(_queue(store, tenant, block))["state"] == "done"
    assert runner.cluster_state() == "connected"
    made[0].status = "connecting"  # the scheduler went away: distributed keeps trying to reconnect
    assert runner.cluster_state() == "connecting"  # what /healthz shows
    assert runner.run_job(_queue(store, tenant, block))["state"] == "done"
    assert len(made) == 2 and made[0].status == "closed"


def test_cluster_that_cannot_start_fails_the_job_clearly(env, monkeypatch):
    settings, store, tenant, block = env

    def broken():
        raise OSError("Timed out trying to connect to tcp://10.0.0.1:8786")

    monkeypatch.setattr(workers_job, "run_job", lambda *a, **k: pytest.fail("must not run"))
    runner = Runner(store, settings, client_factory=broken)
    failed = runner.run_job(_queue(store, tenant, block))
    assert failed["state"] == "failed" and job_error(failed).startswith("cannot start or reach the dask cluster")
    assert runner.cluster_state() == "unreachable"  # /healthz said "not started"


def test_a_job_the_cluster_failed_is_queued_again_later(env, monkeypatch):
    # the cluster cannot be reached twice (a scheduler restarting in the night), then is
    # back: the job waits out the delay each time and ends done on its third attempt
    settings, store, tenant, block = env
    settings = Settings(data_dir=settings.data_dir, job_retries=2, retry_delay_s=0.5)
    calls = []

    def flaky():
        calls.append(time.time())
        if len(calls) < 3:
            raise OSError("Timed out trying to connect to tcp://10.0.0.1:8786")
        return None

    monkeypatch.setattr(workers_job, "run_job", lambda spec, **kw: workers_jobspec.JobOutcome(9, 1, 1, [], False, {}, {}))
    runner = Runner(store, settings, client_factory=flaky)
    job = _queue(store, tenant, block)
    for attempt in (1, 2):
        again = runner.run_job(job)
        assert again["state"] == "queued" and again["attempts"] == attempt and again["tiles_done"] == 0
        assert job_error(again).startswith(f"attempt {attempt} of 3 failed: cannot start or reach the dask cluster")
        assert "trying again from" in job_error(again) and again["retry_at"] >= calls[-1] + 0.5
        assert store.jobs.claim_next() is None  # not before its time
        time.sleep(max(0.0, again["retry_at"] - time.time()) + 0.05)
        job = store.jobs.claim_next()
        assert job["id"] == again["id"] and job_error(job) is None and job["retry_at"] is None
    done = runner.run_job(job)
    assert done["state"] == "done" and done["attempts"] == 3 and job_error(done) is None


def test_the_last_attempt_fails_for_good_and_other_failures_at_once(env, monkeypatch):
    settings, store, tenant, block = env
    settings = Settings(data_dir=settings.data_dir, job_retries=1, retry_delay_s=0.0)
    lost = workers_jobspec.ClusterLost("no dask worker for 120 s with 6 tiles to go", hint="; resume with --work x")
    monkeypatch.setattr(workers_job, "run_job", lambda spec, **kw: (_ for _ in ()).throw(lost))
    runner = Runner(store, settings, client_factory=lambda: None)
    assert runner.run_job(_queue(store, tenant, block))["state"] == "queued"
    failed = runner.run_job(store.jobs.claim_next())
    assert failed["state"] == "failed" and failed["attempts"] == 2
    assert job_error(failed) == ("no dask worker for 120 s with 6 tiles to go (attempt 2, the last); "
                               "start dask workers and submit the job again")
    # a failure of the job itself is not the cluster's: no second attempt
    monkeypatch.setattr(workers_job, "run_job", lambda spec, **kw: (_ for _ in ()).throw(InputError("b.laz: truncated")))
    failed = runner.run_job(_queue(store, tenant, block))
    assert failed["state"] == "failed" and failed["attempts"] == 1 and job_error(failed) == "b.laz: truncated"


def test_a_job_waiting_for_its_retry_can_be_cancelled(env, monkeypatch):
    settings, store, tenant, block = env
    settings = Settings(data_dir=settings.data_dir, job_retries=2, retry_delay_s=3600.0)
    runner = Runner(store, settings, client_factory=lambda: (_ for _ in ()).throw(OSError("refused")))
    waiting = runner.run_job(_queue(store, tenant, block))
    assert waiting["state"] == "queued"
    assert store.jobs.request_cancel(tenant["id"], waiting["id"])["state"] == "cancelled"
    assert store.jobs.claim_next() is None


def test_a_store_of_an_earlier_version_gains_the_retry_column(tmp_path):
    import sqlite3

    path = tmp_path / "old.sqlite"
    con = sqlite3.connect(path)
    old_schema = SCHEMA.replace("    retry_at REAL,\n", "")
    assert "retry_at" not in old_schema
    con.executescript(old_schema)
    con.execute("INSERT INTO tenants (id, name, created_at) VALUES ('t', 'farm', 0)")
    con.execute("INSERT INTO blocks (id, tenant_id, sha256, path, size_bytes, info, created_at) "
                "VALUES ('b', 't', 'x', '/b.laz', 1, '{}', 0)")
    con.execute("INSERT INTO jobs (id, tenant_id, block_id, job, state, created_at) VALUES ('j', 't', 'b', '{}', 'queued', 0)")
    con.commit()
    con.close()
    store = Store(path)
    try:
        job = store.jobs.claim_next()  # the queued job of the old store runs
        assert job["id"] == "j" and job["retry_at"] is None
        Store(path).close()  # a second process opening it: nothing to add
    finally:
        store.close()


def test_cancel_a_running_job_and_stop(env, monkeypatch):
    settings, store, tenant, block = env
    started = threading.Event()

    def slow(spec, *, client, progress, cancel):
        started.set()
        while not cancel.wait(0.01):
            pass
        raise workers_jobspec.JobCancelled("job cancelled")

    monkeypatch.setattr(workers_job, "run_job", slow)
    store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
    runner = Runner(store, settings, client_factory=lambda: None)
    runner.start()
    assert started.wait(10)
    job_id = runner.current_job
    store.jobs.request_cancel(tenant["id"], job_id)
    runner.cancel(job_id)
    deadline = time.monotonic() + 10
    while store.jobs.get_any_tenant(job_id)["state"] == "running" and time.monotonic() < deadline:
        time.sleep(0.02)
    assert store.jobs.get_any_tenant(job_id)["state"] == "cancelled"
    # a job interrupted by shutdown goes back in the queue, and the restart is no attempt
    # of its own (two restarts used up its retries for a lost cluster)
    started.clear()
    store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
    runner.wake()
    assert started.wait(10)
    second = runner.current_job
    assert store.jobs.get_any_tenant(second)["attempts"] == 1
    runner.stop()
    assert not runner.is_alive()
    rec = store.jobs.get_any_tenant(second)
    assert (rec["state"], rec["attempts"]) == ("queued", 0)
    assert store.jobs.requeue_running() == 0
    # ... but one asked to stop just before the shutdown is cancelled then, not re-queued
    started.clear()
    runner = Runner(store, settings, client_factory=lambda: None)
    runner.start()
    assert started.wait(10)
    third = runner.current_job
    store.jobs.request_cancel(tenant["id"], third)
    runner.stop()
    assert store.jobs.get_any_tenant(third)["state"] == "cancelled"


def test_a_job_whose_outcome_cannot_be_recorded_is_not_left_running(env, monkeypatch):
    # an error while recording left the job "running" for good: a client waiting on it
    # (orchard demo) waited for ever
    settings, store, tenant, block = env
    monkeypatch.setattr(Runner, "run_job", lambda self, job: (_ for _ in ()).throw(RuntimeError("store hiccup")))
    job = store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
    runner = Runner(store, settings, client_factory=lambda: None)
    runner.start()
    try:
        deadline = time.monotonic() + 10
        while store.jobs.get_any_tenant(job["id"])["state"] in ("queued", "running") and time.monotonic() < deadline:
            time.sleep(0.02)
        rec = store.jobs.get_any_tenant(job["id"])
        assert rec["state"] == "failed" and "RuntimeError" in job_error(rec)
    finally:
        runner.stop()


def test_a_scheduled_jobs_error_names_the_capture_not_an_earlier_upload_of_the_same_bytes(env, monkeypatch):
    # the block b.laz was first uploaded as "b.laz"; a schedule later found the same
    # bytes as "north-row-2.laz": that job's messages speak of the capture
    settings, store, tenant, block = env

    def fake(spec, **kw):
        raise NoTreesError(f"{spec.input_path}: no trees found in 100 points")

    monkeypatch.setattr(workers_job, "run_job", fake)
    sched = store.schedules.create(tenant_id=tenant["id"], inbox="/in", cron="0 1 * * *", job={}, next_run_at=None)
    store.schedules.create_job(schedule=sched, block_id=block["id"], sha256=block["sha256"], path="/in/north-row-2.laz",
                               capture="north-row-2.laz")
    job = store.jobs.claim_next()
    assert job["capture"] == "north-row-2.laz"
    failed = Runner(store, settings, client_factory=lambda: None).run_job(job)
    assert job_error(failed) == "north-row-2.laz: no trees found in 100 points"
    # an uploaded job's still names the upload
    uploaded = _queue(store, tenant, block)
    assert job_error(Runner(store, settings, client_factory=lambda: None).run_job(uploaded)) == "b.laz: no trees found in 100 points"


def test_a_cancel_stored_by_another_process_stops_a_job_that_makes_no_progress(env, monkeypatch):
    # the cancel flag was read only when a tile finished: a job waiting for dask workers
    # ran on for minutes after a DELETE sent to an API-only process
    settings, store, tenant, block = env
    started = threading.Event()

    def stuck(spec, *, client, progress, cancel):
        started.set()
        while not cancel.wait(0.01):  # no tile ever finishes
            pass
        raise workers_jobspec.JobCancelled("job cancelled")

    monkeypatch.setattr(workers_job, "run_job", stuck)
    job = store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
    runner = Runner(store, settings, client_factory=lambda: None)
    runner.start()
    try:
        assert started.wait(10)
        other = Store(settings.store_path)  # another API process
        other.jobs.request_cancel(tenant["id"], job["id"])
        other.close()
        deadline = time.monotonic() + 10
        while store.jobs.get_any_tenant(job["id"])["state"] == "running" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert store.jobs.get_any_tenant(job["id"])["state"] == "cancelled"
    finally:
        runner.stop()
