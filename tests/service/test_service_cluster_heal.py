"""The embedded dask cluster heals: worker processes of a real `orchard serve` killed
five times in a row, and the next job still runs, with no restart of the service."""

from __future__ import annotations

import os
import signal
import time

import httpx
import psutil
import pytest
from service_fixtures import ServerProcess, make_token, simulated_block, wait_for_job


def _worker_processes(pid: int) -> list[psutil.Process]:
    """The dask worker processes under the server (spawned children, not the resource tracker)."""
    found = []
    for p in psutil.Process(pid).children(recursive=True):
        try:
            cmd = " ".join(p.cmdline())
        except psutil.NoSuchProcess:
            continue
        if "spawn_main" in cmd and "resource_tracker" not in cmd:
            found.append(p)
    return found


@pytest.mark.slow
def test_five_worker_kills_in_a_row_and_the_next_job_runs_without_a_restart(tmp_path):
    srv = ServerProcess(tmp_path / "data", ORCHARD_SCHEDULING="false", ORCHARD_N_WORKERS="2")
    srv.start()
    try:
        token = make_token(srv.data_dir, "farm")
        block = simulated_block(tmp_path / "orchard.laz", rows=1, trees_per_row=3, density=0.3, seed=4)
        with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
            b = c.post("/v1/blocks", files={"file": (block.name, block.read_bytes())}).json()
            first = wait_for_job(c, c.post("/v1/jobs", json={"block_id": b["id"]}).json()["id"], timeout=300)
            assert first["state"] == "done", first
            health = c.get("/healthz").json()
            assert health["workers"] == health["workers_expected"] == 2, health
            server_pid = srv.proc.pid
            killed = 0
            for _ in range(5):  # every worker process there is, about 4 s apart (as they start again)
                for p in _worker_processes(server_pid):
                    os.kill(p.pid, signal.SIGKILL)
                    killed += 1
                time.sleep(4)
            assert killed >= 5
            seen_none = False
            deadline = time.monotonic() + 180
            while time.monotonic() < deadline:
                resp = c.get("/healthz")
                health = resp.json()
                if health["workers"] == 0:
                    seen_none = True
                    assert resp.status_code == 503 and "no workers" in " ".join(health["problems"]), health
                if health["workers"] == 2 and resp.status_code == 200:
                    break
                time.sleep(1)
            assert health["workers"] == health["workers_expected"] == 2, health
            nxt = wait_for_job(c, c.post("/v1/jobs", json={"block_id": b["id"]}).json()["id"], timeout=300)
            assert nxt["state"] == "done", nxt
            assert srv.proc.poll() is None and srv.proc.pid == server_pid  # the same service, never restarted
        print(f"killed {killed} worker processes; healthz saw no workers: {seen_none}")
    finally:
        srv.stop()
