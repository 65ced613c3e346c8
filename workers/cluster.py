"""Dask clients: an embedded LocalCluster, or an existing cluster by address."""

from __future__ import annotations

import logging

from distributed import Client, LocalCluster

from pipeline.errors import ParameterError


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
            return Client(scheduler, timeout=timeout)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ParameterError(
                f"cannot reach the dask scheduler at {scheduler} ({type(exc).__name__}); "
                "start one with `dask scheduler` or fix --scheduler"
            ) from None
    cluster = LocalCluster(
        n_workers=int(n_workers),
        threads_per_worker=int(threads_per_worker),
        processes=processes,
        dashboard_address=":0" if dashboard else None,
        memory_limit=memory_limit,
        silence_logs=logging.CRITICAL if quiet else logging.WARNING,
    )
    client = Client(cluster)
    client.orchard_dashboard = dashboard  # the HTTP server runs anyway; remember whether it serves the dashboard
    return client


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
    cluster = getattr(client, "cluster", None)
    client.close()
    if cluster is not None:
        cluster.close()
