"""The service's edge under load and abuse, on loopback: JSON bodies bounded in shape
before validation, idle and slow connections timed out, connections capped, trickling
uploads stopped. Timings live in bench/edge.py; these tests assert outcomes only."""

from __future__ import annotations

import json
import select
import socket
import threading
import time

import httpx
import pytest
from service_fixtures import client_of

from service.api.bodies import MAX_DEPTH, MAX_KEYS, shape_problem
from service.edge import EdgeLimits, EdgeSocket, edge_protocol


def _many_keys(n: int, size: int | None = None) -> bytes:
    params = {f"k{i:06d}": 1 for i in range(n)}
    body = json.dumps({"block_id": "x", "params": params}).encode()
    return body if size is None else body + b" " * max(0, size - len(body))


def test_shape_limits_count_keys_values_and_depth():
    assert shape_problem({"a": [1, 2, {"b": 3}]}) is None
    assert "keys" in shape_problem({str(i): 0 for i in range(MAX_KEYS + 1)})
    assert "values" in shape_problem({"a": list(range(20_000))})
    deep = 0
    for _ in range(MAX_DEPTH + 1):
        deep = [deep]
    assert "deep" in shape_problem(deep)
    assert shape_problem(json.loads("[" * MAX_DEPTH + "]" * MAX_DEPTH)) is None


def test_a_body_of_many_keys_is_refused_before_validation(api, client_a):
    resp = client_a.post("/v1/jobs", content=_many_keys(90_000)[: 1000 * 1024],
                         headers={"Content-Type": "application/json"})
    assert resp.status_code in (413, 422), resp.text  # cut at the size limit: malformed, still refused by shape or size
    resp = client_a.post("/v1/jobs", content=_many_keys(15_000), headers={"Content-Type": "application/json"})
    assert resp.status_code == 422 and "more than 1000 keys" in resp.json()["detail"], resp.text
    deep = ("[" * 5000 + "]" * 5000).encode()
    resp = client_a.post("/v1/jobs", content=deep, headers={"Content-Type": "application/json"})
    assert resp.status_code == 422 and "deep" in resp.json()["detail"]
    with client_of(api) as anonymous:  # no token: refused all the same, before the sign-in is looked at
        resp = anonymous.post("/v1/jobs", content=_many_keys(15_000), headers={"Content-Type": "application/json"})
        assert resp.status_code == 422
    # an ordinary request is untouched (its error is the usual one: no such block)
    resp = client_a.post("/v1/jobs", json={"block_id": "nope", "params": {}})
    assert resp.status_code == 404, resp.text


@pytest.mark.slow
def test_healthz_answers_while_sixteen_clients_send_1mb_bodies(api_server, server_tokens):
    body = _many_keys(60_000, size=1000 * 1024)  # over the 256 kB limit: refused from its length, unread
    stop = threading.Event()
    statuses: list[int] = []

    def flood(token: str | None) -> None:
        headers = {"Content-Type": "application/json", **({"Authorization": f"Bearer {token}"} if token else {})}
        with httpx.Client(base_url=api_server.url, timeout=60) as c:
            while not stop.is_set():
                statuses.append(c.post("/v1/jobs", content=body, headers=headers).status_code)

    threads = [threading.Thread(target=flood, args=(server_tokens["a"] if i % 2 else None,)) for i in range(16)]
    for t in threads:
        t.start()
    try:
        health = []
        with httpx.Client(base_url=api_server.url, timeout=30) as c:
            while len(health) < 20:
                health.append(c.get("/healthz").status_code)
    finally:
        stop.set()
        for t in threads:
            t.join(60)
    assert health == [200] * 20
    assert statuses and set(statuses) == {413}, set(statuses)


# -- connections and deadlines at the edge --------------------------------------------


def _accept_all(listener: EdgeSocket) -> tuple[list, int]:
    """What ``accept()`` hands on until nothing is queued, and how many BlockingIOErrors it raised on the way."""
    import select

    accepted, stops = [], 0
    while select.select([listener], [], [], 0.2)[0]:
        try:
            accepted.append(listener.accept())
        except BlockingIOError:
            stops += 1
    return accepted, stops


def _closed_by_server(s: socket.socket) -> bool:
    try:
        return s.recv(1) == b""
    except ConnectionResetError:
        return True


@pytest.mark.skipif(not hasattr(socket, "TCP_DEFER_ACCEPT"), reason="TCP_DEFER_ACCEPT is Linux's")
def test_a_connection_that_sends_nothing_is_not_handed_to_the_service():
    import select

    raw = socket.socket()
    raw.bind(("127.0.0.1", 0))
    raw.listen(16)
    with EdgeSocket.wrap(raw, edge_protocol(EdgeLimits(header_timeout_s=10))) as listener, \
            socket.create_connection(listener.getsockname(), timeout=10) as silent:
        assert not select.select([listener], [], [], 0.5)[0]  # connected, as the client sees it; nothing to accept
        silent.sendall(b"G")
        assert select.select([listener], [], [], 10)[0]  # its first byte: handed on


def test_the_listening_socket_closes_a_flood_as_it_accepts_it(monkeypatch):
    """Past the caps and the refusals pending, a connection is closed by accept() itself,
    a batch at a time (the event loop runs between batches); the others are handed on,
    sorted for the protocol: admitted, or to be answered 503."""
    monkeypatch.setattr(EdgeSocket, "DROP_BATCH", 2)
    protocol = edge_protocol(EdgeLimits(max_connections=100, max_per_client=2, max_refusing=1))
    raw = socket.socket()
    raw.bind(("127.0.0.1", 0))  # port 0: the kernel's choice
    raw.listen(16)
    with EdgeSocket.wrap(raw, protocol) as listener:
        listener.setblocking(False)
        clients = [socket.create_connection(listener.getsockname(), timeout=10) for _ in range(8)]
        try:
            for c in clients:
                c.sendall(b"GET / HTTP/1.1\r\n")  # (one that sends nothing is not handed on yet)
            accepted, stops = _accept_all(listener)
            assert [protocol.edge_counts.sorted.pop(addr) for _, addr in accepted] == ["admit", "admit", "refuse"]
            assert [addr for _, addr in accepted] == [c.getsockname() for c in clients[:3]]  # in the order they came
            assert stops == 3  # the 5 dropped: batches of 2, 2 and 1 (the last one ended by the empty queue)
            assert all(_closed_by_server(c) for c in clients[3:])
            counts = protocol.edge_counts
            assert (counts.open, counts.per_client["127.0.0.1"], counts.refusing) == (2, 2, 1)
        finally:
            for c in clients:
                c.close()
            for conn, _ in accepted:
                conn.close()


@pytest.fixture(scope="module")
def edge_server(tmp_path_factory):
    """A server with small edge limits, its log in a rotated file."""
    from bench.edge import Server

    root = tmp_path_factory.mktemp("edge")
    with Server(root, ORCHARD_HEADER_TIMEOUT_S="2", ORCHARD_BODY_TIMEOUT_S="3", ORCHARD_MAX_CONNECTIONS_PER_CLIENT="8",
                ORCHARD_MAX_CONNECTIONS="40", ORCHARD_UPLOAD_IDLE_S="3", ORCHARD_UPLOAD_MIN_KBPS="8",
                ORCHARD_LOG_MAX_MB="0.05", ORCHARD_LOG_BACKUPS="2") as server:
        yield server


def _connect(server, source: str = "127.0.0.1") -> socket.socket:
    s = socket.socket()
    s.settimeout(30)
    s.bind((source, 0))
    s.connect(("127.0.0.1", server.port))
    return s


def _hold(server, source: str) -> socket.socket:
    """A connection the server holds: it has sent the start of a request (one that has sent
    nothing yet stays with the kernel, `test_a_connection_that_sends_nothing_is_not_handed_to_the_service`)."""
    s = _connect(server, source)
    s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
    return s


def _trickle(s: socket.socket, byte: bytes, *, every: float, times: int) -> None:
    """Send ``byte`` every ``every`` s, at most ``times`` times, until the server answers
    or closes (the socket turns readable): no byte goes sooner, none after its answer."""
    for _ in range(times):
        if select.select([s], [], [], every)[0]:
            return
        try:
            s.sendall(byte)
        except OSError:
            return


def _reply(s: socket.socket) -> bytes:
    data = b""
    while True:
        try:
            chunk = s.recv(65536)
        except ConnectionResetError:
            break
        if not chunk:
            break
        data += chunk
    return data


def _token(server, tenant: str) -> str:
    from service.auth import create_token
    from service.db.jobstore import Store

    store = Store(server.data_dir / "orchard.sqlite")
    try:
        return create_token(store, tenant)
    finally:
        store.close()


def test_a_request_whose_headers_do_not_arrive_gets_408_and_is_closed(edge_server):
    with _connect(edge_server) as silent, _connect(edge_server) as partial:
        partial.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: ")
        for s in (silent, partial):
            reply = _reply(s)  # returns once the server has closed it
            assert reply.startswith(b"HTTP/1.1 408") and b"did not arrive within 2 s" in reply, reply


def test_connections_past_the_cap_of_one_address_get_503_and_others_still_get_through(edge_server):
    held = [_hold(edge_server, "127.0.0.2") for _ in range(8)]
    try:
        with _connect(edge_server, "127.0.0.2") as extra:
            extra.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            reply = _reply(extra)
        assert reply.startswith(b"HTTP/1.1 503") and b"retry-after: 5" in reply.lower() and b"too many open connections" in reply
        assert httpx.get(edge_server.url + "/healthz", timeout=30).status_code == 200  # another address: served
    finally:
        for s in held:
            s.close()


def test_connections_past_the_cap_in_all_get_503(edge_server):
    held = [_hold(edge_server, f"127.0.0.{10 + i // 8}") for i in range(40)]  # 5 addresses of 8: the cap of 40
    try:
        with _connect(edge_server, "127.0.0.20") as extra:
            extra.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            reply = _reply(extra)
        assert reply.startswith(b"HTTP/1.1 503") and b"at most 40 in all" in reply, reply
    finally:
        for s in held:
            s.close()
    deadline = time.monotonic() + 30  # (the server sees them close)
    while time.monotonic() < deadline:
        if httpx.get(edge_server.url + "/healthz", timeout=30).status_code == 200:
            break
        time.sleep(0.1)


def test_a_json_body_that_trickles_is_cut_off(edge_server):
    with _connect(edge_server) as s:
        s.sendall(b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{")
        _trickle(s, b" ", every=1, times=8)  # one byte a second: past the 3 s body deadline the server closes it
        assert b"200 OK" not in _reply(s)
    assert "its body did not arrive within 3 s" in edge_server.log_text()


def test_an_upload_below_the_minimum_rate_gets_408(edge_server):
    token = _token(edge_server, "trickle")
    head = b'--b0\r\nContent-Disposition: form-data; name="file"; filename="slow.laz"\r\n\r\n'
    with _connect(edge_server) as s:
        s.sendall((f"POST /v1/blocks HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
                   f"Content-Type: multipart/form-data; boundary=b0\r\nContent-Length: 1000000\r\n\r\n").encode() + head)
        _trickle(s, b"x", every=1, times=15)  # a byte a second (the idle limit is 3 s, so never idle): below 8 kB/s from 3 s on
        reply = _reply(s)
    assert reply.startswith(b"HTTP/1.1 408") and b"below the minimum of 8 kB/s" in reply, reply[:300]


@pytest.mark.slow
def test_idle_connections_from_two_clients_leave_healthz_answering_and_the_log_small(edge_server):
    """bench/edge.py's 20,000-connection run, smaller: 2 clients of 500 idle connections for 8 s."""
    from bench.edge import idle

    result = idle(edge_server, connections=1000, clients=2, hold_s=8)
    assert result["healthz_failed"] == 0 and result["healthz_asked"] > 0, result
    assert result["closed_by_server"] >= 1000 - 2 * 8  # all but each address's 8 answered 503 (or 408) and closed
    assert result["log_growth_bytes"] < 1 << 20, result
    assert edge_server.log_bytes() < 3 * (0.05 * 2**20) + 4096  # rotated: the file and 2 backups of 0.05 MB


@pytest.mark.slow
def test_an_upload_of_a_byte_every_4_s_hits_the_overall_deadline(tmp_path):
    from bench.edge import Server

    # the limits of a byte every 10 s under a 15 s deadline and a 30 s idle limit, scaled down
    with Server(tmp_path, ORCHARD_UPLOAD_DEADLINE_S="6", ORCHARD_UPLOAD_IDLE_S="12", ORCHARD_UPLOAD_MIN_KBPS="0") as server:
        token = _token(server, "trickle")
        head = b'--b0\r\nContent-Disposition: form-data; name="file"; filename="slow.laz"\r\n\r\n'
        with _connect(server) as s:
            s.sendall((f"POST /v1/blocks HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
                       f"Content-Type: multipart/form-data; boundary=b0\r\nContent-Length: 1000000\r\n\r\n").encode() + head)
            _trickle(s, b"x", every=4, times=4)  # a byte every 4 s: never idle for 12 s, and no minimum rate here
            reply = _reply(s)
        assert reply.startswith(b"HTTP/1.1 408") and b"did not arrive within 6 s" in reply, reply[:300]
        assert not list((server.data_dir / "tmp").rglob("upload-*"))
