"""Helpers of the service tests: clients of an app started in this process, the app
served by uvicorn in a thread, a real `orchard serve` on loopback, tokens, small blocks."""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
from fastapi.testclient import TestClient

from service.app import create_app
from service.auth import create_token
from service.db.jobstore import Store
from service.settings import Settings


def client_of(started: TestClient, *, token: str | None = None, **kwargs) -> TestClient:
    """Another client of the app ``started`` (a TestClient whose context is entered),
    sending ``token`` as its bearer token if given: its requests run on the event loop
    the app started on, as those of a second client of one server would. Not to be
    entered itself (that would start the app again); close it when done."""
    client = TestClient(started.app, headers={"Authorization": f"Bearer {token}"} if token else None, **kwargs)
    client.portal = started.portal
    return client


@contextlib.contextmanager
def refusing_address() -> Iterator[str]:
    """``tcp://127.0.0.1:PORT`` where nothing listens (a connection is refused) and
    nothing else can start listening while the block runs: the port is held by a socket
    bound and never listening. A dask scheduler may still be started on it on purpose
    (dask binds with SO_REUSEADDR, as this socket is, and only one socket listens)."""
    with socket.socket() as held:
        held.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        held.bind(("127.0.0.1", 0))
        yield f"tcp://127.0.0.1:{held.getsockname()[1]}"


@contextlib.contextmanager
def app_in_thread(settings: Settings) -> Iterator[str]:
    """`create_app(settings)` served by uvicorn on port 0 of loopback in a thread of this
    process (its lifespan runs; faults can be injected into it with monkeypatch); yields
    its base URL, stops it afterwards."""
    import uvicorn

    app = create_app(settings)
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not srv.started and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert srv.started, "the app did not start"
    port = srv.servers[0].sockets[0].getsockname()[1]
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        srv.should_exit = True
        thread.join(30)


class ServerProcess:
    """`orchard serve` in its own process group on port 0 of loopback; ``port`` and
    ``url`` are those it reports (``--port-file``) once started."""

    _started = itertools.count()

    def __init__(self, data_dir: Path, **env: str) -> None:
        self.data_dir = Path(data_dir)
        self.env = {k: str(v) for k, v in env.items()}
        self.port: int | None = None
        self.url = ""
        self.proc: subprocess.Popen | None = None
        name = f"serve-{os.getpid()}-{next(self._started)}"
        self.log_path = self.data_dir.parent / f"{name}.log"
        self.port_file = self.data_dir.parent / f"{name}.port"

    def start(self, timeout: float = 60.0) -> "ServerProcess":
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.port_file.unlink(missing_ok=True)
        env = {**os.environ, "ORCHARD_RUNNER_POLL_S": "0.2", "ORCHARD_N_WORKERS": "2", **self.env}
        cmd = [sys.executable, "-m", "service.cli", "serve", "--data-dir", str(self.data_dir), "--host", "127.0.0.1",
               "--port", "0", "--port-file", str(self.port_file), "--log-level", "warning"]
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(cmd, env=env, stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"orchard serve exited early:\n{self.log()}")
            if self.port_file.exists():  # written once the server listens
                self.port = int(self.port_file.read_text())
                self.url = f"http://127.0.0.1:{self.port}"
                with contextlib.suppress(httpx.HTTPError):
                    if httpx.get(self.url + "/healthz", timeout=30).status_code == 200:
                        return self
            time.sleep(0.1)
        self.kill()
        raise RuntimeError(f"orchard serve did not come up:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-4000:] if self.log_path.exists() else ""

    def kill(self) -> None:
        """SIGKILL the server and everything it started (its process group): a crash."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
        self._reap_group()

    def stop(self) -> None:
        """A graceful stop (SIGTERM), then SIGKILL for whatever is left of the group."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                pass
        self.kill()

    def _reap_group(self) -> None:
        if self.proc is None:
            return
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def temp_files(data_dir: Path, pattern: str = "*") -> list[Path]:
    """The service's temporary files under ``data_dir/tmp`` (in its processes' own
    folders), without those folders' lock files."""
    tmp = Path(data_dir) / "tmp"
    return [p for p in tmp.rglob(pattern) if p.is_file() and p.name != ".lock"] if tmp.is_dir() else []


def tenant_inbox(data_dir: Path, tenant: str, name: str = "inbox") -> Path:
    """A folder in ``tenant``'s inbox folder of a server with the default inbox root
    (``<data dir>/inboxes/<tenant>``): the only place its schedules may watch over HTTP."""
    path = Path(data_dir) / "inboxes" / tenant / name
    path.mkdir(parents=True, exist_ok=True)
    return path


def make_token(data_dir: Path, tenant: str) -> str:
    store = Store(Path(data_dir) / "orchard.sqlite")
    try:
        return create_token(store, tenant)
    finally:
        store.close()


def write_las(path: Path, n: int = 2000, *, seed: int = 0, compressed: bool | None = None) -> Path:
    """A small valid LAS/LAZ file of random points (enough for upload tests, not for trees)."""
    import laspy

    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([500000.0, 6000000.0, 0.0])
    las = laspy.LasData(header)
    las.x = 500000.0 + rng.uniform(0, 10, n)
    las.y = 6000000.0 + rng.uniform(0, 10, n)
    las.z = rng.uniform(0, 3, n)
    las.write(str(path))
    return Path(path)


def simulated_block(path: Path, *, rows: int = 2, trees_per_row: int = 4, seed: int = 7, **kwargs) -> Path:
    """A generated orchard block and its truth beside it."""
    from simulator.simparams import SimulationParams
    from simulator.simulate import simulate_orchard
    from simulator.truth import write_simulation

    params = SimulationParams(rows=rows, trees_per_row=trees_per_row, seed=seed, **kwargs)
    orchard = simulate_orchard(params)
    write_simulation(orchard, str(path), str(path.with_suffix(".truth.parquet")))
    return path


def wait_for_job(client: httpx.Client, job_id: str, *, states=("done", "failed", "cancelled"), timeout: float = 150.0,
                 when=lambda job: True) -> dict:
    """The job once it is in one of ``states`` and ``when(job)`` holds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in states and when(job):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} still {job['state']} after {timeout} s")
