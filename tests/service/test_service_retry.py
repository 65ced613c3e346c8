"""A job whose dask scheduler is down waits for it, with real scheduler and worker processes.

``orchard serve --scheduler`` points at a port where nothing listens yet: the job's
first attempt cannot reach the cluster and is queued again (``ORCHARD_JOB_RETRIES``,
``ORCHARD_RETRY_DELAY_S``). Then ``dask scheduler`` and ``dask worker`` start on that
port, as after a restart in the night, and a later attempt runs the job to the end.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time

import httpx
import pytest
from service_fixtures import (
    ServerProcess,
    make_token,
    refusing_address,
    simulated_block,
    wait_for_job,
)

pytestmark = pytest.mark.skipif(shutil.which("dask") is None, reason="the `dask` command is not installed")


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


@pytest.mark.slow
def test_a_job_waits_for_a_scheduler_that_comes_back(tmp_path):
    with refusing_address() as address:
        _waits_for_a_scheduler_that_comes_back(tmp_path, address)


def _waits_for_a_scheduler_that_comes_back(tmp_path, address: str) -> None:
    port = address.rsplit(":", 1)[1]
    block = simulated_block(tmp_path / "b.laz", rows=1, trees_per_row=3, seed=7, density=0.3)
    srv = ServerProcess(tmp_path / "data", ORCHARD_SCHEDULER=address, ORCHARD_JOB_RETRIES="10",
                        ORCHARD_RETRY_DELAY_S="1", ORCHARD_SCHEDULER_TIMEOUT_S="3", ORCHARD_SCHEDULING="false").start()
    cluster: list[subprocess.Popen] = []
    try:
        token = make_token(srv.data_dir, "farm")
        with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
            up = c.post("/v1/blocks", files={"file": ("b.laz", block.read_bytes())})
            assert up.status_code == 201, up.text
            job = c.post("/v1/jobs", json={"block_id": up.json()["id"], "tiling": {"tile_size": 20}}).json()
            # the first attempt cannot reach the scheduler: queued again, saying why and when
            waiting = wait_for_job(c, job["id"], states=("queued",), timeout=90, when=lambda j: j["attempts"] >= 1)
            assert waiting["error"].startswith("attempt 1 of 11 failed: cannot start or reach the dask cluster")
            assert "trying again from" in waiting["error"] and waiting["retry_at"]
            # the cluster comes back: a later attempt runs the job on it
            logs = open(tmp_path / "cluster.log", "ab")  # noqa: SIM115 - closed below
            cluster.append(subprocess.Popen(
                ["dask", "scheduler", "--host", "127.0.0.1", "--port", port, "--dashboard-address", ":0"],
                stdout=logs, stderr=subprocess.STDOUT, start_new_session=True))
            cluster.append(subprocess.Popen(
                ["dask", "worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard"],
                stdout=logs, stderr=subprocess.STDOUT, start_new_session=True))
            done = wait_for_job(c, job["id"], timeout=240)
            assert done["state"] == "done", (done["error"], srv.log())
            assert done["n_trees"] == 3 and done["attempts"] >= 2 and done["error"] is None and done["retry_at"] is None
    finally:
        srv.stop()
        for proc in reversed(cluster):
            _stop(proc)
        time.sleep(0.1)
