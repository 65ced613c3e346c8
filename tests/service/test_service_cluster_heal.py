"""The embedded dask cluster heals: worker processes of a real `orchard serve` killed
five times in a row, and the next job still runs, with no restart of the service."""

from __future__ import annotations

import os
import signal
import threading
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


class _Client:
    """A client of an external cluster as the runner sees it: the workers it last heard of."""

    def __init__(self, n_workers: int) -> None:
        self._scheduler_identity = {"n_workers": n_workers}
        self.status = "running"

    def close(self) -> None:
        pass


def test_a_running_job_without_workers_says_so_until_some_connect(tmp_path, monkeypatch):
    import service.runner as runner_module
    from service.db.jobstore import Store
    from service.runner import Runner
    from service.settings import Settings

    monkeypatch.setattr(runner_module, "DOCTOR_POLL_S", 0.05)
    settings = Settings(data_dir=tmp_path, scheduler="tcp://127.0.0.1:1")
    store = Store(settings.store_path)
    tenant = store.accounts.ensure_tenant("farm")
    block, _ = store.blocks.insert(tenant_id=tenant["id"], sha256="ab" * 32, path="/x.las", filename="b.las",
                                  size_bytes=1, info={})
    store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
    job = store.jobs.claim_next()
    runner = Runner(store, settings)
    runner._client, runner._current = _Client(0), job["id"]
    doctor = threading.Thread(target=runner._doctor)
    doctor.start()
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not store.jobs.get_any_tenant(job["id"])["error"]:
            time.sleep(0.05)
        assert store.jobs.get_any_tenant(job["id"])["error"] == "waiting for dask workers: the cluster has none"
        runner._client._scheduler_identity = {"n_workers": 1}
        while time.monotonic() < deadline and store.jobs.get_any_tenant(job["id"])["error"]:
            time.sleep(0.05)
        assert store.jobs.get_any_tenant(job["id"])["error"] is None  # put back as it was
    finally:
        runner._stopping.set()
        doctor.join(10)
        store.close()
