"""Rough edges of the API and of `orchard serve`: operationIds, bodies that are not JSON,
paged job lists, over-long file names, a full disk on /healthz, malformed ranges and a
port in use."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest
from fastapi.testclient import TestClient
from service_fixtures import client_of, make_token, temp_files, write_las

from service.api.openapi import unique_operation_ids
from service.app import create_app
from service.db.jobstore import Store
from service.jobfolders import job_dir
from service.settings import Settings

_METHODS = {"get", "put", "post", "delete", "options", "head", "patch", "trace"}


@pytest.fixture(scope="module")
def edges(tmp_path_factory):
    """An app without runner (jobs stay queued) started in this process, and a client of one tenant."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("edges") / "data", runner=False, scheduling=False)
    with TestClient(create_app(settings)) as started:
        c = client_of(started, token=make_token(settings.data_dir, "farm"))
        yield settings, c
        c.close()


@pytest.fixture(scope="module")
def block(edges, tmp_path_factory):
    _, c = edges
    path = write_las(tmp_path_factory.mktemp("las") / "b.laz", 500, seed=5)
    r = c.post("/v1/blocks", files={"file": ("b.laz", path.read_bytes())})
    assert r.status_code == 201, r.text
    return r.json()


def _operation_ids(spec: dict) -> list[tuple[str, str, str]]:
    return [(path, method, op["operationId"]) for path, item in spec["paths"].items()
            for method, op in item.items() if method in _METHODS]


def test_every_operation_id_is_unique_and_names_its_method(tmp_path):
    spec = create_app(Settings(data_dir=tmp_path / "data", runner=False, scheduling=False)).openapi()
    ops = _operation_ids(spec)
    ids = [op_id for _, _, op_id in ops]
    assert len(ids) == len(set(ids)), sorted(i for i in ids if ids.count(i) > 1)
    assert all(op_id.endswith("_" + method) for _, method, op_id in ops)
    # a download answers GET and HEAD as two operations
    download = spec["paths"]["/v1/jobs/{job_id}/trees.parquet"]
    assert {download["get"]["operationId"], download["head"]["operationId"]} == {
        "job_trees_parquet_v1_jobs__job_id__trees_parquet_get", "job_trees_parquet_v1_jobs__job_id__trees_parquet_head"}
    assert spec["paths"]["/v1/jobs"]["get"]["operationId"] == "list_jobs_v1_jobs_get"  # one-method routes as before


@pytest.mark.slow
def test_operation_ids_are_the_same_whatever_the_hash_seed(tmp_path):
    # the duplicated ids ended in whichever method a set yielded first: with these two seeds,
    # both operations of a download were once "..._get" and once "..._head"
    code = ("import json, sys; from service.app import create_app; from service.settings import Settings; "
            "spec = create_app(Settings(data_dir=sys.argv[1], runner=False, scheduling=False)).openapi(); "
            "print(json.dumps(sorted(op['operationId'] for item in spec['paths'].values() for op in item.values() "
            "if isinstance(op, dict) and 'operationId' in op)))")
    runs = []
    for seed in ("1", "3"):
        r = subprocess.run([sys.executable, "-c", code, str(tmp_path / f"d{seed}")], capture_output=True, text=True,
                           timeout=120, env={**os.environ, "PYTHONHASHSEED": seed})
        assert r.returncode == 0, r.stderr
        runs.append(json.loads(r.stdout))
    assert runs[0] == runs[1]


def test_unique_operation_ids_renames_only_the_shared_ones():
    spec = {"paths": {
        "/a": {"get": {"operationId": "a_head"}, "head": {"operationId": "a_head"}, "parameters": []},
        "/b": {"post": {"operationId": "b_post"}},
    }}
    unique_operation_ids(spec)
    assert [op_id for _, _, op_id in _operation_ids(spec)] == ["a_get", "a_head", "b_post"]


@pytest.mark.parametrize("headers", [{}, {"Content-Type": "text/plain"}, {"Content-Type": "application/x-www-form-urlencoded"}])
def test_a_json_body_without_its_content_type_is_415_in_our_words(edges, block, headers):
    _, c = edges
    r = c.post("/v1/jobs", content=json.dumps({"block_id": block["id"]}).encode(), headers=headers)
    assert r.status_code == 415, r.text
    detail = r.json()["detail"]
    assert "Content-Type: application/json" in detail and "dictionary" not in detail


@pytest.mark.parametrize(("body", "says"), [
    (b'{"block_id": ', "not valid JSON"),
    (b'["a list"]', "must be a JSON object"),
    (b"", "no body"),
])
def test_a_body_that_is_not_a_json_object_is_422_in_our_words(edges, body, says):
    _, c = edges
    r = c.post("/v1/jobs", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and says in r.json()["detail"], r.text


def test_field_errors_keep_their_list(edges):
    _, c = edges
    r = c.post("/v1/jobs", json={"block_id": "x", "nope": 1})
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "nope"], r.text


def test_jobs_are_listed_a_page_at_a_time_like_trees(edges, block):
    settings, c = edges
    made = [c.post("/v1/jobs", json={"block_id": block["id"]}).json()["id"] for _ in range(3)]
    first = c.get("/v1/jobs", params={"block_id": block["id"], "limit": 2}).json()
    assert set(first) == {"items", "total", "limit", "offset"}
    assert first["total"] == 3 and first["limit"] == 2 and first["offset"] == 0
    second = c.get("/v1/jobs", params={"block_id": block["id"], "limit": 2, "offset": 2}).json()
    assert [j["id"] for j in first["items"] + second["items"]] == made[::-1]  # newest first, each once
    assert c.get("/v1/jobs", params={"block_id": block["id"], "state": "done"}).json()["total"] == 0
    # the bare list of before, for callers not yet reading pages
    bare = c.get("/v1/jobs", params={"block_id": block["id"], "paged": "false"}).json()
    assert [j["id"] for j in bare] == made[::-1]


def test_an_over_long_file_name_is_refused_as_such(edges):
    settings, c = edges
    data = write_las(settings.data_dir.parent / "long.laz", 300, seed=6).read_bytes()
    r = c.post("/v1/blocks", files={"file": ("a" * 5000 + ".laz", data)})
    assert r.status_code == 422 and "file name of the upload is too long" in r.json()["detail"], r.text
    assert temp_files(settings.data_dir) == []
    ok = c.post("/v1/blocks", files={"file": ("b" * 1000 + ".laz", data)})  # long, within the limit: shortened
    assert ok.status_code == 201 and ok.json()["filename"] == "b" * 200, ok.text


def test_healthz_is_not_ok_when_the_disk_is_below_the_threshold(tmp_path):
    low = Settings(data_dir=tmp_path / "data", runner=False, scheduling=False, min_free_mb=1e12)  # an exabyte
    with TestClient(create_app(low)) as c:
        r = c.get("/healthz")
    assert r.status_code == 503, r.text
    body = r.json()
    assert body["status"] == "not ok" and body["disk_free_mb"] > 0
    assert "MB free, below 1e+12 MB (ORCHARD_MIN_FREE_MB)" in body["problems"][0]


def test_healthz_is_ok_with_room(edges):
    _, c = edges
    body = c.get("/healthz").json()
    assert body["status"] == "ok" and body["problems"] == [] and body["disk_free_mb"] > 512


def _finished_job(edges, block, write_outputs, n_trees: int) -> str:
    """A job of ``block`` claimed and marked done, its folder filled by ``write_outputs(folder)``."""
    settings, c = edges
    job_id = c.post("/v1/jobs", json={"block_id": block["id"]}).json()["id"]
    store = Store(settings.store_path)
    try:
        while (claimed := store.jobs.claim_next()) is not None and claimed["id"] != job_id:
            pass
        out = job_dir(settings, job_id)
        out.mkdir(parents=True, exist_ok=True)
        write_outputs(out)
        store.jobs.finish(job_id, "done", outcome={"n_trees": n_trees})
    finally:
        store.close()
    return job_id


@pytest.fixture(scope="module")
def done_job(edges, block):
    """A job marked done with a 100-byte trees.parquet (the download routes serve files)."""
    return _finished_job(edges, block, lambda out: (out / "trees.parquet").write_bytes(bytes(range(100))), 0)


@pytest.mark.parametrize("method", ["GET", "HEAD"])
@pytest.mark.parametrize(("range_", "status"), [
    ("bytes=abc", 400), ("bytes=5-2", 400), ("bytes", 400), ("bytes=100-", 416), ("bytes=500-600", 416),
])
def test_a_range_that_cannot_be_served_is_a_json_error(edges, done_job, method, range_, status):
    _, c = edges
    r = c.request(method, f"/v1/jobs/{done_job}/trees.parquet", headers={"Range": range_})
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/json"
    if method == "GET":
        assert "Range" in r.json()["detail"]
    if status == 416:
        assert r.headers["content-range"] == "bytes */100"


def test_ranges_that_can_be_served_are(edges, done_job):
    _, c = edges
    url = f"/v1/jobs/{done_job}/trees.parquet"
    r = c.get(url, headers={"Range": "bytes=10-13"})
    assert r.status_code == 206 and r.content == bytes(range(10, 14)) and r.headers["content-range"] == "bytes 10-13/100"
    assert c.get(url, headers={"Range": "bytes=-3"}).content == bytes(range(97, 100))
    whole = c.get(url, headers={"Range": "pages=1-2"})  # a unit it does not know: ignored (RFC 9110 14.2)
    assert whole.status_code == 200 and whole.content == bytes(range(100))


def test_a_port_in_use_is_exit_2_naming_it_and_creates_nothing(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        r = subprocess.run(
            [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--data-dir", str(tmp_path / "data")],
            capture_output=True, text=True, timeout=120,
            env={**os.environ, "ORCHARD_RUNNER": "false", "ORCHARD_SCHEDULING": "false"},
        )
    assert r.returncode == 2, r.stderr  # not 3: that is "no trees"
    assert f"cannot listen on 127.0.0.1:{port}: the address is already in use" in r.stderr
    assert "--port" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "data").exists()


def test_a_port_file_in_a_folder_that_is_not_there_is_exit_2_and_creates_nothing(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "service.cli", "serve", "--port", "0", "--port-file", str(tmp_path / "nope" / "port"),
         "--data-dir", str(tmp_path / "data")],
        capture_output=True, text=True, timeout=120, env={**os.environ, "ORCHARD_RUNNER": "false", "ORCHARD_SCHEDULING": "false"},
    )
    assert r.returncode == 2, r.stderr
    assert f"--port-file {tmp_path / 'nope' / 'port'}: its folder does not exist" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "data").exists()


def test_the_servers_connections_send_small_responses_at_once():
    # without TCP_NODELAY a keep-alive response's last segment waited for the client's
    # delayed ACK: every request on a reused connection took about 40 ms
    import asyncio

    from service.commands.serve import bind
    from service.edge import EdgeLimits, EdgeSocket, edge_protocol

    async def accepted_nodelay() -> int:
        seen = asyncio.get_running_loop().create_future()

        async def on_connect(reader, writer):
            seen.set_result(writer.get_extra_info("socket").getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
            writer.close()

        listening = EdgeSocket.wrap(bind("127.0.0.1", 0), edge_protocol(EdgeLimits()))
        server = await asyncio.start_server(on_connect, sock=listening)  # as uvicorn serves it
        async with server:
            _, writer = await asyncio.open_connection("127.0.0.1", listening.getsockname()[1])
            writer.write(b"G")  # (a connection that has sent nothing stays with the kernel)
            value = await asyncio.wait_for(seen, 10)
            writer.close()
        return value

    assert asyncio.run(accepted_nodelay()) != 0


@pytest.fixture(scope="module")
def addressed_job(edges, block):
    """A job marked done whose trees.parquet holds 6 trees in 2 rows, one young."""
    import numpy as np

    from pipeline.parquet import write_trees_parquet

    k = 6
    trees = {
        "tree_id": np.arange(1, k + 1), "trunk_x": np.arange(k, dtype=float), "trunk_y": np.zeros(k),
        "trunk_z": np.zeros(k), "height_m": np.full(k, 3.0), "crown_diameter_m": np.ones(k),
        "crown_area_m2": np.ones(k), "crown_volume_m3": np.ones(k), "trunk_diameter_m": np.full(k, 0.1),
        "n_points": np.full(k, 100), "wood_fraction": np.full(k, 0.2),
        "row": np.array([1, 1, 1, 2, 2, 2], np.int32), "position": np.array([1, 2, 4, 1, 2, 3], np.int32),
        "young": np.array([False, False, True, False, False, False]),
    }
    return _finished_job(edges, block, lambda out: write_trees_parquet(out / "trees.parquet", trees, crs_wkt=None), k)


@pytest.mark.parametrize(("query", "ids"), [
    ({}, [1, 2, 3, 4, 5, 6]),
    ({"row": 2}, [4, 5, 6]),
    ({"row": 1, "position_min": 2}, [2, 3]),
    ({"position_min": 2, "position_max": 3}, [2, 5, 6]),
    ({"young": "true"}, [3]),
    ({"young": "false", "row": 1}, [1, 2]),
    ({"row": 9}, []),
])
def test_trees_filter_by_row_position_and_young(edges, addressed_job, query, ids):
    _, c = edges
    page = c.get(f"/v1/jobs/{addressed_job}/trees", params=query).json()
    assert [t["tree_id"] for t in page["items"]] == ids and page["total"] == len(ids)


@pytest.mark.parametrize("query", [{"rows": 2}, {"row": 1, "colour": "red"}, {"": ""}])
def test_an_unknown_query_parameter_is_refused_by_name(edges, addressed_job, query):
    _, c = edges
    r = c.get(f"/v1/jobs/{addressed_job}/trees", params=query)
    assert r.status_code == 422, r.text
    unknown = [k for k in query if k not in ("row",)]
    assert all(repr(u) in r.json()["detail"] for u in unknown)
    assert "row" in r.json()["detail"].split("takes:")[1]


@pytest.mark.parametrize("query", [{"row": ""}, {"row": "0"}, {"young": "maybe"}])
def test_an_empty_or_bad_filter_is_refused(edges, addressed_job, query):
    _, c = edges
    assert c.get(f"/v1/jobs/{addressed_job}/trees", params=query).status_code == 422


def test_unknown_query_parameters_are_refused_on_every_v1_route(edges):
    _, c = edges
    r = c.get("/v1/jobs", params={"stat": "done"})
    assert r.status_code == 422 and "'stat'" in r.json()["detail"]
