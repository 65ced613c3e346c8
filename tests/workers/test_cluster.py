"""Dask clients: embedded cluster with a dashboard, unreachable scheduler → clear error."""

from __future__ import annotations

import socket

import pytest

from pipeline.errors import ParameterError
from workers.cluster import close_client, dashboard_address, make_client


def test_embedded_cluster_has_workers_and_a_dashboard():
    client = make_client(n_workers=1, processes=False)
    try:
        assert len(client.scheduler_info()["workers"]) == 1
        assert dashboard_address(client).startswith("http://")
        assert client.submit(sum, [1, 2, 3]).result(timeout=30) == 6
    finally:
        close_client(client)


def test_no_dashboard():
    client = make_client(n_workers=1, processes=False, dashboard=False)
    try:
        assert dashboard_address(client) is None
    finally:
        close_client(client)


def test_unreachable_scheduler_is_a_parameter_error():
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ParameterError, match=f"127.0.0.1:{port}.*dask scheduler"):
        make_client(f"tcp://127.0.0.1:{port}", timeout="2s")
