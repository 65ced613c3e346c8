"""The embedded dask cluster speaks mutual TLS with certificates made at its start: a
client on the same machine without them (another local account) cannot reach its
scheduler, in the clear or over TLS with certificates of its own."""

from __future__ import annotations

import gc

import pytest
from distributed import Client
from distributed.security import Security

from workers.cluster import close_client, collect_failed_clients, make_client


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
    with pytest.raises((OSError, TypeError, ValueError)) as refused:
        intruder = Client(**kwargs, timeout="3s")
        try:  # had it connected: this is what it would have done (the proof)
            intruder.run_on_scheduler(lambda: "ran on the scheduler")
        finally:
            intruder.close()
    del refused  # its traceback holds the client that failed to start: finalised now, not inside the next one's start
    collect_failed_clients()


@pytest.mark.slow
def test_a_client_that_failed_to_start_is_finalised_when_collected(embedded):
    # Left to the garbage collector, a client that failed to start was finalised inside
    # the next client's start, on distributed's process-wide LoopRunner lock: a hang.
    port = embedded.scheduler.address.rsplit(":", 1)[1]
    gc.collect()
    gc.disable()
    try:
        with pytest.raises((OSError, TypeError, ValueError)) as refused:
            Client(f"tcp://127.0.0.1:{port}", timeout="3s")
        del refused
        assert _other_clients(embedded), "the failed client is cycle garbage (else this test shows nothing)"
        collect_failed_clients()
        assert not _other_clients(embedded)
    finally:
        gc.enable()


def _other_clients(embedded) -> list:
    return [o for o in gc.get_objects() if type(o) is Client and o is not embedded]
