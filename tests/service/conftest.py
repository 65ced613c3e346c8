"""Fixtures of the service tests (helpers in service_fixtures.py)."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from service_fixtures import ServerProcess, make_token, write_las


@pytest.fixture(scope="session")
def api_server(tmp_path_factory):
    """A server whose runner is off (jobs stay queued): API, upload, schedule and fuzz tests."""
    root = tmp_path_factory.mktemp("api")
    srv = ServerProcess(root / "data", ORCHARD_RUNNER="false", ORCHARD_SCHEDULING="false", ORCHARD_MAX_UPLOAD_MB="1",
                        ORCHARD_CAPTURE_SETTLE_S="0",  # captures are written just before each scan
                        ORCHARD_UPLOAD_IDLE_S="3")
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


@pytest.fixture(scope="session")
def tokens(api_server):
    return {"a": make_token(api_server.data_dir, "farm-a"), "b": make_token(api_server.data_dir, "farm-b")}


@pytest.fixture()
def client_a(api_server, tokens):
    with httpx.Client(base_url=api_server.url, headers={"Authorization": f"Bearer {tokens['a']}"}, timeout=30) as c:
        yield c


@pytest.fixture()
def client_b(api_server, tokens):
    with httpx.Client(base_url=api_server.url, headers={"Authorization": f"Bearer {tokens['b']}"}, timeout=30) as c:
        yield c


@pytest.fixture(scope="session")
def small_las(tmp_path_factory) -> Path:
    return write_las(tmp_path_factory.mktemp("las") / "small.laz", 3000, seed=1)


