"""The service's edge under load and abuse, on loopback: JSON bodies bounded in shape
before validation, idle and slow connections timed out, connections capped, trickling
uploads stopped. Timings live in bench/edge.py; these tests assert outcomes only."""

from __future__ import annotations

import json
import threading

import httpx
import pytest
from service_fixtures import client_of

from service.api.bodies import MAX_DEPTH, MAX_KEYS, shape_problem


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
    resp = client_a.post("/v1/jobs", content=_many_keys(60_000), headers={"Content-Type": "application/json"})
    assert resp.status_code == 422 and "more than 1000 keys" in resp.json()["detail"]
    deep = ("[" * 5000 + "]" * 5000).encode()
    resp = client_a.post("/v1/jobs", content=deep, headers={"Content-Type": "application/json"})
    assert resp.status_code == 422 and "deep" in resp.json()["detail"]
    with client_of(api) as anonymous:  # no token: refused all the same, before the sign-in is looked at
        resp = anonymous.post("/v1/jobs", content=_many_keys(60_000), headers={"Content-Type": "application/json"})
        assert resp.status_code == 422
    # an ordinary request is untouched (its error is the usual one: no such block)
    resp = client_a.post("/v1/jobs", json={"block_id": "nope", "params": {}})
    assert resp.status_code == 404, resp.text


@pytest.mark.slow
def test_healthz_answers_while_sixteen_clients_send_1mb_bodies(api_server, server_tokens):
    body = _many_keys(60_000, size=1000 * 1024)
    assert len(body) <= 1024 * 1024
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
    assert statuses and set(statuses) == {422}, set(statuses)
