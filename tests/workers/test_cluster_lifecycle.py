"""The life of a worker process: the modules a job's tasks need are imported as it
starts (embedded workers, and ``dask worker --preload workers.preload``), and an
embedded worker is stopped by the process that started it, not by a SIGTERM sent to
the whole process group."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from workers.cluster import close_client, make_client
from workers.preload import TASK_MODULES

#: modules the first tasks imported before the preload did (the ground task's kernels)
PIPELINE_MODULES = ("workers.tasks", "workers.cellranges", "pipeline.ground", "scipy.sparse.csgraph", "pyarrow")
REPO = Path(__file__).resolve().parents[2]


def _loaded(names) -> dict[str, bool]:
    return {name: name in sys.modules for name in names}


def _term_blocked(_=None) -> bool:
    with open("/proc/thread-self/status") as fh:
        mask = next(line for line in fh if line.startswith("SigBlk:")).split()[1]
    return bool(int(mask, 16) & (1 << (signal.SIGTERM - 1)))


def _pids(client) -> set[int]:
    try:
        return {v for v in client.run(os.getpid, on_error="return").values() if isinstance(v, int)}
    except Exception:  # noqa: BLE001 - a worker leaving meanwhile
        return set()


def test_the_preload_imports_modules_that_exist():
    from workers import preload

    preload.dask_setup(None)  # what dask calls; no worker is needed for imports
    assert all(_loaded(TASK_MODULES).values())


@pytest.mark.slow  # a cluster of worker processes
def test_a_fresh_embedded_worker_has_the_task_modules_before_its_first_task():
    client = make_client(n_workers=1, dashboard=False, quiet=True)
    try:
        (seen,) = client.run(_loaded, TASK_MODULES + PIPELINE_MODULES).values()  # no task has run
    finally:
        close_client(client)
    assert seen == dict.fromkeys(TASK_MODULES + PIPELINE_MODULES, True)


@pytest.mark.slow  # a scheduler and a `dask worker` process
def test_an_external_worker_started_with_the_preload_has_the_task_modules():
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=0, processes=False, protocol="tcp://", host="127.0.0.1", scheduler_port=0,
                      dashboard_address=None) as cluster:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
        worker = subprocess.Popen(
            [sys.executable, "-c", "from distributed.cli.dask_worker import main; main()", cluster.scheduler_address,
             "--nthreads", "1", "--no-nanny", "--no-dashboard", "--preload", "workers.preload"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
        try:
            with Client(cluster) as client:
                client.wait_for_workers(1, timeout=120)
                # (a lambda travels by value: the worker cannot import this test module)
                (seen,) = client.run(lambda names: {n: n in sys.modules for n in names},
                                     TASK_MODULES + PIPELINE_MODULES).values()
        finally:
            os.killpg(worker.pid, signal.SIGTERM)
            worker.wait(30)
    assert seen == dict.fromkeys(TASK_MODULES + PIPELINE_MODULES, True)


@pytest.mark.slow  # a cluster of worker processes
@pytest.mark.skipif(not Path("/proc/thread-self/status").exists(), reason="needs Linux /proc")
def test_an_embedded_worker_drops_a_sigterm_from_outside_and_takes_one_from_its_parent():
    """systemd's stop (KillMode=control-group) and ``kill -- -PGID`` reach the workers as
    well as the service: a worker killed by it was restarted by its nanny while the
    service stopped. Its parent (the nanny's terminate, multiprocessing at exit) must
    still be able to stop it with SIGTERM."""
    client = make_client(n_workers=1, dashboard=False, quiet=True)
    try:
        assert not _term_blocked()  # this thread's mask is as before
        (pid,) = client.run(os.getpid).values()
        assert list(client.run(_term_blocked).values()) == [True]
        worker = psutil.Process(pid)
        subprocess.run(["kill", "-TERM", str(pid)], check=True)  # sent by another process
        with pytest.raises(psutil.TimeoutExpired):
            worker.wait(3)
        assert list(client.run(os.getpid).values()) == [pid]
        os.kill(pid, signal.SIGTERM)  # sent by its parent: this process, where its nanny lives
        worker.wait(60)
        deadline = time.monotonic() + 120  # the nanny starts another
        while time.monotonic() < deadline and not _pids(client) - {pid}:
            time.sleep(0.2)
        assert len(_pids(client) - {pid}) == 1
    finally:
        close_client(client)
