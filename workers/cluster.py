"""Dask clients: an embedded LocalCluster, or an existing cluster by address."""

from __future__ import annotations

import logging
import signal
import threading
from contextlib import contextmanager
from multiprocessing import resource_tracker

from dask.utils import parse_timedelta
from distributed import Client, LocalCluster

from pipeline.errors import ParameterError


def _check_answers(address: str, seconds: float) -> None:
    """TimeoutError unless a dask scheduler answers at ``address`` within ``seconds``.

    distributed's Client waits forever on a port that accepts connections but does not
    answer its handshake (a web server, the dashboard's 8787 typed for 8786): a job
    stayed "running" for good. One comm opened and closed under a deadline of our own
    tells a scheduler from those.
    """
    import asyncio

    from distributed.comm import connect

    async def knock() -> None:
        comm = await asyncio.wait_for(connect(address, timeout=seconds), seconds)
        await comm.close()

    asyncio.run(knock())


def make_client(
    scheduler: str | None = None,
    n_workers: int = 2,
    threads_per_worker: int = 1,
    dashboard: bool = True,
    *,
    processes: bool = True,
    memory_limit: str | float | None = "auto",
    timeout: str = "20s",
    quiet: bool = False,
) -> Client:
    """A dask client.

    Parameters
    ----------
    scheduler : str, optional
        Address of a running scheduler (``tcp://HOST:PORT``, started with
        ``dask scheduler``); None starts an embedded ``LocalCluster``.
    n_workers, threads_per_worker : int
        Size of the embedded cluster (one thread per worker: the pipeline's kernels
        are numpy/scipy bound and a tile's memory is per worker).
    dashboard : bool
        Serve the dashboard on a free port (``client.dashboard_link`` tells where).
    processes : bool
        Worker processes (True) or threads of this process (False; needed for a
        ``memory://`` work store).
    timeout : str
        How long to try to reach ``scheduler``.
    quiet : bool
        Embedded cluster only: its workers print nothing (a failing tile is reported once,
        by the job, instead of as a worker traceback per attempt).

    Raises
    ------
    ParameterError
        The scheduler cannot be reached.
    """
    if scheduler:
        try:
            _check_answers(scheduler, parse_timedelta(timeout))
            return Client(scheduler, timeout=timeout)
        except TimeoutError:
            raise ParameterError(
                f"no dask scheduler answered at {scheduler} within {parse_timedelta(timeout):g} s (TimeoutError); "
                "start one with `dask scheduler`, or fix --scheduler (its port, 8786 by default, not the "
                "dashboard's 8787)"
            ) from None
        except (OSError, ValueError) as exc:
            raise ParameterError(
                f"cannot reach the dask scheduler at {scheduler} ({type(exc).__name__}); "
                "start one with `dask scheduler` or fix --scheduler"
            ) from None
    with _workers_ignore_interrupt():
        cluster = LocalCluster(
            n_workers=int(n_workers),
            threads_per_worker=int(threads_per_worker),
            processes=processes,
            # the scheduler's HTTP server runs either way; on a free port, so that a second
            # cluster (or anything else on 8787) is no cause for a warning
            dashboard_address=":0",
            memory_limit=memory_limit,
            silence_logs=logging.CRITICAL if quiet else logging.WARNING,
            preload=[__name__] if processes else None,  # dask_setup below, in each worker
        )
    client = Client(cluster)
    client.orchard_dashboard = dashboard  # the HTTP server runs anyway; remember whether it serves the dashboard
    return client


class _ClosingNoise(logging.Filter):
    """Drops the warning a worker logs for each task it was running when it was closed
    ("Async instruction for <Task ...> ended with CancelledError": distributed logs it
    only from ``Worker.close``), which otherwise follows every shutdown mid-job."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).endswith("ended with CancelledError")


def dask_setup(worker) -> None:
    """Preload hook of the embedded cluster's workers (dask calls it at worker start)."""
    logging.getLogger("distributed.worker.state_machine").addFilter(_ClosingNoise())


@contextmanager
def _workers_ignore_interrupt():
    """Start an embedded cluster with SIGINT blocked in the starting thread.

    A terminal's Ctrl-C goes to its whole process group, worker processes included,
    each of which then printed a KeyboardInterrupt traceback while this process was
    already shutting them down. The cluster's event-loop thread, created in here,
    inherits the blocked signal, and so do the worker processes it spawns (now and
    when a worker is restarted): they are stopped by this process, never by Ctrl-C.
    This thread's own mask is restored on the way out, so an interrupt that arrived
    meanwhile is delivered then.
    """
    # multiprocessing's resource tracker, when it first starts (here: at the first worker's
    # queue), unblocks SIGINT in the thread that starts it; start it beforehand
    resource_tracker.ensure_running()
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    except (AttributeError, OSError, ValueError):  # no POSIX signal masks
        yield
        return
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextmanager
def interrupts_deferred():
    """Let a shutdown finish before Ctrl-C takes effect.

    In the main thread, a SIGINT that arrives inside the block is held back and acted on
    (as ``KeyboardInterrupt``, or whatever the previous handler does) when the block
    ends: interrupted half-way, closing a cluster left it to an exit hook of
    distributed's that then failed with a traceback. Elsewhere (signals go to the main
    thread) it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught and callable(previous):
        previous(signal.SIGINT, None)
    elif caught and previous == signal.SIG_DFL:
        raise KeyboardInterrupt


def dashboard_address(client: Client) -> str | None:
    """The dashboard URL of a client's cluster, or None when it has none."""
    if getattr(client, "orchard_dashboard", True) is False:
        return None
    try:
        info = client.scheduler_info()
        port = info.get("services", {}).get("dashboard")
    except Exception:
        return None
    if not port:
        return None
    try:
        return client.dashboard_link
    except Exception:
        return None


def close_client(client: Client) -> None:
    """Close a client and, for an embedded cluster, the cluster too."""
    with interrupts_deferred():
        _close(client)


def _close(client: Client) -> None:
    cluster = getattr(client, "cluster", None)
    client.close()
    if cluster is not None:
        # closing it is the end of the embedded cluster's work: a worker still starting
        # or busy is killed, and the nanny's and scheduler's warnings about that (worker
        # "still alive after 4.0 seconds, killing", tasks lost with it) are expected
        loggers = [logging.getLogger(name) for name in ("distributed.nanny", "distributed.scheduler")]
        levels = [lg.level for lg in loggers]
        for lg in loggers:
            lg.setLevel(max(lg.getEffectiveLevel(), logging.ERROR))
        try:
            cluster.close()
        finally:
            for lg, level in zip(loggers, levels):
                lg.setLevel(level)
