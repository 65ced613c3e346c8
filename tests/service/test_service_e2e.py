"""End to end against a real `orchard serve` with its runner and an embedded LocalCluster:
upload a generated block, run a tiled job on the dask workers, download every result; a
job cancelled while it runs; a job that finds no trees (the restarts of a server on one
data folder: test_service_restarts.py)."""

from __future__ import annotations

import io
import re
import time

import httpx
import numpy as np
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest
from service_fixtures import ServerProcess, make_token, simulated_block, wait_for_job

pytestmark = pytest.mark.slow

TREE_COLUMNS = ["tree_id", "trunk_x", "trunk_y", "trunk_z", "height_m", "crown_diameter_m", "crown_area_m2",
                "crown_volume_m3", "trunk_diameter_m", "n_points", "wood_fraction"]


@pytest.fixture(scope="module")
def block_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("e2e") / "orchard.laz"
    return simulated_block(path, rows=2, trees_per_row=4, seed=7, density=0.3)


@pytest.fixture(scope="module")
def runner_server(tmp_path_factory):
    srv = ServerProcess(tmp_path_factory.mktemp("e2e-server") / "data", ORCHARD_SCHEDULING="false")
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def _client(srv: ServerProcess, tenant: str) -> httpx.Client:
    token = make_token(srv.data_dir, tenant)
    return httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60)


def test_upload_job_results(runner_server, block_file):
    with _client(runner_server, "farm-e2e") as c, _client(runner_server, "farm-other") as other:
        with open(block_file, "rb") as fh:
            block = c.post("/v1/blocks", files={"file": ("orchard.laz", fh)}).json()
        assert block["n_points"] > 100_000 and block["crs_wkt"]
        job = c.post("/v1/jobs", json={"block_id": block["id"], "tiling": {"tile_size": 20}}).json()
        deadline = time.monotonic() + 150
        while time.monotonic() < deadline:
            cur = c.get(f"/v1/jobs/{job['id']}").json()
            if cur["state"] in ("done", "failed", "cancelled"):
                break
            time.sleep(0.2)
        assert cur["state"] == "done", cur["error"]
        assert httpx.get(runner_server.url + "/healthz").json()["cluster"] == "connected"
        assert cur["tiles_total"] > 1 and cur["tiles_done"] == cur["tiles_total"]
        assert cur["timings"] and cur["n_trees"] >= 6 and cur["n_points"] == block["n_points"]

        page = c.get(f"/v1/jobs/{job['id']}/trees", params={"limit": 3, "offset": 1}).json()
        assert page["total"] == cur["n_trees"] and len(page["items"]) == min(3, page["total"] - 1)
        assert page["items"][0]["tree_id"] == 2 and set(TREE_COLUMNS) <= set(page["items"][0])

        r = c.get(f"/v1/jobs/{job['id']}/trees.parquet")
        assert r.status_code == 200 and r.headers["content-type"] == "application/vnd.apache.parquet"
        trees = pq.read_table(io.BytesIO(r.content))
        assert trees.num_rows == cur["n_trees"] and set(TREE_COLUMNS) <= set(trees.column_names)
        assert b"geo" in trees.schema.metadata

        r = c.get(f"/v1/jobs/{job['id']}/trees.csv")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
        csv = pacsv.read_csv(io.BytesIO(r.content))
        assert csv.num_rows == cur["n_trees"]
        assert csv.column_names[: len(TREE_COLUMNS) + 3] == TREE_COLUMNS + ["row", "position", "young"]
        assert {"tree_key", "status", "height_change_m"} <= set(csv.column_names)
        np.testing.assert_allclose(csv.column("height_m").to_numpy(), trees.column("height_m").to_numpy())

        r = c.get(f"/v1/jobs/{job['id']}/points.parquet")
        points = pq.read_table(io.BytesIO(r.content))
        # download tools ask for the size first and resume a broken download where it stopped
        head = c.head(f"/v1/jobs/{job['id']}/points.parquet")
        assert head.status_code == 200 and int(head.headers["content-length"]) == len(r.content) and head.content == b""
        part = c.get(f"/v1/jobs/{job['id']}/points.parquet", headers={"Range": f"bytes={len(r.content) - 100}-"})
        assert part.status_code == 206 and part.content == r.content[-100:]
        assert points.num_rows == block["n_points"]
        assert np.array_equal(np.sort(points.column("point_index").to_numpy()), np.arange(block["n_points"]))
        assert set(np.unique(points.column("tree_id").to_numpy())) <= set(range(cur["n_trees"] + 1))

        r = c.get(f"/v1/jobs/{job['id']}/report")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert re.search(r'<img [^>]*src="data:image/png;base64,[A-Za-z0-9+/=]{1000,}"', r.text)
        assert r.text.count("<tr>") == cur["n_trees"] + 1
        assert {"self", "trees", "trees.parquet", "trees.csv", "points.parquet", "rows.parquet", "gaps.parquet", "report",
                "map.png"} <= set(cur["links"])
        rows = pq.read_table(io.BytesIO(c.get(cur["links"]["rows.parquet"]).content))
        assert rows.column("n_trees").to_numpy().sum() == cur["n_trees"] and b"geo" in rows.schema.metadata
        gaps = pq.read_table(io.BytesIO(c.get(cur["links"]["gaps.parquet"]).content))
        assert {"row", "position", "x", "y", "geometry"} <= set(gaps.column_names)
        png = c.get(cur["links"]["map.png"])
        assert png.content[:8] == b"\x89PNG\r\n\x1a\n"

        for suffix in ("", "/trees", "/trees.csv", "/points.parquet", "/rows.parquet", "/gaps.parquet", "/report"):
            assert other.get(f"/v1/jobs/{job['id']}{suffix}").status_code == 404
        assert c.delete(f"/v1/jobs/{job['id']}").status_code == 409


def test_cancel_a_running_job(runner_server, block_file):
    with _client(runner_server, "farm-e2e") as c:
        with open(block_file, "rb") as fh:
            block = c.post("/v1/blocks", files={"file": ("orchard.laz", fh)}).json()
        job = c.post("/v1/jobs", json={"block_id": block["id"], "tiling": {"tile_size": 10}}).json()
        assert wait_for_job(c, job["id"], states=("running", "done", "failed"))["state"] == "running"
        deadline = time.monotonic() + 60  # cancel once the tiles are written and being processed
        while not c.get(f"/v1/jobs/{job['id']}").json()["tiles_total"] and time.monotonic() < deadline:
            time.sleep(0.05)
        r = c.delete(f"/v1/jobs/{job['id']}")
        assert r.status_code == 202 and r.json()["cancel_requested"] is True
        final = wait_for_job(c, job["id"])
        assert final["state"] == "cancelled", final
        r = c.get(f"/v1/jobs/{job['id']}/trees")
        assert r.status_code == 409 and "cancelled and has no results" in r.json()["detail"]
    # the service never resumes a cancelled job: its tiles are deleted, not kept for good
    job_dir = runner_server.data_dir / "jobs" / job["id"]
    assert not (job_dir / "_work").exists(), sorted(p.name for p in job_dir.iterdir())


def test_job_that_finds_no_trees_fails_with_its_message(runner_server, tmp_path):
    from pipeline.laswriting import LasBlockWriter

    # bare, gently sloping ground with a few low weeds: a block without trees (a cloud
    # of uniform random points 3 m deep is no such block: see docs/limits.md)
    rng = np.random.default_rng(9)
    xy = rng.uniform(0, 20, (20_000, 2))
    z = 0.02 * xy[:, 0] + rng.normal(0, 0.01, len(xy))
    weeds = rng.random(len(xy)) < 0.05
    z[weeds] += rng.uniform(0.0, 0.3, int(weeds.sum()))
    flat = tmp_path / "flat.laz"
    with LasBlockWriter(flat, crs_epsg=28356) as w:
        w.write(np.column_stack([xy + [500_000.0, 6_950_000.0], z + 100.0]))
    with _client(runner_server, "farm-e2e") as c:
        with open(flat, "rb") as fh:
            block = c.post("/v1/blocks", files={"file": ("flat.laz", fh)}).json()
        job = c.post("/v1/jobs", json={"block_id": block["id"]}).json()
        done = wait_for_job(c, job["id"])
        assert done["state"] == "failed"
        assert "tree" in done["error"] and "Traceback" not in done["error"]
        # named as the client knows them: its file name, the request's fields; not the
        # server's stored file (named by its sha256) or the command line's options
        assert done["error"].startswith("flat.laz: "), done["error"]
        assert block["sha256"][:12] not in done["error"]
        assert "params.trunks.min_tree_height" in done["error"] and "--" not in done["error"]
        assert c.get(f"/v1/jobs/{job['id']}/trees").status_code == 409
