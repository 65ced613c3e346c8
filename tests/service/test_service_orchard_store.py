"""Orchard blocks and their captures in the job store (real SQLite): their order, the
queue that takes a block's captures one at a time, tenants kept apart, and a store of
an earlier version brought up to date in place."""

from __future__ import annotations

import sqlite3
import threading

import pytest

from service.db.database import SCHEMA
from service.db.errors import ConflictError, NotFoundError
from service.db.jobstore import Store


@pytest.fixture()
def store(tmp_path):
    s = Store(tmp_path / "orchard.sqlite")
    yield s
    s.close()


def _file(store, tenant, n: int) -> dict:
    block, _ = store.blocks.insert(tenant_id=tenant["id"], sha256=f"{n:064x}", path=f"/x/{n}.laz", filename=f"scan{n}.laz",
                                  size_bytes=10, info={})
    return block


def _capture(store, tenant, ob, n: int, **kw) -> dict:
    return store.orchard_blocks.create_capture(tenant_id=tenant["id"], orchard_block_id=ob["id"], block_id=_file(store, tenant, n)["id"],
                                job={}, **kw)


def test_blocks_are_named_once_per_tenant_and_listed_by_name(store):
    a, b = store.accounts.ensure_tenant("farm-a"), store.accounts.ensure_tenant("farm-b")
    north = store.orchard_blocks.create(a["id"], "north")
    store.orchard_blocks.create(a["id"], "east")
    store.orchard_blocks.create(b["id"], "north")  # another farm may use the name
    with pytest.raises(ConflictError, match="already has an orchard block called 'north'"):
        store.orchard_blocks.create(a["id"], "north")
    assert [o["name"] for o in store.orchard_blocks.list(a["id"])] == ["east", "north"]
    assert store.orchard_blocks.by_name(a["id"], "north")["id"] == north["id"]
    with pytest.raises(NotFoundError):
        store.orchard_blocks.get(b["id"], north["id"])


def test_captures_keep_their_arrival_order_and_dates(store):
    t = store.accounts.ensure_tenant("farm")
    ob = store.orchard_blocks.create(t["id"], "north")
    first = _capture(store, t, ob, 1, captured_at="2026-04-01")
    second = _capture(store, t, ob, 2)
    assert (first["seq"], second["seq"]) == (1, 2)
    assert (first["captured_at"], first["captured_at_source"]) == ("2026-04-01", "given")
    # no date given: the day its file arrived, until the job's outputs say otherwise
    assert second["captured_at_source"] == "upload" and len(second["captured_at"]) == 10
    assert [c["id"] for c in store.orchard_blocks.list_captures(t["id"], ob["id"])] == [first["id"], second["id"]]
    assert first["state"] == "queued" and store.orchard_blocks.get(t["id"], ob["id"])["n_captures"] == 2


def test_a_capture_needs_the_tenants_own_block_and_file(store):
    a, b = store.accounts.ensure_tenant("farm-a"), store.accounts.ensure_tenant("farm-b")
    ob_b = store.orchard_blocks.create(b["id"], "north")
    with pytest.raises(NotFoundError):  # another farm's orchard block
        store.orchard_blocks.create_capture(tenant_id=a["id"], orchard_block_id=ob_b["id"], block_id=_file(store, a, 1)["id"],
                             job={})
    ob_a = store.orchard_blocks.create(a["id"], "north")
    with pytest.raises(NotFoundError):  # another farm's file
        store.orchard_blocks.create_capture(tenant_id=a["id"], orchard_block_id=ob_a["id"], block_id=_file(store, b, 2)["id"],
                             job={})
    assert store.jobs.list(a["id"]) == []  # nothing queued by the refusals
    with pytest.raises(NotFoundError):
        store.orchard_blocks.list_captures(a["id"], ob_b["id"])


def test_a_blocks_captures_run_one_at_a_time_in_arrival_order(store):
    t = store.accounts.ensure_tenant("farm")
    north, south = store.orchard_blocks.create(t["id"], "north"), store.orchard_blocks.create(t["id"], "south")
    n1, n2, n3 = (_capture(store, t, north, i) for i in (1, 2, 3))
    s1 = _capture(store, t, south, 4)
    plain = store.jobs.create(tenant_id=t["id"], block_id=_file(store, t, 5)["id"], job={})
    claimed = store.jobs.claim_next()
    assert claimed["id"] == n1["job_id"]
    # north's next capture waits while its first runs; the other block and a plain job do not
    assert store.jobs.claim_next()["id"] == s1["job_id"]
    assert store.jobs.claim_next()["id"] == plain["id"]
    assert store.jobs.claim_next() is None
    store.jobs.finish(n1["job_id"], "failed", error="no overlap")
    assert store.jobs.claim_next()["id"] == n2["job_id"]  # a failed capture does not hold the block
    assert store.jobs.claim_next() is None
    # a retry keeps the order: the later capture waits for the retried one
    store.jobs.retry(n2["job_id"], error="cluster lost", retry_at=0)
    assert store.jobs.claim_next()["id"] == n2["job_id"]
    store.jobs.finish(n2["job_id"], "done")
    assert store.jobs.claim_next()["id"] == n3["job_id"]


def test_the_previous_capture_is_the_latest_done_before_it(store):
    t = store.accounts.ensure_tenant("farm")
    ob = store.orchard_blocks.create(t["id"], "north")
    caps = [_capture(store, t, ob, i) for i in (1, 2, 3)]
    for cap, state in zip(caps[:2], ("done", "failed")):
        assert store.jobs.claim_next()["id"] == cap["job_id"]
        store.jobs.finish(cap["job_id"], state)
    assert store.orchard_blocks.latest_done_capture(t["id"], ob["id"], before_seq=caps[2]["seq"])["id"] == caps[0]["id"]
    assert store.orchard_blocks.latest_done_capture(t["id"], ob["id"], before_seq=caps[0]["seq"]) is None
    assert store.orchard_blocks.latest_done_capture(t["id"], ob["id"])["id"] == caps[0]["id"]
    other = store.accounts.ensure_tenant("other")
    assert store.orchard_blocks.latest_done_capture(other["id"], ob["id"]) is None


def test_the_record_of_a_finished_capture_gives_its_date(store):
    t = store.accounts.ensure_tenant("farm")
    ob = store.orchard_blocks.create(t["id"], "north")
    cap = _capture(store, t, ob, 1, captured_at="2026-05-02")
    rec = {"capture_id": cap["id"], "captured_at": "2026-04-30", "captured_at_source": "file",
           "registration": {"dx": 1.0, "dy": 0.5, "rotation_deg": 1.2, "residual_m": 0.03, "n_matched": 40}}
    store.orchard_blocks.set_capture_record(cap["job_id"], rec)
    again = store.orchard_blocks.get_capture(t["id"], cap["id"])
    assert (again["captured_at"], again["captured_at_source"]) == ("2026-04-30", "file")
    assert again["record"]["registration"]["residual_m"] == 0.03 and again["given_captured_at"] == "2026-05-02"


def test_a_store_of_an_earlier_version_gains_blocks_and_captures_in_place(tmp_path):
    path = tmp_path / "old.sqlite"
    old = SCHEMA.split("CREATE TABLE IF NOT EXISTS orchard_blocks")[0] + "CREATE TABLE IF NOT EXISTS capture_hashes" \
        + SCHEMA.split("CREATE TABLE IF NOT EXISTS capture_hashes", 1)[1]
    old = old.replace("    paused INTEGER NOT NULL DEFAULT 0,\n    orchard_block_id TEXT\n", "    paused INTEGER NOT NULL DEFAULT 0\n")
    assert "orchard_block" not in old and "CREATE TABLE IF NOT EXISTS captures" not in old
    con = sqlite3.connect(path)
    con.executescript(old)
    con.execute("INSERT INTO tenants VALUES ('t1', 'farm', 0)")
    con.execute("INSERT INTO blocks (id, tenant_id, sha256, path, size_bytes, info, created_at) "
                "VALUES ('b1', 't1', 'ab', '/x/ab.las', 5, '{}', 0)")
    con.execute("INSERT INTO jobs (id, tenant_id, block_id, job, state, created_at) VALUES ('j1', 't1', 'b1', '{}', 'queued', 0)")
    con.execute("INSERT INTO schedules (id, tenant_id, inbox, cron, job, created_at) VALUES ('s1', 't1', '/in', '0 1 * * *', '{}', 0)")
    con.commit()
    con.close()
    s = Store(path)
    try:
        assert s.schedules.get_any_tenant("s1")["orchard_block_id"] is None  # the column, added
        assert s.jobs.claim_next()["id"] == "j1"  # the queue reads the new tables
        ob = s.orchard_blocks.create("t1", "north")
        cap = s.orchard_blocks.create_capture(tenant_id="t1", orchard_block_id=ob["id"], block_id="b1", job={})
        assert cap["seq"] == 1 and cap["block_id"] == "b1"
    finally:
        s.close()
    assert Store(path).orchard_blocks.list_captures("t1", ob["id"])[0]["id"] == cap["id"]  # opened again: nothing added twice


def test_captures_sent_at_the_same_moment_each_get_their_own_place(tmp_path):
    path = tmp_path / "orchard.sqlite"
    s = Store(path)
    t = s.accounts.ensure_tenant("farm")
    ob = s.orchard_blocks.create(t["id"], "north")
    files = [_file(s, t, i)["id"] for i in range(8)]
    s.close()
    errors, barrier = [], threading.Barrier(len(files))

    def send(block_id):
        store = Store(path)  # each its own connection, as requests of two processes
        try:
            barrier.wait()
            store.orchard_blocks.create_capture(tenant_id=t["id"], orchard_block_id=ob["id"], block_id=block_id, job={})
        except Exception as exc:  # noqa: BLE001 - collected for the assertion
            errors.append(exc)
        finally:
            store.close()

    threads = [threading.Thread(target=send, args=(b,)) for b in files]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    s = Store(path)
    assert errors == [] and sorted(c["seq"] for c in s.orchard_blocks.list_captures(t["id"], ob["id"])) == list(range(1, 9))
    s.close()
