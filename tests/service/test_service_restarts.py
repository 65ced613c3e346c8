"""A real `orchard serve` started, killed and started again on one data folder: a job
killed with its server completes after a restart; a second service on the folder leaves
the first one's work alone; a job cancelled just before a shutdown loses its tiles at the
next start; a work store the workers cannot use stops the service at start (split from
test_service_e2e.py so that the two halves run side by side under ``-n 2 --dist loadfile``)."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from service_fixtures import ServerProcess, make_token, simulated_block, wait_for_job, write_las

from service.db.block_files import accept_block
from service.db.jobstore import Store
from service.schedules import file_sha256
from service.wording import job_error

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tiny_block(tmp_path_factory):
    path = tmp_path_factory.mktemp("e2e") / "tiny.laz"
    return simulated_block(path, rows=1, trees_per_row=3, seed=7, density=0.3)


def test_restart_in_the_middle_of_a_job(tmp_path, tiny_block):
    block_file = tiny_block
    data = tmp_path / "data"
    srv = ServerProcess(data, ORCHARD_SCHEDULING="false").start()
    try:
        token = make_token(data, "farm-restart")
        c = httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60)
        with open(block_file, "rb") as fh:
            block = c.post("/v1/blocks", files={"file": ("orchard.laz", fh)}).json()
        job = c.post("/v1/jobs", json={"block_id": block["id"]}).json()
        wait_for_job(c, job["id"], states=("running", "done", "failed"), timeout=60)
        srv.kill()  # the server and its dask workers die with the job running
        c.close()
        con = sqlite3.connect(data / "orchard.sqlite")
        state = con.execute("SELECT state FROM jobs WHERE id = ?", (job["id"],)).fetchone()[0]
        con.close()
        assert state == "running"
    finally:
        srv.kill()
    srv2 = ServerProcess(data, ORCHARD_SCHEDULING="false").start()
    try:
        with httpx.Client(base_url=srv2.url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c2:
            assert c2.get(f"/v1/blocks/{block['id']}").json()["sha256"] == block["sha256"]  # the upload survived
            done = wait_for_job(c2, job["id"])
            assert done["state"] == "done", done["error"]
            assert done["n_trees"] >= 2
            assert c2.get(f"/v1/jobs/{job['id']}/trees").json()["total"] == done["n_trees"]
    finally:
        srv2.stop()


def test_a_second_service_on_one_data_folder_leaves_the_first_ones_work_alone(tmp_path):
    # a second `orchard serve` on the same folder re-queued the job the first was running
    # (which then ran twice) and deleted the upload it was receiving
    data = tmp_path / "data"
    first = ServerProcess(data, ORCHARD_SCHEDULING="false").start()
    api_only = None
    try:
        store = Store(data / "orchard.sqlite")
        tenant = store.accounts.ensure_tenant("farm-two")
        block_file = write_las(tmp_path / "b.las", 500, seed=5)
        block, _ = accept_block(store, blocks_dir=data / "blocks", tenant_id=tenant["id"],
                                tmp_path=block_file, sha256=file_sha256(block_file),
                                size_bytes=block_file.stat().st_size, filename="b.las")
        # a job the first service runs (as the store sees it), and an upload it is receiving
        con = sqlite3.connect(data / "orchard.sqlite")
        with con:
            con.execute("INSERT INTO jobs (id, tenant_id, block_id, job, state, created_at, started_at) "
                        "VALUES ('j-running', ?, ?, '{}', 'running', 0, 0)", (tenant["id"], block["id"]))
        con.close()
        holder = subprocess.Popen(
            [sys.executable, "-c",
             ("import sys, time; from pathlib import Path; from service.tempfiles import process_dir; "
              "d = process_dir(Path(sys.argv[1])); (d / 'upload-x.part').write_bytes(b'half'); "
              "print(d, flush=True); time.sleep(120)"), str(data / "tmp")],
            stdout=subprocess.PIPE, text=True,
        )
        receiving = Path(holder.stdout.readline().strip())
        # started as the runner too: refused, in one line, nothing touched
        refused = subprocess.run(
            [sys.executable, "-m", "service.cli", "serve", "--data-dir", str(data), "--port", "0"],
            capture_output=True, text=True, timeout=60, check=False,
        )
        assert refused.returncode == 2, refused.stderr
        assert len(refused.stderr.strip().splitlines()) == 1 and "already runs the jobs" in refused.stderr
        assert "ORCHARD_RUNNER=false" in refused.stderr and "Traceback" not in refused.stderr
        # as API only it starts, and leaves the running job and the upload alone
        api_only = ServerProcess(data, ORCHARD_RUNNER="false", ORCHARD_SCHEDULING="false").start()
        assert store.jobs.get_any_tenant("j-running")["state"] == "running"
        assert (receiving / "upload-x.part").read_bytes() == b"half"
        holder.kill()
        holder.wait()
        api_only.stop()
        api_only = None
        first.stop()
        # the folder's next runner finds both orphaned: the job is re-queued, the upload swept
        third = ServerProcess(data, ORCHARD_SCHEDULING="false").start()
        try:
            deadline = time.monotonic() + 30
            while store.jobs.get_any_tenant("j-running")["state"] == "running" and time.monotonic() < deadline:
                time.sleep(0.2)
            assert store.jobs.get_any_tenant("j-running")["state"] != "running"
            assert not receiving.exists()
        finally:
            third.stop()
        store.close()
    finally:
        if api_only is not None:
            api_only.stop()
        first.stop()


def test_a_job_cancelled_just_before_a_shutdown_loses_its_tiles_at_the_next_start(tmp_path):
    # DELETE then SIGTERM at once: the job stayed "running" with cancel requested, the next
    # start cancelled it in the store, and its tiles stayed on disk for good
    from service.jobfolders import work_dir_of
    from service.settings import Settings
    from workers.workstore import WorkStore

    data = tmp_path / "data"
    store = Store(data / "orchard.sqlite")
    tenant = store.accounts.ensure_tenant("farm-cancel")
    block_file = write_las(tmp_path / "b.las", 500, seed=6)
    block, _ = accept_block(store, blocks_dir=data / "blocks", tenant_id=tenant["id"], tmp_path=block_file,
                            sha256=file_sha256(block_file), size_bytes=block_file.stat().st_size, filename="b.las")
    job = store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={"tiling": {"tile_size": 6.0}})
    assert store.jobs.claim_next()["id"] == job["id"]
    store.jobs.request_cancel(tenant["id"], job["id"])
    work = WorkStore(work_dir_of(Settings(data_dir=data), job["id"]))
    work.claim()
    work.put_json("job.json", {"tiles": []})
    assert Path(work.root).is_dir()
    srv = ServerProcess(data, ORCHARD_SCHEDULING="false").start()
    try:
        rec = store.jobs.get_any_tenant(job["id"])
        assert rec["state"] == "cancelled" and job_error(rec) == "cancelled on request" and rec["error_kind"] == "cancelled"
        assert not Path(work.root).exists()
    finally:
        srv.stop()
        store.close()


@pytest.mark.parametrize("work, words", [("memory://orchard", "lives in this process only"),
                                         ("nosuch://bucket/orchard", "Protocol not known")])
def test_a_work_store_the_workers_cannot_use_stops_the_service_at_start(tmp_path, work, words):
    # each job failed on it instead (ImportError: Install s3fs, for s3:// without s3fs)
    run = subprocess.run(
        [sys.executable, "-m", "service.cli", "serve", "--data-dir", str(tmp_path / "data"), "--port", "0"],
        capture_output=True, text=True, timeout=60, check=False, env={**os.environ, "ORCHARD_WORK_DIR": work},
    )
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip().splitlines() == [run.stderr.strip()] and "ORCHARD_WORK_DIR" in run.stderr
    assert words in run.stderr and "Traceback" not in run.stderr
