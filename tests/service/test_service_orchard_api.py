"""``/v1/orchard-blocks`` over HTTP (the app in this process, its runner off): blocks,
captures sent as files or as uploaded blocks, their order, the block's history and a
tree's, tenants kept apart, and the upload and job routes beside them.

A capture's job does not run here: the tests mark it done and put the outputs it would
have written (by hand, with the contract's columns: `seasons_fixtures`) in its folder.
"""

from __future__ import annotations

import io
import uuid

import pyarrow.parquet as pq
import pytest
from seasons_fixtures import write_capture_outputs
from service_fixtures import tenant_inbox, write_las

from service.jobfolders import job_dir


def _name() -> str:
    return f"block-{uuid.uuid4().hex[:8]}"


def _finish(api, job_id: str, which: str | None, *, state: str = "done") -> None:
    """Mark a capture's job as its runner would, with the outputs of capture ``which``
    (`seasons_fixtures`) in its folder."""
    store, settings = api.app.state.store, api.app.state.settings
    out = job_dir(settings, job_id)
    outputs = {}
    if which is not None:
        write_capture_outputs(out, which)
        outputs = {"trees": str(out / "trees.parquet"), "history": str(out / "history.parquet")}
    with store.db.transaction() as con:  # claimed, as the runner would (the shared queue holds other tests' jobs)
        con.execute("UPDATE jobs SET state = 'running' WHERE id = ?", (job_id,))
    if which is not None:
        from service.seasons import capture_record

        store.orchard_blocks.set_capture_record(job_id, capture_record(out))
    store.jobs.finish(job_id, state, outcome={"outputs": outputs, "n_trees": 7} if state == "done" else None,
                     error=None if state == "done" else "no overlap")


@pytest.fixture()
def las(tmp_path):
    return write_las(tmp_path / "scan.laz", 500, seed=uuid.uuid4().int % 1000)


def test_create_list_and_read_blocks_per_tenant(client_a, client_b):
    name = _name()
    r = client_a.post("/v1/orchard-blocks", json={"name": f"  {name}  "})
    assert r.status_code == 201, r.text
    ob = r.json()
    assert ob["name"] == name and ob["n_captures"] == 0 and r.headers["Location"] == f"/v1/orchard-blocks/{ob['id']}"
    again = client_a.post("/v1/orchard-blocks", json={"name": name})
    assert again.status_code == 409 and "already has an orchard block" in again.json()["detail"]
    assert client_b.post("/v1/orchard-blocks", json={"name": name}).status_code == 201  # another farm's own
    assert client_a.post("/v1/orchard-blocks", json={"name": ""}).status_code == 422
    assert client_a.post("/v1/orchard-blocks", json={"name": "a\nb"}).status_code == 422
    assert ob["id"] in [o["id"] for o in client_a.get("/v1/orchard-blocks").json()]
    assert ob["id"] not in [o["id"] for o in client_b.get("/v1/orchard-blocks").json()]
    assert client_a.get(f"/v1/orchard-blocks/{ob['id']}").json()["name"] == name


def test_add_captures_as_files_and_as_uploaded_blocks_in_order(client_a, las, tmp_path):
    ob = client_a.post("/v1/orchard-blocks", json={"name": _name()}).json()
    r = client_a.post(f"/v1/orchard-blocks/{ob['id']}/captures", params={"captured_at": "2026-04-01"},
                      files={"file": ("april.laz", las.read_bytes())})
    assert r.status_code == 201, r.text
    first = r.json()
    assert (first["seq"], first["state"], first["captured_at"], first["captured_at_source"]) == (1, "queued", "2026-04-01", "given")
    # the upload and job routes see the capture's file and job as any other
    assert client_a.get(f"/v1/blocks/{first['block_id']}").json()["filename"] == "april.laz"
    job = client_a.get(f"/v1/jobs/{first['job_id']}").json()
    assert job["state"] == "queued" and job["block_id"] == first["block_id"]
    assert job["orchard_block"] == {"id": ob["id"], "name": ob["name"], "capture_id": first["id"], "seq": 1,
                                    "captured_at": "2026-04-01"}
    # an uploaded block, by its id, as JSON
    other = write_las(tmp_path / "july.laz", 400, seed=11)
    block = client_a.post("/v1/blocks", files={"file": ("july.laz", other.read_bytes())}).json()
    r = client_a.post(f"/v1/orchard-blocks/{ob['id']}/captures", json={"block_id": block["id"]})
    assert r.status_code == 201, r.text
    second = r.json()
    assert second["seq"] == 2 and second["captured_at_source"] == "upload" and second["block_id"] == block["id"]
    listed = client_a.get(f"/v1/orchard-blocks/{ob['id']}/captures").json()
    assert [c["id"] for c in listed] == [first["id"], second["id"]]
    assert client_a.get(f"/v1/orchard-blocks/{ob['id']}/captures/{second['id']}").json()["job_id"] == second["job_id"]
    assert client_a.get(f"/v1/orchard-blocks/{ob['id']}").json()["n_captures"] == 2


@pytest.mark.parametrize("how, expected", [
    ({"params": {"captured_at": "1st of May"}, "files": True}, 422),
    ({"json": {"block_id": "nope"}}, 404),
    ({"json": {"block_id": "x", "captured_at": "2026-13-01"}}, 422),
    ({"json": {"block_id": "x", "extra": 1}}, 422),
    ({"content": b"block_id=x", "headers": {"Content-Type": "application/x-www-form-urlencoded"}}, 415),
    # JSON is held in memory: the server's small body limit, not the upload limit of the route
    ({"content": b'{"block_id": "' + b"x" * 1_200_000 + b'"}', "headers": {"Content-Type": "application/json"}}, 413),
])
def test_a_bad_capture_is_refused_and_nothing_is_queued(client_a, las, how, expected):
    ob = client_a.post("/v1/orchard-blocks", json={"name": _name()}).json()
    kwargs = dict(how)
    if kwargs.pop("files", False):
        kwargs["files"] = {"file": ("scan.laz", las.read_bytes())}
    r = client_a.post(f"/v1/orchard-blocks/{ob['id']}/captures", **kwargs)
    assert r.status_code == expected, r.text
    assert "Traceback" not in r.text and r.json()["detail"]
    assert client_a.get(f"/v1/orchard-blocks/{ob['id']}/captures").json() == []


def test_another_tenants_block_is_not_found(client_a, client_b, las):
    ob = client_a.post("/v1/orchard-blocks", json={"name": _name()}).json()
    cap = client_a.post(f"/v1/orchard-blocks/{ob['id']}/captures", files={"file": ("scan.laz", las.read_bytes())}).json()
    _finish(_api(client_a), cap["job_id"], "c1")
    base = f"/v1/orchard-blocks/{ob['id']}"
    for path in ("", "/captures", f"/captures/{cap['id']}", "/history.parquet", "/trees/1/history"):
        r = client_b.get(base + path)
        assert r.status_code == 404, (path, r.text)
        assert ob["id"] in r.json()["detail"] or "capture" in r.json()["detail"]
    r = client_b.post(base + "/captures", files={"file": ("scan.laz", las.read_bytes())})
    assert r.status_code == 404
    # nor may farm b capture farm a's uploaded file into a block of its own
    own = client_b.post("/v1/orchard-blocks", json={"name": _name()}).json()
    r = client_b.post(f"/v1/orchard-blocks/{own['id']}/captures", json={"block_id": cap["block_id"]})
    assert r.status_code == 404
    assert client_b.get(f"/v1/orchard-blocks/{own['id']}/captures").json() == []


def _api(client):
    """The started app behind a client (its store and settings)."""
    class _A:
        app = client.app
    return _A


def test_history_routes_serve_the_latest_done_capture(client_a, las, tmp_path):
    api = _api(client_a)
    ob = client_a.post("/v1/orchard-blocks", json={"name": _name()}).json()
    base = f"/v1/orchard-blocks/{ob['id']}"
    caps = []
    for i in range(3):
        f = write_las(tmp_path / f"s{i}.laz", 300, seed=100 + i)
        caps.append(client_a.post(f"{base}/captures", files={"file": (f.name, f.read_bytes())}).json())
    r = client_a.get(f"{base}/history.parquet")
    assert r.status_code == 404 and "no processed capture yet" in r.json()["detail"]
    _finish(api, caps[0]["job_id"], "c1")
    _finish(api, caps[1]["job_id"], "c2")
    _finish(api, caps[2]["job_id"], None, state="failed")  # leaves the history as it was
    table = pq.read_table(io.BytesIO(client_a.get(f"{base}/history.parquet").content))
    assert set(table.column("capture").to_pylist()) == {"c1", "c2"}
    assert {"tree_key", "capture", "captured_at", "row", "position", "height_m", "crown_volume_m3", "trunk_diameter_m",
            "status"} <= set(table.column_names)
    gone = client_a.get(f"{base}/trees/3/history").json()
    assert [(h["captured_at"], h["status"]) for h in gone["items"]] == [("2026-04-01", "new"), ("2026-07-01", "removed")]
    assert gone["items"][1]["height_m"] is None
    grown = client_a.get(f"{base}/trees/1/history").json()["items"]
    assert grown[1]["height_m"] - grown[0]["height_m"] == pytest.approx(0.30)
    assert client_a.get(f"{base}/trees/99/history").status_code == 404
    assert client_a.get(f"{base}/trees/-1/history").status_code == 422
    listed = {c["id"]: c for c in client_a.get(f"{base}/captures").json()}
    second = listed[caps[1]["id"]]
    assert second["state"] == "done" and second["registration"]["residual_m"] == 0.021
    assert second["captured_at"] == "2026-07-01" and second["captured_at_source"] == "file"
    assert second["counts"] == {"same": 6, "new": 1, "replanted": 1, "removed": 1}
    assert listed[caps[2]["id"]]["state"] == "failed"
    assert client_a.get(base).json()["n_done"] == 2
    # the capture's job gives its own history too, among its results
    job = client_a.get(f"/v1/jobs/{caps[1]['job_id']}").json()
    assert job["links"]["history.parquet"] == f"/v1/jobs/{job['id']}/history.parquet"
    assert client_a.get(job["links"]["history.parquet"]).content == client_a.get(f"{base}/history.parquet").content


def test_two_blocks_of_one_tenant_never_mix(client_a, las, tmp_path):
    api = _api(client_a)
    north = client_a.post("/v1/orchard-blocks", json={"name": _name()}).json()
    south = client_a.post("/v1/orchard-blocks", json={"name": _name()}).json()
    n = client_a.post(f"/v1/orchard-blocks/{north['id']}/captures", files={"file": ("n.laz", las.read_bytes())}).json()
    f = write_las(tmp_path / "s.laz", 300, seed=77)
    s = client_a.post(f"/v1/orchard-blocks/{south['id']}/captures", files={"file": ("s.laz", f.read_bytes())}).json()
    _finish(api, n["job_id"], "c2")
    assert [c["id"] for c in client_a.get(f"/v1/orchard-blocks/{north['id']}/captures").json()] == [n["id"]]
    assert [c["id"] for c in client_a.get(f"/v1/orchard-blocks/{south['id']}/captures").json()] == [s["id"]]
    assert client_a.get(f"/v1/orchard-blocks/{north['id']}/trees/1/history").status_code == 200
    assert client_a.get(f"/v1/orchard-blocks/{south['id']}/history.parquet").status_code == 404  # north's is not south's
    # a capture is read through its own block only
    assert client_a.get(f"/v1/orchard-blocks/{south['id']}/captures/{n['id']}").status_code == 404


def test_an_inbox_schedule_of_a_block_over_http(client_a, client_b, api_data, las):
    ob = client_a.post("/v1/orchard-blocks", json={"name": _name()}).json()
    inbox = tenant_inbox(api_data, "farm-a", f"inbox-{uuid.uuid4().hex[:6]}")
    r = client_a.post("/v1/schedules", json={"inbox": str(inbox), "orchard_block_id": ob["id"]})
    assert r.status_code == 201, r.text
    sched = r.json()
    assert sched["orchard_block_id"] == ob["id"]
    (inbox / "night1.laz").write_bytes(las.read_bytes())
    run = client_a.post(f"/v1/schedules/{sched['id']}/run").json()
    assert len(run["jobs"]) == 1
    caps = client_a.get(f"/v1/orchard-blocks/{ob['id']}/captures").json()
    assert [c["job_id"] for c in caps] == run["jobs"] and caps[0]["captured_at_source"] == "upload"
    # farm b cannot point an inbox at farm a's block
    inbox_b = tenant_inbox(api_data, "farm-b", f"inbox-{uuid.uuid4().hex[:6]}")
    assert client_b.post("/v1/schedules", json={"inbox": str(inbox_b), "orchard_block_id": ob["id"]}).status_code == 404


def test_a_capture_file_has_the_upload_limit(client_a, api):
    ob = client_a.post("/v1/orchard-blocks", json={"name": _name()}).json()
    big = b"LASF" + b"\0" * (api.app.state.settings.max_upload_bytes + 10)
    r = client_a.post(f"/v1/orchard-blocks/{ob['id']}/captures", files={"file": ("big.laz", big)})
    assert r.status_code == 413 and "upload limit" in r.json()["detail"]
    assert client_a.get(f"/v1/orchard-blocks/{ob['id']}/captures").json() == []
