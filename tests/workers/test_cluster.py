"""Dask clients: embedded cluster with a dashboard, unreachable scheduler → clear error,
Ctrl-C handled by this process alone."""

from __future__ import annotations

import os
import signal
import socket
import time
from pathlib import Path

import pytest

from pipeline.errors import ParameterError
from workers.cluster import (
    close_client,
    dashboard_address,
    interrupts_deferred,
    make_client,
    worker_allocator,
    WORKER_MALLOC_ENV,
)


def test_embedded_cluster_has_workers_and_a_dashboard():
    client = make_client(n_workers=1, processes=False)
    try:
        assert len(client.scheduler_info()["workers"]) == 1
        assert dashboard_address(client).startswith("http://")
        assert client.submit(sum, [1, 2, 3]).result(timeout=30) == 6
    finally:
        close_client(client)


@pytest.mark.slow  # a cluster of worker processes
def test_embedded_worker_processes_get_the_allocator_settings_not_dasks_trim():
    client = make_client(n_workers=1, dashboard=False, quiet=True)
    try:
        seen = client.run(lambda: {k: os.environ.get(k) for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_",
                                                                  "OMP_NUM_THREADS")})
    finally:
        close_client(client)
    (env,) = seen.values()
    assert env == {**WORKER_MALLOC_ENV, "OMP_NUM_THREADS": "1"}  # dask's other settings kept


def test_the_allocator_settings_are_given_only_within_worker_allocator():
    import dask

    before = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
    with worker_allocator():
        inside = dask.config.get("distributed.nanny.pre-spawn-environ")
    assert inside == {**before, **WORKER_MALLOC_ENV} and inside["OMP_NUM_THREADS"] == before["OMP_NUM_THREADS"]
    assert dask.config.get("distributed.nanny.pre-spawn-environ") == before


def test_no_dashboard():
    client = make_client(n_workers=1, processes=False, dashboard=False)
    try:
        assert dashboard_address(client) is None
    finally:
        close_client(client)


def test_unreachable_scheduler_is_a_parameter_error():
    with socket.socket() as s:  # bound, never listening: refused, and no other process can take the port meanwhile
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        with pytest.raises(ParameterError, match=f"127.0.0.1:{port}.*dask scheduler"):
            make_client(f"tcp://127.0.0.1:{port}", timeout="0.5s")


def test_a_port_that_accepts_but_never_answers_is_a_parameter_error_in_time():
    # distributed's Client waited for good on such a port (a web server; the dashboard's
    # 8787 typed for the scheduler's 8786): the service's job stayed "running" for ever
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(8)  # the kernel completes the connection; nobody ever answers
        port = s.getsockname()[1]
        t = time.monotonic()
        with pytest.raises(ParameterError, match=f"no dask scheduler answered at tcp://127.0.0.1:{port} within 0.5 s"):
            make_client(f"tcp://127.0.0.1:{port}", timeout="0.5s")
        assert time.monotonic() - t < 30


def _sigint_blocked(_=None) -> bool:
    with open("/proc/thread-self/status") as fh:
        mask = next(line for line in fh if line.startswith("SigBlk:")).split()[1]
    return bool(int(mask, 16) & (1 << (signal.SIGINT - 1)))


@pytest.mark.slow  # a cluster of worker processes
@pytest.mark.skipif(not Path("/proc/thread-self/status").exists(), reason="needs Linux /proc")
def test_embedded_workers_do_not_take_ctrl_c_and_this_thread_does():
    """A terminal's Ctrl-C reaches every process of its group: the embedded workers
    must leave it to this process (which stops them) instead of each printing a
    KeyboardInterrupt traceback; the calling thread's own mask is as before."""
    client = make_client(n_workers=1, dashboard=False)
    try:
        assert not _sigint_blocked()
        worker_blocked = client.run(_sigint_blocked)
        assert list(worker_blocked.values()) == [True]
    finally:
        close_client(client)


def test_interrupt_during_a_shutdown_is_held_until_it_ends(default_sigint):
    done = []
    with pytest.raises(KeyboardInterrupt), interrupts_deferred():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.2)  # the signal is delivered meanwhile
        done.append(True)
    assert done == [True]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with interrupts_deferred():  # nothing caught, nothing raised
        pass


def test_an_embedded_workers_closing_noise_is_dropped_and_nothing_else():
    import logging

    from workers.cluster import _ClosingNoise

    def record(msg):
        return logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1, msg, None, None)

    noise = _ClosingNoise()
    assert not noise.filter(record("Failed to communicate with scheduler during heartbeat."))
    assert not noise.filter(record("Async instruction for <Task 'x' executing> ended with CancelledError"))
    assert noise.filter(record("Unexpected exception during heartbeat. Closing worker."))
    assert noise.filter(record("Compute Failed"))
