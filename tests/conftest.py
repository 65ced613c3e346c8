import os

import pytest

_ALLOCATOR_KEYS = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_")


@pytest.fixture(autouse=True)
def _allocator_environment_restored():
    """dask's nanny writes its pre-spawn settings into this process's environment, where
    they would override the next cluster's (an inherited value wins): undo that after each test."""
    before = {k: os.environ.get(k) for k in _ALLOCATOR_KEYS}
    yield
    for key, value in before.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@pytest.fixture(scope="session")
def dask_cluster():
    """The one dask cluster of the fast tests: a scheduler and two one-thread workers in
    this process (each process of a ``-n 2`` run has its own), on loopback TCP so that a
    test can also hand its address to ``orchard process --scheduler``; the scheduler
    binds port 0 and reports the address it got. Clusters of worker processes are for
    tests marked ``slow``. Tests share it: read its state as a change, not a total."""
    from distributed import LocalCluster

    from workers.cluster import _stop_http_servers

    # memory_limit 0: an in-process worker would judge its memory by this whole process
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp://", host="127.0.0.1",
                      scheduler_port=0, dashboard_address="127.0.0.1:0", memory_limit=0) as cluster:
        # no dashboard, as the embedded cluster's default: the command line names none
        cluster.sync(_stop_http_servers, [cluster.scheduler, *cluster.workers.values()])
        yield cluster


@pytest.fixture(scope="session")
def dask_client(dask_cluster):
    """A client of `dask_cluster`: the default client while no newer one is open (as
    workers.dispatch's ``distributed.wait`` needs)."""
    from distributed import Client

    with Client(dask_cluster) as client:
        yield client
