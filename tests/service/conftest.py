"""Fixtures of the service tests (helpers in service_fixtures.py).

`api` is the app of a server whose runner is off (jobs stay queued), started in this
process and called through an in-process client: the API, upload and schedule tests.
`api_server` is a real `orchard serve` on loopback, for what needs one (sockets held
open, signals, the server's log, a fuzzer that calls a URL).
"""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from service_fixtures import ServerProcess, client_of, make_token, write_las

from service.app import create_app
from service.settings import Settings


@pytest.fixture(scope="session")
def api(tmp_path_factory) -> TestClient:
    """The started app (its lifespan ran) of a server whose runner and clock are off."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("api") / "data", runner=False, scheduling=False,
                        max_upload_mb=1, capture_settle_s=0)  # captures are written just before each scan
    with TestClient(create_app(settings)) as client:
        yield client


@pytest.fixture(scope="session")
def api_data(api) -> Path:
    """The data folder of `api`."""
    return api.app.state.settings.data_dir


@pytest.fixture(scope="session")
def tokens(api_data):
    return {"a": make_token(api_data, "farm-a"), "b": make_token(api_data, "farm-b")}


@pytest.fixture()
def client_a(api, tokens):
    c = client_of(api, token=tokens["a"])  # (not entered: that would start the app a second time)
    yield c
    c.close()


@pytest.fixture()
def client_b(api, tokens):
    c = client_of(api, token=tokens["b"])  # (not entered: that would start the app a second time)
    yield c
    c.close()


@pytest.fixture(scope="session")
def api_server(tmp_path_factory):
    """A real server whose runner is off, for the tests that need one."""
    root = tmp_path_factory.mktemp("api-server")
    srv = ServerProcess(root / "data", ORCHARD_RUNNER="false", ORCHARD_SCHEDULING="false", ORCHARD_MAX_UPLOAD_MB="1",
                        ORCHARD_CAPTURE_SETTLE_S="0",  # captures are written just before each scan
                        ORCHARD_UPLOAD_IDLE_S="3")
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


@pytest.fixture(scope="session")
def server_tokens(api_server):
    return {"a": make_token(api_server.data_dir, "farm-a"), "b": make_token(api_server.data_dir, "farm-b")}


@pytest.fixture()
def server_client_a(api_server, server_tokens):
    with httpx.Client(base_url=api_server.url, headers={"Authorization": f"Bearer {server_tokens['a']}"}, timeout=30) as c:
        yield c


@pytest.fixture(scope="session")
def small_las(tmp_path_factory) -> Path:
    return write_las(tmp_path_factory.mktemp("las") / "small.laz", 3000, seed=1)
