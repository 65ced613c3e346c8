"""The job queue between tenants and across service deaths: fair share, crash counting,
poison jobs, quotas checked in the store (no HTTP, no dask)."""

from __future__ import annotations

import sqlite3
import tempfile
import threading
from pathlib import Path

import pytest
from hypothesis import given, settings as hsettings, strategies as st

from service.db.database import SCHEMA
from service.db.jobstore import Store
from service.quotas import GB, QueueQuotaExceeded, StorageQuotaExceeded
from service.runner import Runner
from service.settings import Settings
from service.wording import job_error

import workers.job as workers_job
import workers.jobspec as workers_jobspec


@pytest.fixture()
def store(tmp_path):
    s = Store(tmp_path / "orchard.sqlite")
    yield s
    s.close()


def _block(store, tenant_id, sha="ab" * 32, size=10):
    block, _ = store.blocks.insert(tenant_id=tenant_id, sha256=sha, path=f"/x/{sha}.las", filename="b.las",
                                  size_bytes=size, info={})
    return block


def _jobs(store, tenant, n):
    block = _block(store, tenant["id"], sha=tenant["id"][:2] * 32)
    return [store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})["id"]
            for i in range(n)]


def _drain(store) -> list[str]:
    """Tenant ids in the order their jobs start, one job at a time, each finished before the next."""
    order = []
    while (job := store.jobs.claim_next()) is not None:
        order.append(job["tenant_id"])
        store.jobs.finish(job["id"], "done")
    return order


# -- fair share ------------------------------------------------------------------------


def test_a_flooding_tenant_delays_another_by_one_job(store):
    a, b = store.accounts.ensure_tenant("flood"), store.accounts.ensure_tenant("small")
    _jobs(store, a, 15)
    _jobs(store, b, 1)  # queued behind all 15: it waited for all of them before
    first = store.jobs.claim_next()
    assert first["tenant_id"] == a["id"]
    store.jobs.finish(first["id"], "done")
    assert store.jobs.claim_next()["tenant_id"] == b["id"]


def test_tenants_take_turns_and_each_keeps_its_own_order(store):
    a, b, c = (store.accounts.ensure_tenant(n) for n in "abc")
    ids = {t["id"]: _jobs(store, t, n) for t, n in ((a, 3), (b, 2), (c, 1))}
    started = []
    while (job := store.jobs.claim_next()) is not None:
        started.append(job)
        store.jobs.finish(job["id"], "done")
    assert [j["tenant_id"] for j in started] == [a["id"], b["id"], c["id"], a["id"], b["id"], a["id"]]
    for tid, queued in ids.items():  # FIFO within a tenant
        assert [j["id"] for j in started if j["tenant_id"] == tid] == queued


def test_a_tenant_with_a_running_job_waits_for_one_without(store):
    a, b = store.accounts.ensure_tenant("a"), store.accounts.ensure_tenant("b")
    _jobs(store, a, 3)
    assert store.jobs.claim_next()["tenant_id"] == a["id"]  # still running (a second runner claims next)
    _jobs(store, b, 1)
    assert store.jobs.claim_next()["tenant_id"] == b["id"]
    assert store.jobs.claim_next()["tenant_id"] == a["id"]


def test_a_job_waiting_for_its_retry_time_does_not_hold_its_tenant_back(store):
    a, b = store.accounts.ensure_tenant("a"), store.accounts.ensure_tenant("b")
    first, second = _jobs(store, a, 2)
    job = store.jobs.claim_next()
    store.jobs.retry(job["id"], error="attempt 1 failed", retry_at=2e9)  # far in the future
    _jobs(store, b, 1)
    assert store.jobs.claim_next()["tenant_id"] == b["id"]  # never served
    assert store.jobs.claim_next()["id"] == second
    assert store.jobs.claim_next() is None


@hsettings(max_examples=25, deadline=None)
@given(st.lists(st.integers(0, 3), min_size=1, max_size=24))
def test_served_counts_of_waiting_tenants_never_differ_by_more_than_one(arrivals):
    # every job queued up front, in any interleaving of 4 tenants: a round robin
    with tempfile.TemporaryDirectory(dir="/dev/shm" if Path("/dev/shm").is_dir() else None) as tmp:  # no disk syncs
        s = Store(Path(tmp) / "o.sqlite")
        try:
            tenants = [s.accounts.ensure_tenant(f"t{i}") for i in range(4)]
            blocks = {t["id"]: _block(s, t["id"], sha=f"{i:02d}" * 32) for i, t in enumerate(tenants)}
            for i in arrivals:
                t = tenants[i]
                s.jobs.create(tenant_id=t["id"], block_id=blocks[t["id"]]["id"], job={})
            total = {t["id"]: arrivals.count(i) for i, t in enumerate(tenants)}
            served = dict.fromkeys(total, 0)
            for tid in _drain(s):
                served[tid] += 1
                waiting = [served[t] for t in total if served[t] < total[t]]
                if waiting:
                    assert max(waiting) - min(waiting) <= 1 and min(waiting) >= served[tid] - 1
            assert served == total
        finally:
            s.close()


def test_the_runner_starts_the_other_tenants_job_next(tmp_path, monkeypatch):
    # the runner thread itself, with run_job faked: tenant b's one job, queued while
    # tenant a's first of 15 runs, starts second
    settings = Settings(data_dir=tmp_path / "data", runner_poll_s=0.05)
    store = Store(settings.store_path)
    a, b = store.accounts.ensure_tenant("flood"), store.accounts.ensure_tenant("small")
    started, first_running, release = [], threading.Event(), threading.Event()

    def fake(spec, *, client, progress, cancel):
        started.append(spec.out_dir.rsplit("/", 1)[-1])
        first_running.set()
        assert release.wait(30)
        return workers_jobspec.JobOutcome(0, 1, 1, [], False, {}, {}, trees={})

    monkeypatch.setattr(workers_job, "run_job", fake)
    flood = _jobs(store, a, 15)
    runner = Runner(store, settings, client_factory=lambda: None)
    runner.start()
    try:
        assert first_running.wait(30)
        small = _jobs(store, b, 1)
        release.set()
        deadline = threading.Event()
        for _ in range(600):
            if len(started) == 16:
                break
            deadline.wait(0.05)
    finally:
        release.set()
        runner.stop()
        store.close()
    assert started[:3] == [flood[0], small[0], flood[1]] and started[3:] == flood[2:]


# -- crashes and poison jobs -----------------------------------------------------------


def _crash_during(path, job_id=None):
    """Claim the next job in a store at ``path`` and close it as a killed process would."""
    s = Store(path)
    job = s.jobs.claim_next()
    assert job_id is None or job["id"] == job_id
    s.close()
    return job


def test_a_crash_is_counted_apart_from_attempts(tmp_path):
    path = tmp_path / "o.sqlite"
    s = Store(path)
    t = s.accounts.ensure_tenant("farm")
    (jid,) = _jobs(s, t, 1)
    s.close()
    _crash_during(path, jid)
    s = Store(path)
    assert s.jobs.requeue_running(max_crashes=3) == 1
    again = s.jobs.get_any_tenant(jid)
    assert again["state"] == "queued" and again["attempts"] == 0 and again["crashes"] == 1
    again = s.jobs.claim_next()
    assert again["attempts"] == 1  # one attempt, however many times the service died under it
    # a lost cluster still has its own retries: attempts are not used up by crashes
    s.jobs.retry(jid, error="attempt 1 failed", retry_at=0)
    assert s.jobs.claim_next()["attempts"] == 2
    s.close()


def test_a_job_that_keeps_killing_the_service_is_failed_and_the_rest_run(tmp_path):
    path = tmp_path / "o.sqlite"
    s = Store(path)
    t = s.accounts.ensure_tenant("farm")
    poison, other = _jobs(s, t, 2)
    s.close()
    _crash_during(path, poison)
    s = Store(path)
    assert s.jobs.requeue_running(max_crashes=2) == 1
    s.close()
    _crash_during(path, poison)
    s = Store(path)
    assert s.jobs.requeue_running(max_crashes=2) == 0
    failed = s.jobs.get_any_tenant(poison)
    assert failed["state"] == "failed" and failed["crashes"] == 2 and failed["finished_at"] is not None
    assert failed["error_kind"] == "crashed" and failed["error_fields"] == {"crashes": 2}
    assert job_error(failed).startswith("the service stopped 2 times while running this job; it is not retried")
    nxt = s.jobs.claim_next()
    assert nxt["id"] == other and nxt["crashes"] == 0
    s.close()


def test_a_graceful_stop_is_no_crash(store):
    t = store.accounts.ensure_tenant("farm")
    (jid,) = _jobs(store, t, 1)
    store.jobs.claim_next()
    store.jobs.release(jid)  # the service stopping: the runner gives the job back
    job = store.jobs.get_any_tenant(jid)
    assert job["state"] == "queued" and job["crashes"] == 0 and job["attempts"] == 0


def test_a_store_of_an_earlier_version_gains_the_crash_column_in_place(tmp_path):
    path = tmp_path / "old.sqlite"
    old_schema = SCHEMA.replace("    crashes INTEGER NOT NULL DEFAULT 0,\n", "")
    old_schema = old_schema.split("CREATE INDEX IF NOT EXISTS jobs_by_tenant_started")[0]
    assert "crashes" not in old_schema and "tenant_quotas" not in old_schema
    con = sqlite3.connect(path)
    con.executescript(old_schema)
    con.execute("INSERT INTO tenants VALUES ('t1', 'farm', 0)")
    con.execute("INSERT INTO blocks (id, tenant_id, sha256, path, size_bytes, info, created_at) "
                "VALUES ('b1', 't1', 'ab', '/x/ab.las', 5, '{}', 0)")
    con.execute("INSERT INTO jobs (id, tenant_id, block_id, job, state, attempts, created_at, started_at) "
                "VALUES ('j1', 't1', 'b1', '{}', 'running', 1, 0, 1)")
    con.commit()
    con.close()
    s = Store(path)
    assert s.jobs.requeue_running(max_crashes=2) == 1
    job = s.jobs.get_any_tenant("j1")
    assert job["crashes"] == 1 and job["attempts"] == 0 and job["state"] == "queued"
    assert s.quotas.get("t1")["used_storage_bytes"] == 5
    s.close()


# -- quotas ----------------------------------------------------------------------------


def test_a_storage_quota_refuses_a_block_and_keeps_nothing(store):
    a, b = store.accounts.ensure_tenant("a"), store.accounts.ensure_tenant("b")
    store.quotas.set_limits(a["id"], storage_bytes=100)
    _block(store, a["id"], sha="01" * 32, size=60)
    with pytest.raises(StorageQuotaExceeded) as err:
        _block(store, a["id"], sha="02" * 32, size=41)
    assert (err.value.tenant, err.value.limit, err.value.used, err.value.requested) == ("a", 100, 60, 41)
    assert "'a' is at its storage quota" in str(err.value) and "nothing of it was kept" in str(err.value)
    assert [x["sha256"] for x in store.blocks.list(a["id"])] == ["01" * 32]
    _block(store, a["id"], sha="02" * 32, size=40)  # exactly at the limit fits
    _block(store, a["id"], sha="01" * 32, size=60)  # the same file again takes no more room
    _block(store, b["id"], sha="03" * 32, size=10 * GB)  # another tenant is not limited by it
    store.quotas.set_limits(a["id"], storage_bytes=None)
    _block(store, a["id"], sha="04" * 32, size=GB)
    assert store.quotas.get(a["id"]) == {"storage_bytes": None, "queued_jobs": None,
                                    "used_storage_bytes": GB + 100, "used_queued_jobs": 0}


def test_a_queue_quota_refuses_the_job_past_it(store):
    a, b = store.accounts.ensure_tenant("a"), store.accounts.ensure_tenant("b")
    store.quotas.set_limits(a["id"], queued_jobs=2)
    first, _ = _jobs(store, a, 2)
    with pytest.raises(QueueQuotaExceeded, match="has 2 job\\(s\\) queued, its limit of 2"):
        _jobs(store, a, 1)
    _jobs(store, b, 5)  # another tenant is not limited by it
    assert store.jobs.claim_next()["id"] == first  # a started job is no longer queued: room for one more
    blk = store.blocks.list(a["id"])[0]
    store.jobs.create(tenant_id=a["id"], block_id=blk["id"], job={})
    assert store.quotas.get(a["id"])["used_queued_jobs"] == 2


def test_a_queue_quota_holds_under_simultaneous_submissions(store):
    t = store.accounts.ensure_tenant("farm")
    store.quotas.set_limits(t["id"], queued_jobs=3)
    blk = _block(store, t["id"])
    made, refused, lock = [], [], threading.Lock()

    def submit():
        try:
            job = store.jobs.create(tenant_id=t["id"], block_id=blk["id"], job={})
            with lock:
                made.append(job["id"])
        except QueueQuotaExceeded:
            with lock:
                refused.append(1)

    threads = [threading.Thread(target=submit) for _ in range(12)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(made) == 3 and len(refused) == 9


def test_no_work_folder_of_a_failed_job_survives_a_restart(tmp_path):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from workers.workstore import MARKER

    settings = Settings(data_dir=tmp_path / "data", runner=False, scheduling=True)  # holds the runner lock, runs nothing
    settings.data_dir.mkdir()
    s = Store(settings.store_path)
    t = s.accounts.ensure_tenant("farm")
    poison, ended, waiting = _jobs(s, t, 3)
    s.close()
    for jid in (poison, ended, waiting):
        tiles = settings.jobs_dir / jid / "_work" / "tiles"
        tiles.mkdir(parents=True)
        (tiles / "t0.npy").write_bytes(b"x" * 1000)
        (tiles.parent / MARKER).touch()  # as a job's work store leaves it
    _crash_during(settings.store_path, poison)
    s = Store(settings.store_path)
    assert s.jobs.requeue_running(max_crashes=2) == 1  # the first crash: queued again
    s.jobs.claim_next()  # (the poison job again: it is the oldest)
    s.close()
    # a job that failed while its tiles were being deleted (a crash cut it short)
    con = sqlite3.connect(settings.store_path)
    with con:
        con.execute("UPDATE jobs SET state = 'failed', finished_at = 1 WHERE id = ?", (ended,))
    con.close()
    with TestClient(create_app(settings)):  # the restart after the second crash
        pass
    s = Store(settings.store_path)
    assert s.jobs.get_any_tenant(poison)["state"] == "failed" and s.jobs.get_any_tenant(ended)["state"] == "failed"
    assert s.jobs.get_any_tenant(waiting)["state"] == "queued"
    s.close()
    assert not (settings.jobs_dir / poison).exists() and not (settings.jobs_dir / ended).exists()
    assert (settings.jobs_dir / waiting / "_work" / "tiles" / "t0.npy").exists()  # still to run: kept
