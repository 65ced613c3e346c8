"""Dask clients: an embedded LocalCluster, or an existing cluster by address."""

from __future__ import annotations

import gc
import logging
import os
import re
import signal
import socket
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from multiprocessing import resource_tracker

import dask
from dask.utils import parse_timedelta
from distributed import Client, LocalCluster

from pipeline.errors import ParameterError
from workers.runoptions import WORKERS
from workers.identity import DISTRIBUTION, identity

log = logging.getLogger(__name__)

#: Where an embedded cluster listens unless told otherwise (its comms need the cluster's
#: own TLS certificates; its dashboard, when on, answers anyone who can reach it).
LOOPBACK = "127.0.0.1"
#: glibc's allocator settings in the embedded cluster's worker processes [bytes], in
#: place of dask's ``MALLOC_TRIM_THRESHOLD_=65536``: setting that fixes the mmap
#: threshold at 128 KiB, so every mid-sized array (a tile's per-node arrays, 0.1-16 MB) is
#: mapped afresh and page-faulted on each use. Arrays up to 16 MiB reuse the heap, and at
#: most 32 MiB of free heap is kept (docs/performance.md, "The allocator of worker processes").
WORKER_MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(16 << 20), "MALLOC_TRIM_THRESHOLD_": str(32 << 20)}
#: Workers of an external cluster named in a :class:`WorkersUnfit` message (the rest are counted).
MAX_NAMED_WORKERS = 3
#: Signals the embedded cluster's worker processes start with blocked: Ctrl-C in a terminal
#: and a stop of the whole process group (systemd's default KillMode=control-group,
#: ``kill -- -PGID``) reach every process of the group, and the workers are this process's
#: to stop (:func:`_workers_signals_blocked`).
WORKER_BLOCKED_SIGNALS = frozenset({signal.SIGINT, signal.SIGTERM})
#: The preloads of the embedded cluster's workers: this module's :func:`dask_setup`, then
#: the modules a job's tasks import (:mod:`workers.preload`).
EMBEDDED_PRELOADS = (__name__, "workers.preload")


class WorkersUnfit(ParameterError):
    """Workers of an external dask cluster that cannot run this process's tasks.

    Attributes
    ----------
    scheduler : str
        The cluster's scheduler address.
    problems : dict[str, str]
        Worker address -> what is wrong there (cannot import the project, another
        version, other pipeline parameters).
    n_workers : int
        Workers checked.
    expected : dict
        This process's :func:`workers.identity.identity`.
    """

    def __init__(self, scheduler: str, problems: dict[str, str], n_workers: int, expected: dict):
        self.scheduler, self.problems, self.n_workers, self.expected = scheduler, problems, n_workers, expected
        named = [f"{address} {what}" for address, what in list(problems.items())[:MAX_NAMED_WORKERS]]
        more = len(problems) - len(named)
        version = expected.get("version") or "(this checkout)"
        super().__init__(
            f"{len(problems)} of {n_workers} dask worker(s) of {scheduler} cannot run orchard tiles: "
            + "; ".join(named) + (f"; and {more} more" if more else "")
            + f". Install {DISTRIBUTION} {version}, the release or checkout this process runs "
            f"({expected.get('python')} on {expected.get('host')}), into the Python of each of those workers, "
            "then restart them"
        )


def _check_answers(address: str, seconds: float) -> None:
    """TimeoutError unless a dask scheduler answers at ``address`` within ``seconds``.

    distributed's Client waits forever on a port that accepts connections but does not
    answer its handshake (a web server, the dashboard's 8787 typed for 8786): a job
    stayed "running" for good. One comm opened and closed under a deadline of our own
    tells a scheduler from those.
    """
    import asyncio

    from distributed.comm import connect

    from distributed.security import Security

    # a tls:// scheduler: the credentials of dask's configuration (docs/cluster.md)
    args = Security().get_connection_args("client")

    async def knock() -> None:
        comm = await asyncio.wait_for(connect(address, timeout=seconds, **args), seconds)
        await comm.close()

    asyncio.run(knock())


def make_client(
    scheduler: str | None = None,
    n_workers: int = WORKERS,
    threads_per_worker: int = 1,
    dashboard: bool = True,
    *,
    processes: bool = True,
    memory_limit: str | float | None = "auto",
    timeout: str = "20s",
    quiet: bool = False,
    host: str = LOOPBACK,
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
        Embedded cluster only: serve the dashboard on a free port of ``host``
        (``client.dashboard_link`` tells where); False starts no HTTP server at all.
    processes : bool
        Worker processes (True) or threads of this process (False; needed for a
        ``memory://`` work store).
    timeout : str
        How long to try to reach ``scheduler``, and for each of its workers to answer
        :func:`check_workers`.
    quiet : bool
        Embedded cluster only: its workers print nothing (a failing tile is reported once,
        by the job, instead of as a worker traceback per attempt).
    host : str
        Embedded cluster only: the address its scheduler, nannies, workers and
        dashboard listen on (loopback by default). With worker processes, every comm
        of the cluster is mutual TLS with certificates made at start-up, held in
        memory: a client without them is refused (the dashboard, off by default,
        asks for no login).

    Raises
    ------
    ParameterError
        The scheduler cannot be reached, or ``host`` is not an address of this machine.
    WorkersUnfit
        A worker of ``scheduler``'s cluster cannot run this process's tasks.
    """
    if scheduler:
        return _external_client(scheduler, timeout)
    return _embedded_client(n_workers, threads_per_worker, dashboard, processes=processes,
                            memory_limit=memory_limit, quiet=quiet, host=host)


def collect_failed_clients() -> None:
    """Finalise now the clients whose start failed (call it once their exception is gone).

    Such a client closes itself in ``__del__``, which takes distributed's ``LoopRunner``
    lock, one for the whole process and not re-entrant. Left to the garbage collector it
    can be finalised inside the next client's start, which holds that lock: the process
    hung there (seen in a test of the TLS refusal)."""
    gc.collect()


def _external_client(scheduler: str, timeout: str) -> Client:
    """A client of the running cluster at ``scheduler``, once it answers and its workers
    can run this process's tasks (:func:`make_client`'s errors)."""
    failure = None
    try:
        _check_answers(scheduler, parse_timedelta(timeout))
        client = Client(scheduler, timeout=timeout)
    except TimeoutError:
        failure = ParameterError(
            f"no dask scheduler answered at {scheduler} within {parse_timedelta(timeout):g} s (TimeoutError); "
            "start one with `dask scheduler`, or fix {job.scheduler} (its port, 8786 by default, not the "
            "dashboard's 8787)", param="job.scheduler", value=scheduler,
        )
    except (OSError, ValueError) as exc:
        failure = ParameterError(
            f"cannot reach the dask scheduler at {scheduler} ({type(exc).__name__}); "
            "start one with `dask scheduler` or fix {job.scheduler}", param="job.scheduler", value=scheduler,
        )
    if failure is not None:
        collect_failed_clients()
        raise failure
    try:
        check_workers(client, scheduler=scheduler, seconds=parse_timedelta(timeout))
    except BaseException:
        client.close()
        raise
    return client


def _embedded_client(
    n_workers: int,
    threads_per_worker: int,
    dashboard: bool,
    *,
    processes: bool,
    memory_limit: str | float | None,
    quiet: bool,
    host: str,
) -> Client:
    """A client of a new ``LocalCluster`` listening on ``host`` (:func:`make_client`'s
    parameters of the embedded cluster)."""
    _check_host(host)
    # worker processes talk to the scheduler over TLS with certificates made here, for this
    # cluster alone: a client without them (another local account) is refused
    security = _temporary_security() if processes else None
    logging.getLogger("distributed.batched").addFilter(_CLIENT_GONE)  # the scheduler runs in this process
    with _workers_signals_blocked(), worker_allocator():
        cluster = LocalCluster(
            n_workers=int(n_workers),
            threads_per_worker=int(threads_per_worker),
            processes=processes,
            security=security,
            protocol="tls://" if security is not None else None,
            host=host if processes else None,  # in-process workers talk over inproc://, no network
            # the scheduler's HTTP server starts even without a dashboard (None means 8787):
            # on a free port of ``host`` (a bare ":0" would mean every interface)
            dashboard_address=f"{_bracketed(host)}:0",
            scheduler_kwargs={"dashboard": dashboard},
            memory_limit=memory_limit,
            silence_logs=logging.CRITICAL if quiet else logging.WARNING,
            preload=list(EMBEDDED_PRELOADS) if processes else None,  # dask_setup below and the task modules
        )
    # distributed starts an HTTP server (metrics, health, task and worker details) in the
    # scheduler even without a dashboard, and one in each worker: none is needed here
    cluster.sync(_stop_http_servers, [cluster.scheduler, *cluster.workers.values()] if not dashboard
                 else list(cluster.workers.values()))
    client = Client(cluster)
    client.orchard_dashboard = dashboard
    client.orchard_host = host
    return client


def _temporary_security():
    """Mutual TLS for an embedded cluster: a certificate made now, in memory only
    (`distributed.security.Security.temporary`, which needs the ``cryptography``
    package); every comm needs it, both ways, and nothing is sent in the clear."""
    from distributed.security import Security

    return Security.temporary()


def cluster_workers(client: Client) -> tuple[int, int | None]:
    """(workers connected to the scheduler, workers it should have): the second is the
    embedded cluster's size, None for an external cluster (its size is not ours to know)."""
    cluster = getattr(client, "cluster", None)
    if cluster is not None and getattr(cluster, "scheduler", None) is not None:
        return len(cluster.scheduler.workers), len(cluster.worker_spec)
    # the client's cached view (refreshed every few seconds): asking the scheduler could hang
    ident = getattr(client, "_scheduler_identity", None) or {}
    n = ident.get("n_workers")
    return (int(n) if n is not None else len(ident.get("workers") or {})), None


def heal_cluster(client: Client, n_workers: int, *, timeout: float = 120.0) -> int:
    """Replace the embedded cluster's lost workers; returns how many it started.

    A nanny restarts its worker process when that dies, but gives up (and leaves the
    cluster) when the new one dies while it starts: killed five times about 4 s apart,
    the cluster kept 0 of its 2 workers for good. A nanny that left, closed or failed is
    replaced here by a new one (with the same allocator settings), until the cluster
    has ``n_workers`` again. An external cluster, or an embedded one that is closing, is
    left alone.
    """
    from distributed.core import Status

    cluster = getattr(client, "cluster", None)
    if cluster is None or getattr(cluster, "status", None) not in (Status.running,):
        return 0
    lost = [name for name, w in list(cluster.workers.items()) if getattr(w, "status", None) in (Status.closed, Status.failed)]
    if not lost and len(cluster.worker_spec) >= n_workers and len(cluster.workers) >= n_workers:
        return 0
    missing = n_workers - (len(cluster.workers) - len(lost))
    log.warning("the embedded dask cluster lost %d of its %d worker(s) for good; starting new ones", missing, n_workers)
    cluster.sync(_replace_workers, cluster, lost, n_workers, callback_timeout=timeout)
    return missing


async def _replace_workers(cluster, lost: list, n_workers: int) -> None:
    for name in lost:
        cluster.worker_spec.pop(name, None)  # _correct_state closes and forgets it
    while len(cluster.worker_spec) < n_workers:
        cluster.worker_spec.update(cluster.new_worker_spec())
    with worker_allocator():  # (each nanny reads the settings as it is made)
        try:
            await cluster._correct_state()
        except Exception as exc:  # noqa: BLE001 - a new worker that failed to start: the next round replaces it
            log.warning("a new dask worker failed to start: %s", exc)


@contextmanager
def worker_allocator():
    """Within it, the worker processes a dask ``LocalCluster`` starts get
    :data:`WORKER_MALLOC_ENV` (dask's other pre-spawn settings kept): each nanny takes
    them when it is made, for every worker process it starts (restarts too)."""
    environ = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **WORKER_MALLOC_ENV}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
        yield


def _bracketed(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def _check_host(host: str) -> None:
    """ParameterError unless this machine can listen on ``host``."""
    try:
        family, _, _, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            sock.bind(address)
    except (OSError, UnicodeError) as exc:
        raise ParameterError(
            f"the embedded dask cluster cannot listen on {host!r} ({getattr(exc, 'strerror', None) or exc}); "
            f"give an address of this machine: {LOOPBACK} (the default) for this machine alone, 0.0.0.0 for every interface"
        ) from None


def _stop_http(server) -> None:
    """Stop the HTTP server of a dask scheduler or worker (on its event loop) and stop
    advertising it."""
    http = getattr(server, "http_server", None)
    if http is not None:
        http.stop()
        server.services.pop("dashboard", None)


async def _stop_http_servers(servers: list) -> None:
    for server in servers:  # nannies have none; in-process workers (processes=False) do
        _stop_http(server)


def expected_identity() -> dict:
    """What every worker's :func:`workers.identity.identity` must match: this process's."""
    return identity()


def check_workers(client: Client, *, scheduler: str = "", expected: dict | None = None, seconds: float = 20.0) -> None:
    """Make sure every worker of ``client``'s cluster can run this process's tasks.

    Each worker runs :func:`workers.identity.identity` (``Client.run``, at most
    ``seconds`` [s] each, all at once): the project must import there, in the version
    and with the pipeline parameters of this process (``expected``, by default
    :func:`expected_identity`). A worker missing the project would die at its first
    task and leave the job waiting for workers; this says so before any task is sent. A
    worker that does not answer in time is logged, not refused (a busy event loop is no
    proof).

    Raises
    ------
    WorkersUnfit
        Names each unfit worker and what it lacks.
    """
    expected = expected_identity() if expected is None else expected
    addresses = sorted(client.ncores())
    if not addresses:
        return  # nothing to check yet: the job waits for workers (and says so if none come)

    def ask(address: str):
        try:
            return client.run(identity, workers=[address], on_error="return", callback_timeout=seconds).get(address)
        except TimeoutError:
            return None
        except Exception as exc:  # noqa: BLE001 - e.g. the worker left meanwhile
            return exc

    with ThreadPoolExecutor(max_workers=min(16, len(addresses))) as pool:
        answers = dict(zip(addresses, pool.map(ask, addresses)))
    problems = {}
    for address, answer in answers.items():
        if answer is None:
            log.warning("dask worker %s did not answer a check within %g s", address, seconds)
            continue
        what = _unfit(answer, expected)
        if what:
            problems[address] = what
    if problems:
        raise WorkersUnfit(scheduler or str(client.scheduler.address), problems, len(addresses), expected)


def _unfit(answer, expected: dict) -> str | None:
    """What keeps a worker whose :func:`identity` is ``answer`` from running this
    process's tasks, or None."""
    if isinstance(answer, BaseException):  # it could not even load workers.identity
        text = f"{type(answer).__name__}: {answer}"
        # distributed may hand back the worker's exception as Exception('ModuleNotFoundError("...")')
        repr_ = re.fullmatch(r"""(\w+)\((['"])(.*)\2\)""", str(answer)) if type(answer) is Exception else None
        if repr_:
            text = f"{repr_[1]}: {repr_[3]}"
        return f"cannot import the project ({text})"
    where = f"({answer.get('python')} on {answer.get('host')})"
    if answer.get("error"):
        return f"{where} cannot import the project ({answer['error']})"
    if answer.get("version") != expected.get("version"):
        return f"{where} has {DISTRIBUTION} {answer.get('version') or '(not installed)'}, not {expected.get('version')}"
    if answer.get("schema") != expected.get("schema"):
        return (f"{where} has {DISTRIBUTION} {answer.get('version')} with other pipeline parameters "
                "(another revision of the code)")
    return None


class _ClosingNoise(logging.Filter):
    """Drops what a worker logs when the embedded cluster closes: the warning for each
    task it was running ("Async instruction for <Task ...> ended with CancelledError":
    distributed logs it only from ``Worker.close``), and the traceback of a heartbeat
    caught by the scheduler closing first (the scheduler lives in the process that
    started the cluster, so only its closing makes a heartbeat fail)."""

    def filter(self, record: logging.LogRecord) -> bool:
        msg = str(record.msg)
        return not (msg.endswith("ended with CancelledError")
                    or msg == "Failed to communicate with scheduler during heartbeat.")


class _ClientGone(logging.Filter):
    """Drops the traceback the embedded scheduler logs (at INFO) when a client's stream
    closes while it still sends to it: a job's client closing as the service stops."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Batched Comm Closed")


_CLIENT_GONE = _ClientGone()


def dask_setup(worker) -> None:
    """Preload hook of the embedded cluster's workers (dask calls it at worker start,
    on its event loop, before it registers with the scheduler)."""
    _stop_term_from_parent_only()
    for name in ("distributed.worker.state_machine", "distributed.worker"):
        logging.getLogger(name).addFilter(_ClosingNoise())
    _stop_http(worker)  # also in a worker the nanny restarts


def _stop_term_from_parent_only() -> None:
    """In a worker process started with SIGTERM blocked (:func:`_workers_signals_blocked`),
    a thread that takes every SIGTERM: one from the parent process (its nanny's
    ``terminate``, at a start that failed or above the memory limit; multiprocessing's
    at the parent's exit) ends the process as SIGTERM does; one from anyone else (a stop
    sent to the whole process group) is dropped, as the service is stopping and stops
    its workers itself. A worker never outlives its parent: distributed's child process
    exits when its parent's pipe closes. Elsewhere (SIGTERM not blocked: a ``dask
    worker`` of an external cluster, with handlers of its own) it does nothing."""
    if signal.SIGTERM not in signal.pthread_sigmask(signal.SIG_BLOCK, set()):
        return
    parent = os.getppid()

    def take() -> None:
        while True:
            sender = signal.sigwaitinfo({signal.SIGTERM}).si_pid
            if sender == parent or os.getppid() != parent:
                # what SIGTERM does (the nanny sees "killed by signal 15"): sent to this
                # thread, the only one that no longer blocks it
                signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
                signal.pthread_kill(threading.get_ident(), signal.SIGTERM)
                return
            log.debug("SIGTERM from process %d dropped: the service stops its own workers", sender)

    threading.Thread(target=take, name="orchard-sigterm", daemon=True).start()


@contextmanager
def _workers_signals_blocked():
    """Start an embedded cluster with :data:`WORKER_BLOCKED_SIGNALS` blocked in the
    starting thread.

    A terminal's Ctrl-C goes to its whole process group, worker processes included,
    each of which then printed a KeyboardInterrupt traceback while this process was
    already shutting them down; a SIGTERM to the whole group (systemd stopping the
    service) killed every worker at once, and their nannies started new ones while the
    service was stopping. The cluster's event-loop thread, created in
    here, inherits the blocked signals, and so do the worker processes it spawns (now
    and when a worker is restarted): they are stopped by this process, never by Ctrl-C
    or a signal to the group (:func:`_stop_term_from_parent_only`). This thread's own
    mask is restored on the way out, so a signal that arrived meanwhile is delivered then.
    """
    # multiprocessing's resource tracker, when it first starts (here: at the first worker's
    # queue), unblocks SIGINT and SIGTERM in the thread that starts it; start it beforehand
    resource_tracker.ensure_running()
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, WORKER_BLOCKED_SIGNALS)
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
    host = getattr(client, "orchard_host", None)
    if host and host not in ("0.0.0.0", "::"):  # where it listens (an in-process cluster's link names another address)
        return f"http://{_bracketed(host)}:{port}/status"
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
