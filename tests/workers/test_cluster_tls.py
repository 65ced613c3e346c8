"""The embedded dask cluster speaks mutual TLS with certificates made at its start: a
client on the same machine without them (another local account) cannot reach its
scheduler, in the clear or over TLS with certificates of its own."""

from __future__ import annotations

import pytest
from distributed import Client
from distributed.security import Security

from workers.cluster import close_client, make_client


@pytest.fixture(scope="module")
def embedded():
    client = make_client(None, n_workers=1, dashboard=False, quiet=True)
    try:
        yield client
    finally:
        close_client(client)


@pytest.mark.slow
def test_the_embedded_cluster_runs_tasks_over_tls(embedded):
    assert embedded.scheduler.address.startswith("tls://127.0.0.1:")
    assert embedded.submit(sum, [1, 2, 3]).result(timeout=60) == 6
    workers = embedded.scheduler_info()["workers"]
    assert workers and all(address.startswith("tls://") for address in workers)


@pytest.mark.slow
@pytest.mark.parametrize("how", ["tcp", "tls without certificates", "tls with another certificate"])
def test_a_loopback_client_without_the_credentials_cannot_reach_the_scheduler(embedded, how):
    port = embedded.scheduler.address.rsplit(":", 1)[1]
    if how == "tcp":
        kwargs = {"address": f"tcp://127.0.0.1:{port}"}
    elif how == "tls without certificates":
        kwargs = {"address": f"tls://127.0.0.1:{port}"}
    else:
        kwargs = {"address": f"tls://127.0.0.1:{port}", "security": Security.temporary()}
    with pytest.raises((OSError, TypeError, ValueError)):
        intruder = Client(**kwargs, timeout="3s")
        try:  # had it connected: this is what it would have done (the proof)
            intruder.run_on_scheduler(lambda: "ran on the scheduler")
        finally:
            intruder.close()
