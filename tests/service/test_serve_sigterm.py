"""A SIGTERM to the whole process group of a real `orchard serve` running a job (systemd's
stop with KillMode=control-group, ``kill -- -PGID``): the service stops by itself, no
worker is restarted on the way, nothing of the group is left, and the job goes back to
the queue for the next start."""

from __future__ import annotations

import os
import signal
import sqlite3
import time

import httpx
import psutil
import pytest
from service_fixtures import ServerProcess, make_token, simulated_block, wait_for_job

pytestmark = pytest.mark.slow

#: long enough for a stuck shutdown to show; no bound on a normal one's speed
STOP_TIMEOUT_S = 120


def _group(pgid: int) -> list[psutil.Process]:
    """The live processes of process group ``pgid``."""
    found = []
    for p in psutil.process_iter():
        try:
            if os.getpgid(p.pid) == pgid and p.status() != psutil.STATUS_ZOMBIE:
                found.append(p)
        except (ProcessLookupError, psutil.Error):
            continue
    return found


def test_sigterm_to_the_group_stops_the_service_and_requeues_the_running_job(tmp_path):
    block = simulated_block(tmp_path / "orchard.laz", rows=2, trees_per_row=6, seed=5, density=0.6)
    srv = ServerProcess(tmp_path / "data", ORCHARD_SCHEDULING="false", ORCHARD_N_WORKERS="2").start()
    try:
        token = make_token(srv.data_dir, "farm")
        with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
            b = c.post("/v1/blocks", files={"file": (block.name, block.read_bytes())}).json()
            job = c.post("/v1/jobs", json={"block_id": b["id"], "tiling": {"tile_size": 10}}).json()
            wait_for_job(c, job["id"], states=("running",), timeout=300,
                         when=lambda j: 1 <= j["tiles_done"] < j["tiles_total"])
        pgid = srv.proc.pid
        workers = [p for p in _group(pgid) if p.pid != pgid]
        assert len(workers) >= 2, workers  # the two dask workers (and multiprocessing's resource tracker)
        os.killpg(pgid, signal.SIGTERM)
        assert srv.proc.wait(STOP_TIMEOUT_S) == 0, srv.log()
        _, left = psutil.wait_procs(_group(pgid), timeout=30)  # workers leave with their parent
        assert not left, [p.cmdline() for p in left]
        log = srv.log_path.read_text(errors="replace")
        assert "Restarting worker" not in log and "killed by signal" not in log, log[-3000:]
        assert "Traceback" not in log and "ERROR" not in log, log[-3000:]
        con = sqlite3.connect(srv.data_dir / "orchard.sqlite")
        try:
            assert con.execute("PRAGMA integrity_check").fetchone() == ("ok",)
            row = con.execute("SELECT state, attempts, crashes, tiles_done FROM jobs WHERE id = ?", (job["id"],)).fetchone()
        finally:
            con.close()
        assert row == ("queued", 0, 0, 0)  # released, as at every stop: no attempt, no crash used up
    finally:
        srv.kill()
