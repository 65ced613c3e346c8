"""API tests on the app in this process (runner off: jobs stay queued); those that hold
a socket open, hang up or signal the server run against a real `orchard serve` on loopback."""

from __future__ import annotations

import hashlib

import httpx
import pytest

from service_fixtures import ServerProcess, make_token, temp_files, tenant_inbox, write_las


def upload(client: httpx.Client, path, name: str | None = None) -> httpx.Response:
    with open(path, "rb") as fh:
        return client.post("/v1/blocks", files={"file": (name or path.name, fh, "application/octet-stream")})


# -- health, docs, auth -------------------------------------------------------------------


def test_healthz_needs_no_token(api):
    r = api.get("/healthz")
    assert r.status_code == 200
    assert r.json()["status"] == "ok" and r.json()["cluster"] == "disabled"  # this server runs no jobs


def test_warmed_routes_still_route(tmp_path):
    # orchard serve matches a path no route has before it listens (FastAPI builds its
    # routers' models on first use); every route must still answer as before
    from fastapi.testclient import TestClient

    from service.app import create_app, warm_routes
    from service.settings import Settings

    app = create_app(Settings(data_dir=tmp_path / "data", runner=False, scheduling=False))
    warm_routes(app)
    warm_routes(app)  # twice: a restart of the same app object changes nothing
    with TestClient(app) as client:
        assert client.get("/healthz").status_code == 200
        assert client.get("/v1/jobs").status_code == 401
        missing = client.get("/no-such-page")
        assert missing.status_code == 404 and "detail" in missing.json()


def test_openapi_and_docs(api):
    spec = api.get("/openapi.json").json()
    for path in ("/v1/blocks", "/v1/jobs", "/v1/jobs/{job_id}/report", "/v1/schedules/{schedule_id}/run"):
        assert path in spec["paths"]
    assert "multipart/form-data" in spec["paths"]["/v1/blocks"]["post"]["requestBody"]["content"]
    assert api.get("/docs").status_code == 200


@pytest.mark.parametrize(
    "headers",
    [{}, {"Authorization": "Bearer nope"}, {"Authorization": "Basic Zm9vOmJhcg=="}, {"Authorization": "Bearer"}],
    ids=["missing", "unknown", "basic", "empty"],
)
@pytest.mark.parametrize("path", ["/v1/blocks", "/v1/jobs", "/v1/schedules", "/v1/jobs/x/report"])
def test_missing_or_bad_token_is_401(api, headers, path):
    r = api.get(path, headers=headers)
    assert r.status_code == 401
    assert r.headers["www-authenticate"] == "Bearer"
    assert "token" in r.json()["detail"]


def test_upload_without_token_is_401(api, small_las):
    with open(small_las, "rb") as fh:
        r = api.post("/v1/blocks", files={"file": ("a.laz", fh)})
    assert r.status_code == 401


# -- uploads ------------------------------------------------------------------------------


def test_upload_block_and_same_file_twice(client_a, small_las):
    r1 = upload(client_a, small_las)
    assert r1.status_code in (200, 201), r1.text
    block = r1.json()
    assert block["sha256"] == hashlib.sha256(small_las.read_bytes()).hexdigest()
    assert block["n_points"] == 3000
    assert block["compressed"] is True
    assert block["mins"][0] >= 500000.0 and block["maxs"][0] <= 500010.0
    r2 = upload(client_a, small_las, name="renamed.laz")
    assert r2.status_code == 200
    assert r2.json()["id"] == block["id"]
    assert client_a.get(f"/v1/blocks/{block['id']}").json()["id"] == block["id"]
    assert block["id"] in [b["id"] for b in client_a.get("/v1/blocks").json()]


def test_uploaded_file_lands_under_its_checksum(api_data, client_a, tmp_path):
    path = write_las(tmp_path / "evil.las", 500, seed=11)
    r = upload(client_a, path, name="../../../etc/passwd.las")
    assert r.status_code == 201, r.text
    block = r.json()
    assert block["filename"] == "passwd.las"
    stored = api_data / "blocks" / f"{block['sha256']}.las"
    assert stored.read_bytes() == path.read_bytes()
    assert not temp_files(api_data)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"this is not a point cloud\n" * 20, "LAS"),
        (b"", "empty"),
        (b"LASF", ""),
    ],
    ids=["not-las", "empty", "header-only"],
)
def test_bad_upload_is_422(client_a, content, message):
    r = client_a.post("/v1/blocks", files={"file": ("x.laz", content)})
    assert r.status_code == 422, r.text
    assert message.lower() in r.json()["detail"].lower()


def test_truncated_upload_is_422(client_a, tmp_path):
    path = write_las(tmp_path / "t.las", 2000, seed=3)
    data = path.read_bytes()
    r = client_a.post("/v1/blocks", files={"file": ("t.las", data[: len(data) // 2])})
    assert r.status_code == 422
    assert "truncated" in r.json()["detail"]


def test_upload_without_its_closing_boundary_is_422_and_stores_nothing(client_a, tmp_path):
    # a whole LAS file in the part, but the body stops before the part's boundary: the
    # parser's finalize() does not notice, and the block was stored (201)
    data = write_las(tmp_path / "u.las", 2000, seed=11).read_bytes()
    body = b'--abc\r\nContent-Disposition: form-data; name="file"; filename="u.las"\r\n\r\n' + data
    r = client_a.post("/v1/blocks", content=body, headers={"content-type": "multipart/form-data; boundary=abc"})
    assert r.status_code == 422 and "no closing boundary" in r.json()["detail"]
    assert all(b["filename"] != "u.las" for b in client_a.get("/v1/blocks").json())
    closed = body + b"\r\n--abc--\r\n"
    r = client_a.post("/v1/blocks", content=closed, headers={"content-type": "multipart/form-data; boundary=abc"})
    assert r.status_code == 201, r.text


def test_zero_point_las_is_422(client_a, tmp_path):
    path = write_las(tmp_path / "z.las", 0)
    r = upload(client_a, path)
    assert r.status_code == 422
    assert "t.las" not in r.json()["detail"]


def test_upload_without_file_field_is_422(client_a):
    r = client_a.post("/v1/blocks", files={"other": ("x.las", b"abc")})
    assert r.status_code == 422
    assert "'file'" in r.json()["detail"]


def test_upload_not_multipart_is_422(client_a):
    r = client_a.post("/v1/blocks", content=b"LASF", headers={"content-type": "application/octet-stream"})
    assert r.status_code == 422
    assert "multipart" in r.json()["detail"]


def test_too_big_upload_is_413(api_data, client_a, tmp_path):
    # the test app's limit is 1 MB: a 1.3 MB file passes the Content-Length check
    # (1 MB multipart slack), is streamed, counted and refused
    path = write_las(tmp_path / "big.las", 45_000, seed=5)
    assert 1.1e6 < path.stat().st_size < 1.9e6
    r = upload(client_a, path)
    assert r.status_code == 413, r.text
    assert "limit" in r.json()["detail"]
    assert not temp_files(api_data)


def test_far_too_big_upload_is_413_before_reading(api_server, server_tokens):
    # Content-Length far above the limit: refused at once, without reading the body. Sent
    # by hand, headers only: a client still sending the body may see the connection close
    # before it reads the answer.
    import json
    import socket
    from urllib.parse import urlsplit

    url = urlsplit(api_server.url)
    head = (
        f"POST /v1/blocks HTTP/1.1\r\nHost: {url.hostname}:{url.port}\r\n"
        f"Authorization: Bearer {server_tokens['a']}\r\n"
        "Content-Type: multipart/form-data; boundary=x\r\nContent-Length: 8000200\r\nConnection: close\r\n\r\n"
    )
    with socket.create_connection((url.hostname, url.port), timeout=30) as sock:
        sock.sendall(head.encode() + b"--x\r\n")
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    status = int(answer.split(b" ", 2)[1])
    assert status == 413
    assert "1 MB" in json.loads(answer.split(b"\r\n\r\n", 1)[1])["detail"]


def test_json_body_too_big_is_413(client_a):
    r = client_a.post("/v1/jobs", content=b"{" + b" " * (2 << 20) + b"}", headers={"content-type": "application/json"})
    assert r.status_code == 413


# -- jobs ---------------------------------------------------------------------------------


@pytest.fixture()
def block_a(client_a, small_las):
    return upload(client_a, small_las).json()


def test_job_lifecycle_without_runner(client_a, block_a):
    r = client_a.post("/v1/jobs", json={"block_id": block_a["id"], "tiling": {"tile_size": 20}})
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["state"] == "queued" and job["id"] and job["tiling"]["tile_size"] == 20
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert client_a.get(f"/v1/jobs/{job['id']}").json()["state"] == "queued"
    listed = client_a.get("/v1/jobs", params={"state": "queued", "block_id": block_a["id"]}).json()["items"]
    assert listed[0]["id"] == job["id"]  # newest first: other tests' jobs do not push it off the page
    assert job["id"] not in [j["id"] for j in client_a.get("/v1/jobs", params={"state": "done"}).json()["items"]]
    for suffix in ("trees", "trees.parquet", "trees.csv", "points.parquet", "report", "map.png"):
        res = client_a.get(f"/v1/jobs/{job['id']}/{suffix}")
        assert res.status_code == 409, suffix
        assert "queued" in res.json()["detail"]
    r = client_a.delete(f"/v1/jobs/{job['id']}")
    assert r.status_code == 202
    assert r.json()["state"] == "cancelled"
    assert client_a.delete(f"/v1/jobs/{job['id']}").status_code == 409


@pytest.mark.parametrize(
    "body, fragment",
    [
        ({"params": {"graph": {"voxel_size": -1}}}, "voxel_size"),
        ({"params": {"graph": {"edge_radius": 0.05}}}, "edge_radius"),
        ({"params": {"nonsense": 1}}, "nonsense"),
        ({"params": {"matter": {"method": "magic"}}}, "method"),
        ({"tiling": {"tile_size": 0}}, "tile_size"),
        ({"tiling": {"tile_size": 20, "buffer": 0.5}}, "reach"),
    ],
)
def test_bad_job_params_are_422(client_a, block_a, body, fragment):
    r = client_a.post("/v1/jobs", json={"block_id": block_a["id"], **body})
    assert r.status_code == 422
    assert fragment in r.json()["detail"]


def test_a_parameter_error_names_its_request_field_and_location(client_a, block_a):
    r = client_a.post("/v1/jobs", json={"block_id": block_a["id"], "tiling": {"tile_size": 20, "buffer": 0.5}})
    assert r.status_code == 422
    body = r.json()
    assert body["detail"].endswith("use tiling.buffer 6.15 or more, or a smaller params.segment.max_crown_radius")
    assert body["errors"] == [{"loc": ["body", "tiling", "buffer"], "msg": body["detail"], "type": "parameter",
                               "input": 0.5, "limit": 6.15}]


def test_job_for_unknown_block_is_404(client_a):
    assert client_a.post("/v1/jobs", json={"block_id": "0" * 32}).status_code == 404


@pytest.mark.parametrize(
    "path",
    ["/v1/blocks/{x}", "/v1/jobs/{x}", "/v1/jobs/{x}/trees", "/v1/jobs/{x}/trees.csv", "/v1/jobs/{x}/report",
     "/v1/schedules/{x}"],
)
def test_unknown_ids_are_404(client_a, path):
    r = client_a.get(path.format(x="f" * 32))
    assert r.status_code == 404
    assert "detail" in r.json()


def test_cross_tenant_access_is_404(client_a, client_b, block_a, api_data):
    job = client_a.post("/v1/jobs", json={"block_id": block_a["id"]}).json()
    assert client_b.get(f"/v1/blocks/{block_a['id']}").status_code == 404
    assert client_b.get(f"/v1/jobs/{job['id']}").status_code == 404
    assert client_b.get(f"/v1/jobs/{job['id']}/report").status_code == 404
    assert client_b.get(f"/v1/jobs/{job['id']}/trees").status_code == 404
    assert client_b.delete(f"/v1/jobs/{job['id']}").status_code == 404
    assert client_b.post("/v1/jobs", json={"block_id": block_a["id"]}).status_code == 404
    assert block_a["id"] not in [b["id"] for b in client_b.get("/v1/blocks").json()]
    assert job["id"] not in [j["id"] for j in client_b.get("/v1/jobs").json()["items"]]
    inbox = tenant_inbox(api_data, "farm-a", "cross-tenant")
    sched = client_a.post("/v1/schedules", json={"inbox": str(inbox)}).json()
    assert client_b.get(f"/v1/schedules/{sched['id']}").status_code == 404
    assert client_b.post(f"/v1/schedules/{sched['id']}/run").status_code == 404
    assert client_b.delete(f"/v1/schedules/{sched['id']}").status_code == 404
    assert client_a.delete(f"/v1/schedules/{sched['id']}").status_code == 204
    client_a.delete(f"/v1/jobs/{job['id']}")


def test_same_file_for_two_tenants_gives_two_blocks(client_a, client_b, block_a, small_las):
    b = upload(client_b, small_las).json()
    assert b["sha256"] == block_a["sha256"] and b["id"] != block_a["id"]


def test_errors_are_json_without_traceback(client_a):
    r = client_a.post("/v1/jobs", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422
    assert "Traceback" not in r.text and isinstance(r.json()["detail"], str)


def _read_response(sock) -> str:
    """One whole HTTP response from a raw socket: the headers and the body can arrive in
    separate segments, so read until Content-Length is met or the server closes."""
    data = b""
    while True:
        head, sep, rest = data.partition(b"\r\n\r\n")
        if sep:
            length = next((int(line.split(b":", 1)[1]) for line in head.split(b"\r\n")
                           if line.lower().startswith(b"content-length:")), None)
            if length is not None and len(rest) >= length:
                break
        chunk = sock.recv(65536)
        if not chunk:
            break
        data += chunk
    return data.decode(errors="replace")


def test_an_upload_that_stops_sending_is_dropped_with_408(api_server, server_tokens, small_las):
    """A client that sends half its body and then nothing, keeping the connection open,
    held the request and its partial file for good (ORCHARD_UPLOAD_IDLE_S is 3 s here)."""
    import socket
    import time

    body = small_las.read_bytes()
    head = (b'--b0\r\nContent-Disposition: form-data; name="file"; filename="slow.laz"\r\n\r\n')
    with socket.create_connection(("127.0.0.1", api_server.port), timeout=20) as sock:
        sock.sendall((f"POST /v1/blocks HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {server_tokens['a']}\r\n"
                      f"Content-Type: multipart/form-data; boundary=b0\r\nContent-Length: {len(head) + len(body) + 8}"
                      "\r\n\r\n").encode() + head + body[: len(body) // 2])
        time.sleep(1.0)
        assert temp_files(api_server.data_dir, "upload-*")  # still arriving
        t0 = time.monotonic()
        reply = _read_response(sock)
    assert reply.startswith("HTTP/1.1 408"), reply[:200]
    assert "sent nothing for 3 s" in reply and time.monotonic() - t0 < 10
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and temp_files(api_server.data_dir, "upload-*"):
        time.sleep(0.1)
    assert not temp_files(api_server.data_dir, "upload-*")


def test_an_upload_arriving_when_the_server_is_told_to_stop_gets_503_at_once(tmp_path, small_las):
    """SIGTERM during an upload that is still arriving: the server waited out its graceful
    shutdown (10 s), then cut the connection without a reply and logged an ERROR."""
    import os
    import signal
    import socket
    import time

    srv = ServerProcess(tmp_path / "data", ORCHARD_RUNNER="false", ORCHARD_SCHEDULING="false").start()
    try:
        token = make_token(srv.data_dir, "farm")
        body = small_las.read_bytes()
        head = b'--b0\r\nContent-Disposition: form-data; name="file"; filename="slow.laz"\r\n\r\n'
        with socket.create_connection(("127.0.0.1", srv.port), timeout=20) as sock:
            sock.sendall((f"POST /v1/blocks HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {token}\r\n"
                          f"Content-Type: multipart/form-data; boundary=b0\r\nContent-Length: {len(head) + len(body) + 8}"
                          "\r\n\r\n").encode() + head + body[: len(body) // 2])
            deadline = time.monotonic() + 10
            while not temp_files(srv.data_dir, "upload-*") and time.monotonic() < deadline:
                time.sleep(0.05)
            assert temp_files(srv.data_dir, "upload-*")  # arriving
            t0 = time.monotonic()
            os.killpg(srv.proc.pid, signal.SIGTERM)
            reply = _read_response(sock)
        assert reply.startswith("HTTP/1.1 503"), reply[:300]
        assert "the server is stopping" in reply and time.monotonic() - t0 < 5
        assert srv.proc.wait(30) == 0  # stopped as asked (uvicorn passes the signal on once shut down)
        assert not temp_files(srv.data_dir, "upload-*")
        assert "ERROR" not in srv.log() and "Traceback" not in srv.log(), srv.log()[-2000:]
    finally:
        srv.stop()


def test_client_hanging_up_mid_upload_is_not_a_server_error(api_server, server_tokens, small_las):
    """A capture upload cut short by the client (a dropped connection) leaves no
    temporary file and no error with a traceback in the server's log."""
    import socket
    import time

    body = small_las.read_bytes()
    boundary = "orchardboundary"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"cut.laz\"\r\n"
            "Content-Type: application/octet-stream\r\n\r\n").encode()
    total = len(head) + len(body) + len(f"\r\n--{boundary}--\r\n")
    before = api_server.log_path.stat().st_size
    with socket.create_connection(("127.0.0.1", api_server.port), timeout=10) as sock:
        sock.sendall((f"POST /v1/blocks HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {server_tokens['a']}\r\n"
                      f"Content-Type: multipart/form-data; boundary={boundary}\r\nContent-Length: {total}\r\n\r\n").encode()
                     + head + body[: len(body) // 2])
        time.sleep(0.5)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and temp_files(api_server.data_dir, "upload-*"):
        time.sleep(0.1)
    assert not temp_files(api_server.data_dir, "upload-*")
    time.sleep(0.5)
    with open(api_server.log_path, "rb") as fh:
        fh.seek(before)
        new_log = fh.read().decode(errors="replace")
    assert "Traceback" not in new_log and "ERROR" not in new_log, new_log[-2000:]
    assert httpx.get(api_server.url + "/healthz", timeout=5).status_code == 200
