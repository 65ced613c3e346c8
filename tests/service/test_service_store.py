"""The SQLite job store: state changes, re-queue on restart, tenant isolation, hashed tokens."""

from __future__ import annotations

import sqlite3
import threading

import pytest

from pipeline.errors import InputError
from service.auth import UnauthorizedError, authenticate, create_token, hash_token
from service.db.block_files import accept_block
from service.db.errors import ConflictError, NotFoundError
from service.db.jobstore import Store
from service_fixtures import write_las


@pytest.fixture()
def store(tmp_path):
    s = Store(tmp_path / "orchard.sqlite")
    yield s
    s.close()


def _block(store, tenant_id, sha="ab" * 32):
    block, _ = store.blocks.insert(tenant_id=tenant_id, sha256=sha, path=f"/x/{sha}.las", filename="b.las", size_bytes=10, info={"n_points": 1})
    return block


def test_wal_mode(store):
    con = sqlite3.connect(store.path)
    assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    con.close()


def test_job_states(store):
    t = store.accounts.ensure_tenant("farm")
    b = _block(store, t["id"])
    job = store.jobs.create(tenant_id=t["id"], block_id=b["id"], job={})
    assert job["state"] == "queued"
    claimed = store.jobs.claim_next()
    assert claimed["id"] == job["id"] and claimed["state"] == "running" and claimed["attempts"] == 1
    assert store.jobs.claim_next() is None
    store.jobs.set_progress(job["id"], 2, 5)
    assert (store.jobs.get(t["id"], job["id"])["tiles_done"], store.jobs.get(t["id"], job["id"])["tiles_total"]) == (2, 5)
    done = store.jobs.finish(job["id"], "done", outcome={"n_trees": 3}, timings={"total": 1.5})
    assert done["state"] == "done" and done["tiles_done"] == 5 and done["outcome"]["n_trees"] == 3
    with pytest.raises(ConflictError):
        store.jobs.request_cancel(t["id"], job["id"])


def test_cancel_queued_and_running(store):
    t = store.accounts.ensure_tenant("farm")
    b = _block(store, t["id"])
    j1 = store.jobs.create(tenant_id=t["id"], block_id=b["id"], job={})
    j2 = store.jobs.create(tenant_id=t["id"], block_id=b["id"], job={})
    running = store.jobs.claim_next()
    assert running["id"] == j1["id"]
    assert store.jobs.request_cancel(t["id"], j2["id"])["state"] == "cancelled"
    r = store.jobs.request_cancel(t["id"], j1["id"])
    assert r["state"] == "running" and r["cancel_requested"] == 1
    assert store.jobs.cancel_requested(j1["id"])
    assert store.jobs.claim_next() is None  # the cancelled one is never picked up


def test_requeue_running_after_a_crash(tmp_path):
    s1 = Store(tmp_path / "o.sqlite")
    t = s1.accounts.ensure_tenant("farm")
    b = _block(s1, t["id"])
    j = s1.jobs.create(tenant_id=t["id"], block_id=b["id"], job={"pipeline": {"a": 1}, "tiling": {"tile_size": 20.0}})
    s1.jobs.claim_next()
    s1.close()  # the process dies with the job running
    s2 = Store(tmp_path / "o.sqlite")
    assert s2.jobs.get_any_tenant(j["id"])["state"] == "running"
    assert s2.jobs.requeue_running() == 1
    again = s2.jobs.claim_next()
    # the service's death is a crash, not an attempt of the job's (attempts are for a lost cluster)
    assert again["id"] == j["id"] and again["attempts"] == 1 and again["crashes"] == 1
    assert again["job"]["tiling"]["tile_size"] == 20.0
    s2.close()


def test_claim_is_atomic_across_threads(store):
    t = store.accounts.ensure_tenant("farm")
    b = _block(store, t["id"])
    ids = {store.jobs.create(tenant_id=t["id"], block_id=b["id"], job={})["id"] for _ in range(20)}
    got, lock = [], threading.Lock()

    def worker():
        while (job := store.jobs.claim_next()) is not None:
            with lock:
                got.append(job["id"])

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert sorted(got) == sorted(ids)


def test_tenant_isolation(store):
    a, b = store.accounts.ensure_tenant("a"), store.accounts.ensure_tenant("b")
    blk = _block(store, a["id"])
    job = store.jobs.create(tenant_id=a["id"], block_id=blk["id"], job={})
    with pytest.raises(NotFoundError):
        store.blocks.get(b["id"], blk["id"])
    with pytest.raises(NotFoundError):
        store.jobs.get(b["id"], job["id"])
    with pytest.raises(NotFoundError):
        store.jobs.request_cancel(b["id"], job["id"])
    assert store.jobs.list(b["id"]) == [] and store.blocks.list(b["id"]) == []


def test_tokens_are_stored_hashed(store):
    token = create_token(store, "farm")
    assert authenticate(store, f"Bearer {token}")["name"] == "farm"
    assert store.accounts.tenant_for_token(hash_token(token)) is not None
    rows = store.db.connection().execute("SELECT hash FROM tokens").fetchall()
    assert [r[0] for r in rows] == [hash_token(token)]
    assert token.encode() not in store.path.read_bytes()
    for header in (None, "", "Bearer", "Token " + token, "Bearer x" + token):
        with pytest.raises(UnauthorizedError):
            authenticate(store, header)
    assert store.accounts.revoke_token(hash_token(token))
    with pytest.raises(UnauthorizedError):
        authenticate(store, f"Bearer {token}")


def test_accept_block_lands_file_and_dedupes(store, tmp_path):
    t = store.accounts.ensure_tenant("farm")
    src = write_las(tmp_path / "in.laz", 300, seed=4)
    import hashlib

    sha = hashlib.sha256(src.read_bytes()).hexdigest()
    blocks = tmp_path / "blocks"
    for i in range(2):
        tmp = tmp_path / f"up{i}.part"
        tmp.write_bytes(src.read_bytes())
        block, created = accept_block(store, blocks_dir=blocks, tenant_id=t["id"], tmp_path=tmp, sha256=sha, size_bytes=tmp.stat().st_size, filename="in.laz")
        assert created is (i == 0)
        assert not tmp.exists()
    assert (blocks / f"{sha}.laz").read_bytes() == src.read_bytes()
    assert block["info"]["n_points"] == 300
    bad = tmp_path / "bad.part"
    bad.write_bytes(b"nope" * 100)
    with pytest.raises(InputError, match="capture.las"):
        accept_block(store, blocks_dir=blocks, tenant_id=t["id"], tmp_path=bad, sha256="0" * 64, size_bytes=400, filename="capture.las")
    assert not bad.exists() and not list(tmp_path.glob("bad*"))


def test_block_files_are_found_in_the_data_folder_whatever_path_was_recorded(tmp_path, monkeypatch):
    # a service started with a relative --data-dir recorded block paths relative to its
    # folder: started again from elsewhere, every block was "no such file", and uploading
    # the file again did not mend the record
    import hashlib
    import shutil

    data = tmp_path / "data"
    store = Store(data / "orchard.sqlite")
    t = store.accounts.ensure_tenant("farm")
    src = write_las(tmp_path / "in.laz", 300, seed=4)
    sha = hashlib.sha256(src.read_bytes()).hexdigest()
    (data / "blocks").mkdir()
    shutil.copy(src, data / "blocks" / f"{sha}.laz")
    block, _ = store.blocks.insert(tenant_id=t["id"], sha256=sha, path=f"data/blocks/{sha}.laz", filename="in.laz",
                                  size_bytes=src.stat().st_size, info={"n_points": 300})
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    for rec in (store.blocks.get(t["id"], block["id"]), store.blocks.list(t["id"])[0], store.blocks.by_sha(t["id"], sha)):
        assert rec["path"] == str(data / "blocks" / f"{sha}.laz")
    store.close()
    # the data folder moved (or mounted elsewhere): its blocks come with it
    moved = tmp_path / "moved"
    shutil.move(data, moved)
    store = Store(moved / "orchard.sqlite")
    assert store.blocks.get(t["id"], block["id"])["path"] == str(moved / "blocks" / f"{sha}.laz")
    # a file landed again under a new path mends the record
    (moved / "blocks" / f"{sha}.laz").unlink()
    again = tmp_path / "again.part"
    shutil.copy(src, again)
    rec, created = accept_block(store, blocks_dir=tmp_path / "new-blocks", tenant_id=t["id"], tmp_path=again, sha256=sha,
                                size_bytes=src.stat().st_size, filename="in.laz")
    assert not created and rec["id"] == block["id"] and rec["path"] == str(tmp_path / "new-blocks" / f"{sha}.laz")
    assert store.blocks.get(t["id"], block["id"])["path"] == rec["path"]
    store.close()


def test_settings_paths_are_absolute(tmp_path, monkeypatch):
    from service.settings import Settings

    monkeypatch.chdir(tmp_path)
    s = Settings(data_dir="d", work_dir="w", inbox_root="in")
    assert s.data_dir == tmp_path / "d" and s.store_path == tmp_path / "d" / "orchard.sqlite"
    assert s.work_dir == str(tmp_path / "w") and s.inbox_root == tmp_path / "in"
    assert Settings().data_dir == tmp_path / "orchard-data"
    assert Settings(work_dir="s3://bucket/orchard").work_dir == "s3://bucket/orchard"
