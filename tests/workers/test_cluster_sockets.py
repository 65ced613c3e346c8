"""What the dask clusters listen on, and external workers that cannot run our tasks.

- After a real job, nothing in the process tree (this process with an embedded cluster,
  or a real ``orchard serve`` subprocess) listens beyond loopback by default; with the
  dashboard off no port there answers HTTP at all, with it on exactly one does.
- ``orchard process --scheduler`` against a real ``dask worker`` that cannot import the
  project exits 2 at once, naming the worker and what to install (it used to wait for
  workers until the job gave up); another version or other pipeline parameters on the
  workers are refused the same way; a job whose workers all die stops with a message.
"""

from __future__ import annotations

import contextlib
import os
import signal
import site
import socket
import subprocess
import sys
from pathlib import Path

import httpx
import psutil
import pytest
from cluster_fixtures import scheduler_address
from distributed import Client

from pipeline.jobparams import JobParams, TilingParams
from simulator.simparams import SimulationParams
from simulator.truth import write_simulation
from service.cli import main as orchard
from tests.service.service_fixtures import ServerProcess, make_token, wait_for_job
from workers import cluster as cluster_module
from workers import dispatch
from workers.cluster import WorkersUnfit, check_workers, close_client, dashboard_address, make_client
from workers.identity import identity
from workers.job import run_job
from workers.jobspec import ClusterLost, JobSpec

LOOPBACK_IPS = {"127.0.0.1", "::1"}


@pytest.fixture(scope="module")
def tiny_block(tmp_path_factory) -> Path:
    """Two trees, a few tiles of 6 m."""
    path = tmp_path_factory.mktemp("blocks") / "tiny.laz"
    write_simulation(SimulationParams(rows=1, trees_per_row=2, density=0.1, seed=3), str(path),
                     str(path.with_suffix(".truth.parquet")))
    return path


def listening(pid: int) -> set[tuple[str, int]]:
    """(address, port) of every listening inet socket of process ``pid`` and its descendants."""
    root = psutil.Process(pid)
    found = set()
    for proc in [root, *root.children(recursive=True)]:
        try:
            conns = proc.net_connections(kind="inet")
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        found |= {(c.laddr.ip, c.laddr.port) for c in conns if c.status == psutil.CONN_LISTEN}
    return found


def answers_http(ip: str, port: int) -> bool:
    """Whether an HTTP request to ``ip:port`` gets an HTTP answer (any status) within 2 s;
    a dask comm port reads the request as a malformed frame and answers nothing."""
    try:
        with socket.create_connection((ip, port), timeout=2) as sock:
            # /healthz: the service answers it at once; its first 404 (of /health) took 1.4 s
            # on a loaded machine, past this timeout; any HTTP server answers it, 404 or not
            sock.sendall(b"GET /healthz HTTP/1.0\r\nHost: x\r\n\r\n")
            return sock.recv(5) == b"HTTP/"
    except OSError:
        return False


def http_ports(found: set[tuple[str, int]]) -> set[int]:
    return {port for ip, port in found if answers_http("127.0.0.1" if ip in ("0.0.0.0", "::") else ip, port)}


# -- the embedded cluster ------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("dashboard", [False, True])
def test_embedded_cluster_listens_on_loopback_alone_after_a_job(tiny_block, tmp_path, dashboard):
    before = listening(os.getpid())
    client = make_client(n_workers=2, dashboard=dashboard, quiet=True)
    try:
        outcome = run_job(JobSpec(str(tiny_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=6.0))), client=client)
        assert outcome.n_tiles > 1 and outcome.n_trees >= 1
        new = listening(os.getpid()) - before
        # scheduler, two nannies, two workers (and the dashboard): all there, all on loopback
        assert len(new) >= 5
        assert {ip for ip, _ in new} <= LOOPBACK_IPS, new
        link = dashboard_address(client)
        if dashboard:
            assert link.startswith("http://127.0.0.1:")
            assert http_ports(new) == {int(link.split(":")[2].split("/")[0])}
        else:
            assert link is None
            assert http_ports(new) == set()  # not the scheduler's metrics server, not the workers'
    finally:
        close_client(client)


@pytest.mark.slow
def test_the_operator_can_expose_the_embedded_cluster_deliberately():
    before = listening(os.getpid())
    client = make_client(n_workers=1, dashboard=True, quiet=True, host="0.0.0.0")
    try:
        assert client.submit(sum, [1, 2]).result(timeout=60) == 3
        new = listening(os.getpid()) - before
        assert {ip for ip, _ in new} == {"0.0.0.0"}
        assert len(http_ports(new)) == 1
    finally:
        close_client(client)


def test_a_host_that_is_not_this_machines_is_a_parameter_error():
    with pytest.raises(cluster_module.ParameterError, match="cannot listen on '192.0.2.254'"):
        make_client(n_workers=1, host="192.0.2.254")  # TEST-NET-1: never an address of this machine


@pytest.mark.slow
def test_orchard_serve_listens_on_loopback_alone_after_a_job(tiny_block, tmp_path):
    srv = ServerProcess(tmp_path / "data", ORCHARD_SCHEDULING="false").start()
    try:
        token = make_token(srv.data_dir, "farm")
        with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
            up = c.post("/v1/blocks", files={"file": ("tiny.laz", tiny_block.read_bytes())})
            assert up.status_code == 201, up.text
            job = c.post("/v1/jobs", json={"block_id": up.json()["id"], "tiling": {"tile_size": 6}}).json()
            done = wait_for_job(c, job["id"], timeout=240)
            assert done["state"] == "done", (done["error"], srv.log())
            found = listening(srv.proc.pid)
        assert len(found) >= 6, found  # the API, and the embedded cluster that ran the job
        assert {ip for ip, _ in found} <= LOOPBACK_IPS, found
        assert http_ports(found) == {srv.port}  # the dashboard is off by default: no other HTTP server
    finally:
        srv.stop()


# -- workers of an external cluster --------------------------------------------------------


_SCHEDULER_ARGS = ("--host", "127.0.0.1", "--no-dashboard", "--port", "0")
_WORKER_ARGS = ("--nthreads", "1", "--no-dashboard", "--no-nanny")


def _start(logs, *args: str, cwd=None) -> subprocess.Popen:
    """``python ARGS`` in a process group of its own, its output in ``logs``."""
    return subprocess.Popen([sys.executable, *args], cwd=cwd, stdout=logs, stderr=subprocess.STDOUT,
                            start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


# A dask worker in a Python that has dask but not the project: no site module (so no
# .pth file, and with it no editable install), no PYTHONPATH (-I), run from another
# folder, with only the site-packages folders on its path.
_BARE_WORKER = (
    "import sys; sys.path[:0] = sys.argv.pop(1).split(':'); "
    "from distributed.cli.dask_worker import main; main()"
)


@contextlib.contextmanager
def one_worker_cluster(folder: Path, *, bare: bool = False):
    """``dask scheduler`` and one ``dask worker`` (without the project if ``bare``) on
    loopback: yields the scheduler's address, the worker's address and the worker process."""
    logs = open(folder / "cluster.log", "ab")  # noqa: SIM115 - closed below
    scheduler_file = folder / "scheduler.json"
    procs = [_start(logs, "-m", "distributed.cli.dask_scheduler", *_SCHEDULER_ARGS, "--scheduler-file", str(scheduler_file))]
    try:
        address = scheduler_address(scheduler_file, procs[0])
        if bare:
            paths = ":".join(site.getsitepackages())
            procs.append(_start(logs, "-I", "-S", "-c", _BARE_WORKER, paths, address, *_WORKER_ARGS, cwd=folder))
        else:
            procs.append(_start(logs, "-m", "distributed.cli.dask_worker", address, *_WORKER_ARGS))
        with Client(address, timeout="60s") as c:
            c.wait_for_workers(1, timeout=120)
            (worker,) = c.ncores()
        yield address, worker, procs[1]
    finally:
        for proc in reversed(procs):
            _stop(proc)
        logs.close()


@pytest.mark.slow
def test_a_worker_without_the_project_is_named_at_once(tiny_block, tmp_path):
    with one_worker_cluster(tmp_path, bare=True) as (address, worker, worker_proc):
        proc = subprocess.run(
            [sys.executable, "-m", "service.cli", "process", str(tiny_block), "--out", str(tmp_path / "out"),
             "--tile-size", "6", "--scheduler", address],
            capture_output=True, text=True, timeout=120,  # it waited for workers until the job gave up
        )
        assert proc.returncode == 2, proc.stderr
        assert f"1 of 1 dask worker(s) of {address} cannot run orchard tiles: {worker} cannot import the project " \
               "(ModuleNotFoundError: No module named 'workers')" in proc.stderr
        assert f"Install orchard-trees {identity()['version']}" in proc.stderr and "Traceback" not in proc.stderr
        assert worker_proc.poll() is None  # told before any task was sent: the worker is still there


@pytest.mark.slow
def test_the_service_fails_a_job_on_a_worker_without_the_project_saying_why(tiny_block, tmp_path):
    with one_worker_cluster(tmp_path, bare=True) as (address, worker, _):
        srv = ServerProcess(tmp_path / "data", ORCHARD_SCHEDULER=address, ORCHARD_JOB_RETRIES="0",
                            ORCHARD_SCHEDULING="false").start()
        try:
            token = make_token(srv.data_dir, "farm")
            with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
                up = c.post("/v1/blocks", files={"file": ("tiny.laz", tiny_block.read_bytes())})
                job = c.post("/v1/jobs", json={"block_id": up.json()["id"], "tiling": {"tile_size": 6}}).json()
                failed = wait_for_job(c, job["id"], timeout=120)
        finally:
            srv.stop()
    assert failed["state"] == "failed", failed
    assert f"{worker} cannot import the project (ModuleNotFoundError: No module named 'workers')" in failed["error"]
    assert failed["error"].endswith("into the Python of each of those workers, then restart them"), failed["error"]


@pytest.mark.slow
def test_a_job_whose_workers_all_die_stops_saying_so(tiny_block, tmp_path, monkeypatch):
    monkeypatch.setattr(dispatch, "NO_WORKER_TIMEOUT", 1.0)
    with one_worker_cluster(tmp_path) as (address, _, worker_proc):

        def kill_the_worker(done: int, total: int) -> None:
            if done == 1:  # the rest of the tiles wait for a worker that will not come back
                os.killpg(worker_proc.pid, signal.SIGKILL)

        with Client(address, timeout="60s") as client:
            with pytest.raises(ClusterLost, match=r"no dask worker for 1 s \(they died or left; their logs say why\) "
                                                  r"with \d+ tiles to go"):
                run_job(JobSpec(str(tiny_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=4.0))), client=client,
                        progress=kill_the_worker)
        assert worker_proc.wait(10) == -signal.SIGKILL


@pytest.fixture
def inprocess_cluster(dask_cluster):
    """The fast tests' shared cluster (workers in this process), reached over TCP as an external cluster."""
    return dask_cluster


def test_workers_of_the_same_project_pass(inprocess_cluster):
    client = make_client(inprocess_cluster.scheduler_address)
    try:
        assert client.submit(sum, [1, 2]).result(timeout=30) == 3
    finally:
        client.close()


def test_another_version_on_the_workers_is_refused(inprocess_cluster, monkeypatch, tmp_path, tiny_block, capsys):
    here = identity()
    monkeypatch.setattr(cluster_module, "expected_identity", lambda: {**here, "version": "9.9.9"})
    code = orchard(["process", str(tiny_block), "--out", str(tmp_path / "out"), "--tile-size", "6",
                    "--scheduler", inprocess_cluster.scheduler_address])
    err = capsys.readouterr().err
    assert code == 2, err
    for worker in inprocess_cluster.scheduler.workers:
        assert f"{worker} ({here['python']} on {here['host']}) has orchard-trees {here['version']}, not 9.9.9" in err
    assert "Install orchard-trees 9.9.9" in err
    assert not (tmp_path / "out").exists()


def test_other_pipeline_parameters_on_the_workers_are_refused(inprocess_cluster):
    with Client(inprocess_cluster) as client:
        with pytest.raises(WorkersUnfit, match="with other pipeline parameters") as info:
            check_workers(client, expected={**identity(), "schema": "0" * 16})
    assert list(info.value.problems) == list(inprocess_cluster.scheduler.workers)


def test_at_most_a_few_workers_are_named():
    problems = {f"tcp://10.0.0.{i}:1": "cannot import the project (x)" for i in range(5)}
    text = str(WorkersUnfit("tcp://s:8786", problems, 6, identity()))
    assert text.startswith("5 of 6 dask worker(s) of tcp://s:8786 cannot run orchard tiles: tcp://10.0.0.0:1 ")
    assert "tcp://10.0.0.2:1" in text and "tcp://10.0.0.3:1" not in text and "; and 2 more." in text


def test_a_worker_that_does_not_answer_in_time_is_not_refused(inprocess_cluster, monkeypatch):
    monkeypatch.setattr(Client, "run", lambda self, *a, **k: (_ for _ in ()).throw(TimeoutError()))
    with Client(inprocess_cluster) as client:
        check_workers(client, seconds=0.1)
