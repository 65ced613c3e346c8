"""Fixtures of the worker tests: small generated blocks and a real dask cluster on loopback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cluster_fixtures import scheduler_address
from pipeline.laswriting import LasBlockWriter
from simulator.simparams import SimulationParams
from simulator.truth import write_simulation


def _simulate(path: Path, **kw) -> Path:
    write_simulation(SimulationParams(**kw), str(path), str(path.with_suffix(".truth.parquet")))
    return path


@pytest.fixture(scope="session")
def small_block(tmp_path_factory) -> Path:
    """8 trees in 2 rows, about 190 k points, LAZ."""
    return _simulate(tmp_path_factory.mktemp("blocks") / "small.laz", rows=2, trees_per_row=4, density=0.2, seed=1)


@pytest.fixture(scope="session")
def sparse_block(tmp_path_factory) -> Path:
    """8 trees in 2 rows at a tenth of the default density, LAZ: a block to count and split."""
    return _simulate(tmp_path_factory.mktemp("blocks") / "sparse.laz", rows=2, trees_per_row=4, density=0.1, seed=11)


@pytest.fixture(scope="session")
def orchard_block(tmp_path_factory) -> Path:
    """40 trees in 4 rows, low density, LAZ."""
    return _simulate(
        tmp_path_factory.mktemp("blocks") / "orchard.laz", rows=4, trees_per_row=10, density=0.15, seed=7
    )


@pytest.fixture(scope="session")
def ground_block(tmp_path_factory) -> Path:
    """A bare, gently sloping ground plane: no trees."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 20, (40_000, 2))
    z = 0.02 * xy[:, 0] + rng.normal(0, 0.01, len(xy))
    path = tmp_path_factory.mktemp("blocks") / "ground.laz"
    with LasBlockWriter(path, crs_epsg=28356) as w:
        w.write(np.column_stack([xy + [500_000.0, 6_950_000.0], z + 100.0]))
    return path


class LoopbackCluster:
    """``dask scheduler`` (on port 0, its address read back) and ``dask worker`` processes on 127.0.0.1."""

    def __init__(self, n_workers: int, log_dir: Path):
        self.log_dir = log_dir
        self.procs: list[subprocess.Popen] = []
        scheduler_file = log_dir / "scheduler.json"
        self.scheduler = self._start(
            ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file", str(scheduler_file)],
            "scheduler",
        )
        try:
            self.address = scheduler_address(scheduler_file, self.scheduler)
        except RuntimeError:
            self.close()
            raise
        self.port = int(self.address.rsplit(":", 1)[1])
        self.workers = [self.start_worker(i) for i in range(n_workers)]
        self.wait_for_workers(n_workers)

    def _start(self, args, name) -> subprocess.Popen:
        log = open(self.log_dir / f"{name}.log", "wb")
        # the dask command of this interpreter (a venv's own may have no ``dask`` script beside it)
        proc = subprocess.Popen([sys.executable, "-m", "dask", *args], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append(proc)
        return proc

    def start_worker(self, i: int) -> subprocess.Popen:
        return self._start(
            [
                "worker", self.address, "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1",
                "--no-nanny", "--no-dashboard", "--name", f"w{i}-{time.monotonic_ns()}", "--death-timeout", "60",
            ],
            f"worker{i}",
        )

    def wait_for_workers(self, n: int, timeout: float = 120.0) -> None:
        from distributed import Client

        with Client(self.address, timeout="30s") as c:
            c.wait_for_workers(n, timeout=timeout)

    def close(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        for p in self.procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=5)


    def ensure_workers(self, n: int) -> None:
        """Replace dead workers until ``n`` are alive."""
        alive = [w for w in self.workers if w.poll() is None]
        while len(alive) < n:
            alive.append(self.start_worker(len(self.workers) + len(alive)))
        self.workers = alive
        self.wait_for_workers(n)


@pytest.fixture(scope="module")
def loopback_cluster(tmp_path_factory):
    cluster = LoopbackCluster(2, tmp_path_factory.mktemp("dask-logs"))
    try:
        yield cluster
    finally:
        cluster.close()


@pytest.fixture
def default_sigint():
    """Python's own Ctrl-C handler here, and so the default one in the commands this test
    starts, even when the suite runs as a shell's background job (which starts it with
    SIGINT ignored, and a command inherits that)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
