"""The compose topology without Docker, end to end.

``docker/local-topology.sh`` starts a real ``dask scheduler``, two ``dask worker``
processes and ``orchard serve --scheduler ...`` as separate processes on 127.0.0.1, each
on port 0 (the port it got read back). Through it: a token from ``orchard tokens create``, a generated block
uploaded over HTTP, a tiled job run on the two workers, its trees checked against the
simulation truth; then SIGTERM to the script must stop every process it started.
Every wait is bounded; nothing here can hang the suite.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from workers.cluster import WORKER_MALLOC_ENV
from workers.preload import TASK_MODULES

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "docker" / "local-topology.sh"
ENTRYPOINT = ROOT / "docker" / "entrypoint.sh"
START_TIMEOUT = 150.0
JOB_TIMEOUT = 300.0
STOP_TIMEOUT = 45.0

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("dask") is None, reason="the `dask` command is not installed"),
    pytest.mark.skipif(shutil.which("orchard") is None, reason="the `orchard` command is not installed (pip install -e .)"),
]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is not alive
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def _kill_everything(proc: subprocess.Popen, pids: list[int]) -> None:
    """SIGKILL the script's and every role's process group, and reap the script."""
    for pid in [proc.pid, *pids]:
        try:
            os.killpg(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
    if proc.poll() is None:
        proc.kill()
        proc.wait(timeout=10)


READY_KEYS = ("ORCHARD_URL", "ORCHARD_SCHEDULER", "ORCHARD_DATA_DIR", "DASHBOARD_URL", "LOG_DIR", "PIDS", "TOPOLOGY_PID")


def _read_env(path: Path) -> dict[str, str]:
    """The ready file's variables, as a shell that sources it sees them (the documented
    use: an unquoted list of pids made `source` fail)."""
    script = 'set -a; source "$1"; for k in "${@:2}"; do printf "%s=%s\\0" "$k" "${!k}"; done'
    run = subprocess.run(["bash", "-c", script, "_", str(path), *READY_KEYS],
                         capture_output=True, text=True, timeout=30, check=False)
    assert run.returncode == 0 and not run.stderr, run.stderr
    return dict(item.split("=", 1) for item in run.stdout.split("\0") if "=" in item)


def _tail(path: Path, n: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


@pytest.fixture
def topology(tmp_path):
    data = tmp_path / "data"
    ready = tmp_path / "ready.env"
    log = tmp_path / "topology.log"
    with open(log, "w") as logf:
        proc = subprocess.Popen(
            ["bash", str(SCRIPT), "--data-dir", str(data), "--ready-file", str(ready)],
            stdout=logf, stderr=subprocess.STDOUT, start_new_session=True,
            # dask's nanny leaves its trim setting in the parent's environment: a test
            # process that started a LocalCluster passes it on, as here
            env=dict(os.environ, ORCHARD_TOPOLOGY_TIMEOUT="90", MALLOC_TRIM_THRESHOLD_="65536"),
        )
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while not ready.exists():
            if proc.poll() is not None:
                pytest.fail(f"local-topology.sh exited ({proc.returncode}) before it was up:\n{_tail(log)}")
            if time.monotonic() > deadline:
                pytest.fail(f"local-topology.sh not up after {START_TIMEOUT:.0f} s:\n{_tail(log)}")
            time.sleep(0.2)
        env = _read_env(ready)
        env["_log"] = str(log)
        yield proc, env
    finally:
        # Clean shutdown through the script: SIGTERM must stop everything it started.
        pids = [int(p) for p in _read_env(ready).get("PIDS", "").split()] if ready.exists() else []
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=STOP_TIMEOUT)
            clean = True
        except subprocess.TimeoutExpired:
            clean = False
        leftovers = []
        for pid in pids:
            deadline = time.monotonic() + 10
            while _alive(pid) and time.monotonic() < deadline:
                time.sleep(0.1)
            if _alive(pid):
                leftovers.append(pid)
        _kill_everything(proc, pids)  # never leave anything behind, even when the test fails
        assert clean, f"local-topology.sh did not stop within {STOP_TIMEOUT:.0f} s of SIGTERM:\n{_tail(log)}"
        assert not leftovers, f"processes still running after shutdown: {leftovers}"
        assert not ready.exists(), "the ready file should be removed on shutdown"


def _health(role: str, port: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, DASK_DASHBOARD_PORT=port, ORCHARD_PORT=port)
    return subprocess.run(["bash", str(ENTRYPOINT), "health", role], capture_output=True, text=True, timeout=30, env=env)


def test_job_end_to_end_through_separate_processes(topology, tmp_path):
    import distributed
    import httpx

    from simulator.scoring.scores import trunk_scores
    from simulator.simparams import SimulationParams
    from simulator.truth import read_truth, write_simulation

    proc, env = topology
    url, scheduler, data_dir = env["ORCHARD_URL"], env["ORCHARD_SCHEDULER"], env["ORCHARD_DATA_DIR"]
    pids = [int(p) for p in env["PIDS"].split()]
    assert len(pids) == 4  # scheduler, two workers, api
    assert all(_alive(p) for p in pids)

    # The compose health checks' probes work against the real processes.
    assert _health("scheduler", env["DASHBOARD_URL"].rsplit(":", 1)[1]).returncode == 0
    assert _health("api", url.rsplit(":", 1)[1]).returncode == 0

    with distributed.Client(scheduler, timeout=30) as client:
        workers = client.scheduler_info(n_workers=-1)["workers"]
        assert len(workers) == 2
        worker_pids = set(client.run(os.getpid).values())
        assert len(worker_pids) == 2 and pids[-1] not in worker_pids  # separate from the API process
        # the workers run with the embedded cluster's allocator settings, not dask's trim
        environ = client.run(lambda: {k: os.environ.get(k) for k in WORKER_MALLOC_ENV})
        assert list(environ.values()) == [WORKER_MALLOC_ENV] * 2, environ
        # and with orchard's task modules imported as they started (--preload workers.preload)
        preloaded = client.run(lambda: all(m in sys.modules for m in TASK_MODULES))
        assert list(preloaded.values()) == [True, True], preloaded

        # A token, the same way an operator gets one.
        tok = subprocess.run(
            ["orchard", "tokens", "create", "--tenant", "topology-farm", "--data-dir", data_dir],
            capture_output=True, text=True, timeout=60,
        )
        assert tok.returncode == 0, tok.stderr
        token = tok.stdout.strip()
        assert token and "\n" not in token
        auth = {"Authorization": f"Bearer {token}"}

        las, truth = tmp_path / "block.laz", tmp_path / "truth.parquet"
        sim = write_simulation(SimulationParams(rows=2, trees_per_row=3, seed=5, density=0.6), str(las), str(truth))

        with httpx.Client(base_url=url, timeout=60) as http:
            assert http.get("/v1/jobs").status_code == 401  # tokens are required
            with open(las, "rb") as fh:
                r = http.post("/v1/blocks", files={"file": ("block.laz", fh, "application/octet-stream")}, headers=auth)
            assert r.status_code in (200, 201), r.text
            block = r.json()
            assert block["n_points"] == sim["n_points"]

            with distributed.get_task_stream(client) as stream:
                r = http.post("/v1/jobs", json={"block_id": block["id"], "params": {}, "tiling": {"tile_size": 10.0}}, headers=auth)
                assert r.status_code in (200, 201, 202), r.text
                job_id = r.json()["id"]
                deadline = time.monotonic() + JOB_TIMEOUT
                while True:
                    job = http.get(f"/v1/jobs/{job_id}", headers=auth).json()
                    if job["state"] in ("done", "failed", "cancelled"):
                        break
                    assert proc.poll() is None, f"the topology died during the job:\n{_tail(Path(env['_log']))}"
                    if time.monotonic() > deadline:
                        pytest.fail(f"job not finished after {JOB_TIMEOUT:.0f} s: {job}")
                    time.sleep(0.5)
            assert job["state"] == "done", job.get("error")
            assert job["tiles_total"] > 1 and job["tiles_done"] == job["tiles_total"]
            assert not job.get("partial")

            # The tiles ran on the two topology workers, not in the API process.
            ran_on = {t.get("worker") for t in stream.data}
            assert ran_on and ran_on <= set(workers), ran_on

            r = http.get(f"/v1/jobs/{job_id}/trees", params={"limit": 1000}, headers=auth)
            assert r.status_code == 200, r.text
            page = r.json()
            trees = page["items"]
            assert page["total"] == len(trees) == job["n_trees"]

    _, true_trunks = read_truth(str(truth))
    found = np.array([[t["trunk_x"], t["trunk_y"]] for t in trees], dtype=float).reshape(-1, 2)
    scores = trunk_scores(true_trunks, found, match_distance=1.0)
    assert scores["recall"] >= 5 / 6 and scores["precision"] >= 5 / 6, scores
    assert all(t["height_m"] > 1.5 for t in trees)


def test_a_command_run_in_the_topology_gets_its_variables_and_sigterm_stops_everything(tmp_path):
    # with `-- COMMAND` a SIGTERM waited until the command ended (bash runs traps only
    # between foreground commands): `timeout 600 local-topology.sh -- client` overran
    ready, seen, log = tmp_path / "ready.env", tmp_path / "seen", tmp_path / "topology.log"
    command = f'echo "$ORCHARD_URL $ORCHARD_SCHEDULER" > {seen}; exec sleep 300'
    with open(log, "w") as logf:
        proc = subprocess.Popen(
            ["bash", str(SCRIPT), "--data-dir", str(tmp_path / "data"), "--workers", "1", "--ready-file", str(ready),
             "--", "sh", "-c", command],
            stdout=logf, stderr=subprocess.STDOUT, start_new_session=True,
        )
    pids: list[int] = []
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while not (ready.exists() and seen.exists() and seen.read_text().strip()):
            assert proc.poll() is None and time.monotonic() < deadline, _tail(log)
            time.sleep(0.2)
        env = _read_env(ready)
        pids = [int(p) for p in env["PIDS"].split()]
        assert seen.read_text().split() == [env["ORCHARD_URL"], env["ORCHARD_SCHEDULER"]]
        sleeper = int(subprocess.run(["pgrep", "-f", "sleep 300", "-P", str(proc.pid)],
                                     capture_output=True, text=True, timeout=10, check=False).stdout.split()[0])
        t = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=STOP_TIMEOUT) == 143, _tail(log)
        assert time.monotonic() - t < 30, "it waited for the command to end"
        assert not _alive(sleeper) and not any(_alive(p) for p in pids)
    finally:
        _kill_everything(proc, pids)
