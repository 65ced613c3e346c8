import os

import pytest

_ALLOCATOR_KEYS = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_")


def pytest_configure(config):
    # `-n 2 --dist loadfile` hands out whole files, by default those with the most tests
    # first: files of one or two slow end-to-end tests came last, and one worker ran them
    # while the other sat idle. Out in collection order instead, which puts them first
    # (pytest_collection_modifyitems).
    if config.getoption("dist", "no") == "loadfile":
        config.option.loadscopereorder = False


@pytest.hookimpl(trylast=True)  # after `-m` has deselected
def pytest_collection_modifyitems(config, items):
    """Files with the most slow tests first, then those with the most tests (a file's own
    tests keep their order): under loadfile the two workers then end close together."""
    by_file: dict[str, list] = {}
    for item in items:
        by_file.setdefault(item.nodeid.split("::")[0], []).append(item)
    order = sorted(by_file.values(),
                   key=lambda tests: (-sum(t.get_closest_marker("slow") is not None for t in tests), -len(tests)))
    items[:] = [t for tests in order for t in tests]


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
