"""A job during which the service keeps dying (SIGKILL) is failed, not run at every start.

Real `orchard serve` processes. While the service is pointed at a dask scheduler that
does not answer, its job stays ``running`` (waiting to connect) for as long as the test
needs: the service is killed with SIGKILL there, twice, as an out-of-memory kill would.
The third start fails the job with the reason (ORCHARD_MAX_CRASHES, default 2) and
runs the next queued job to the end on an embedded cluster.
"""

from __future__ import annotations

import sqlite3

import httpx
import pytest
from service_fixtures import ServerProcess, make_token, refusing_address, simulated_block, wait_for_job

pytestmark = pytest.mark.slow


def test_a_job_that_keeps_killing_the_service_is_failed_and_the_next_one_runs(tmp_path):
    with refusing_address() as address:
        _keeps_killing_the_service(tmp_path, address)


def _keeps_killing_the_service(tmp_path, address: str) -> None:
    block = simulated_block(tmp_path / "b.laz", rows=1, trees_per_row=3, seed=7, density=0.3)
    data = tmp_path / "data"
    # nothing listens at this address: a job waits there up to the timeout, "running"
    hanging = {"ORCHARD_SCHEDULER": address, "ORCHARD_SCHEDULER_TIMEOUT_S": "300", "ORCHARD_SCHEDULING": "false"}
    token = make_token(data, "farm")
    auth = {"Authorization": f"Bearer {token}"}
    seen = []
    for crash in (1, 2):
        srv = ServerProcess(data, **hanging).start()
        try:
            with httpx.Client(base_url=srv.url, headers=auth, timeout=60) as c:
                if crash == 1:
                    up = c.post("/v1/blocks", files={"file": ("b.laz", block.read_bytes())})
                    assert up.status_code == 201, up.text
                    poison = c.post("/v1/jobs", json={"block_id": up.json()["id"]}).json()["id"]
                    after = c.post("/v1/jobs", json={"block_id": up.json()["id"]}).json()["id"]
                job = wait_for_job(c, poison, states=("running",), timeout=60)
                seen.append((job["crashes"], job["attempts"]))
        finally:
            srv.kill()  # SIGKILL, the whole process group: no shutdown of any kind
        con = sqlite3.connect(data / "orchard.sqlite")
        assert con.execute("SELECT state FROM jobs WHERE id = ?", (poison,)).fetchone()[0] == "running"
        con.close()
    # the service's deaths are crashes, not attempts: each start is the job's first attempt
    assert seen == [(0, 1), (1, 1)]
    srv = ServerProcess(data, ORCHARD_SCHEDULING="false").start()  # an embedded cluster that works
    try:
        with httpx.Client(base_url=srv.url, headers=auth, timeout=60) as c:
            failed = c.get(f"/v1/jobs/{poison}").json()
            assert failed["state"] == "failed" and failed["crashes"] == 2, failed
            assert failed["error"].startswith("the service stopped 2 times while running this job; it is not retried")
            done = wait_for_job(c, after, timeout=240)
            assert done["state"] == "done", (done["error"], srv.log())
            assert done["crashes"] == 0 and done["n_trees"] == 3
            assert c.get(f"/v1/jobs/{poison}").json()["state"] == "failed"  # not picked up again
            assert "failed: the service stopped 2 times while running it" in srv.log()
    finally:
        srv.stop()
