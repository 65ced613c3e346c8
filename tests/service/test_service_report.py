"""The per-tree report: subsampled map with the right tree ids, escaped HTML, the table."""

from __future__ import annotations

import math
import shutil
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from service_fixtures import write_las

from service.reports.report import trees_records, write_report, write_trees_csv
from service.reports.sampling import sample_points


def _outputs(tmp_path, n):
    points = pa.table({
        "point_index": pa.array(np.arange(n)[::-1].astype(np.uint64)),  # any row order
        "tree_id": pa.array((np.arange(n)[::-1] % 3).astype(np.int64)),
        "is_ground": pa.array(np.zeros(n, bool)),
        "is_wood": pa.array(np.zeros(n, bool)),
        "wood_score": pa.array(np.zeros(n, np.float32)),
    })
    pq.write_table(points, tmp_path / "points.parquet")
    trees = pa.table({
        "tree_id": pa.array([1, 2], pa.int64()),
        "trunk_x": [500002.0, 500007.0], "trunk_y": [6000005.0, 6000005.0], "trunk_z": [0.0, 0.0],
        "height_m": [3.5, 4.0], "crown_diameter_m": [3.0, 3.2], "crown_area_m2": [7.0, 8.0],
        "crown_volume_m3": [12.0, 14.0], "trunk_diameter_m": [0.12, float("nan")],
        "n_points": pa.array([10, 12], pa.int64()), "wood_fraction": [0.2, 0.3],
        "geometry": pa.array([b"\x01", b"\x01"]),
    })
    pq.write_table(trees, tmp_path / "trees.parquet")
    return tmp_path / "points.parquet", tmp_path / "trees.parquet"


def test_sample_points_keeps_ids_aligned(tmp_path):
    block = write_las(tmp_path / "b.las", 10_000, seed=2)
    points, _ = _outputs(tmp_path, 10_000)
    xy, tree_id, origin = sample_points(str(block), points, max_points=1000)
    assert len(xy) == len(tree_id) == 1000
    stride = 10
    assert np.array_equal(tree_id, (np.arange(0, 10_000, stride) % 3))
    assert origin[0] == 500000.0


def test_report_html_and_csv(tmp_path):
    block = write_las(tmp_path / "b.las", 5_000, seed=3)
    points, trees = _outputs(tmp_path, 5_000)
    page = write_report(block_path=str(block), trees_parquet=trees, points_parquet=points, out_dir=tmp_path,
                        title="Report <script>alert(1)</script>", summary={"Block": "<b>x</b>"})
    text = page.read_text()
    assert "<script>alert" not in text and "&lt;script&gt;" in text and "&lt;b&gt;" in text
    assert text.count("<tr>") == 3 and "data:image/png;base64," in text
    assert (tmp_path / "map.png").read_bytes()[:4] == b"\x89PNG"
    assert "–" in text  # the NaN trunk diameter
    rows = trees_records(trees)
    assert rows[1]["trunk_diameter_m"] is None and "geometry" not in rows[0]
    csv = write_trees_csv(trees, tmp_path / "trees.csv").read_text().splitlines()
    assert csv[0].split(",")[0] == '"tree_id"' and len(csv) == 3 and "geometry" not in csv[0]
    assert not math.isnan(rows[0]["trunk_diameter_m"])


def test_csv_leaves_unmeasured_values_empty(tmp_path):
    # "nan" in a spreadsheet is text; JSON gives null and the report "–"
    _, trees = _outputs(tmp_path, 100)
    lines = write_trees_csv(trees, tmp_path / "trees.csv").read_text().splitlines()
    header = [h.strip('"') for h in lines[0].split(",")]
    second = lines[2].split(",")
    assert "nan" not in lines[2].lower()
    assert second[header.index("trunk_diameter_m")] == ""
    assert float(lines[1].split(",")[header.index("trunk_diameter_m")]) == 0.12


def test_a_title_with_dollar_signs_is_text_and_a_partial_result_says_so(tmp_path):
    # matplotlib read "$...$" in a capture's file name as a formula: the map, and with it
    # the whole report, failed with a 500 on every request
    block = write_las(tmp_path / "b.las", 2_000, seed=3)
    points, trees = _outputs(tmp_path, 2_000)
    for name in ("row_$1_$2.laz", r"price $\frac{a$ and $6.laz"):
        page = write_report(block_path=str(block), trees_parquet=trees, points_parquet=points, out_dir=tmp_path,
                            title=f"Orchard report — {name}", warning="Partial result: tile(s) 3, 4 of this block failed.")
        text = page.read_text()
        assert name.replace("&", "&amp;") in text
        assert text.index("Partial result: tile(s) 3, 4") < text.index("<ul>")


@pytest.fixture
def finished_job(tmp_path):
    """A store holding one uploaded block and a job of it marked done with the given
    outcome (and result files): ``make(filename, outcome) -> (settings, store, job)``."""
    from service.db.block_files import accept_block
    from service.db.jobstore import Store
    from service.jobfolders import job_dir
    from service.schedules import file_sha256
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data")
    settings.blocks_dir.mkdir(parents=True)
    store = Store(settings.store_path)

    def make(filename: str, outcome: dict):
        tenant = store.accounts.ensure_tenant("farm")
        src = write_las(tmp_path / "upload.las", 3_000, seed=4)
        block, _ = accept_block(store, blocks_dir=settings.blocks_dir, tenant_id=tenant["id"], tmp_path=src,
                                sha256=file_sha256(src), size_bytes=src.stat().st_size, filename=filename)
        job = store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={"tiling": {"tile_size": 20}})
        assert store.jobs.claim_next()["id"] == job["id"]
        out = job_dir(settings, job["id"])
        out.mkdir(parents=True)
        points, trees = _outputs(tmp_path, 3_000)
        shutil.copy(points, out / "points.parquet")
        shutil.copy(trees, out / "trees.parquet")
        return settings, store, store.jobs.finish(job["id"], "done", outcome=outcome)

    try:
        yield make
    finally:
        store.close()


def test_the_report_of_a_partial_result_says_which_tiles_are_missing(finished_job):
    # the API said "partial", the report did not: a grower reading it saw a block with
    # fewer trees and no word why
    from service.reports.outputs import ensure_report

    settings, store, job = finished_job("north $block$.las", {"n_trees": 2, "partial": True, "failed_tiles": [3, 4]})
    text = ensure_report(store, settings, job).read_text()
    assert "Partial result: tile(s) 3, 4 of this block failed" in text
    assert "north $block$.las" in text and "(UTC" in text  # the finish time, its zone said


def test_a_lost_map_is_drawn_again_and_a_lost_block_is_a_clear_404(finished_job):
    # map.png lost beside its report.html: every request for it was a 500 (and the map was
    # never drawn again); the block file lost: a 422 naming the server's checksum file
    from service.reports.outputs import ensure_report
    from service.db.errors import NotFoundError
    from service.jobfolders import job_dir

    settings, store, job = finished_job("north.las", {"n_trees": 2})
    out = job_dir(settings, job["id"])
    ensure_report(store, settings, job)
    (out / "map.png").unlink()
    ensure_report(store, settings, job)
    assert (out / "map.png").read_bytes()[:4] == b"\x89PNG"
    (out / "report.html").unlink()
    stored = Path(store.blocks.get(job["tenant_id"], job["block_id"])["path"])
    stored.unlink()
    with pytest.raises(NotFoundError, match="uploaded block of this job is missing on the server") as err:
        ensure_report(store, settings, job)
    assert stored.name not in str(err.value)


def test_a_scheduled_jobs_report_names_its_capture(finished_job):
    # the same bytes were uploaded before as "test-upload.las": the night's report is
    # about the capture the schedule took
    from service.reports.outputs import ensure_report
    from service.api.schemas import job_out

    settings, store, job = finished_job("test-upload.las", {"n_trees": 2})
    store.db.connection().execute("UPDATE jobs SET capture = 'night-7.laz' WHERE id = ?", (job["id"],))
    job = store.jobs.get_any_tenant(job["id"])
    assert job_out(job).capture == "night-7.laz"
    text = ensure_report(store, settings, job).read_text()
    assert "Orchard report — night-7.laz" in text and "test-upload.las" not in text


@pytest.mark.skipif(not hasattr(time, "tzset") or not Path("/usr/share/zoneinfo/Australia/Sydney").exists(),
                    reason="needs time.tzset and the system's zone files")
def test_the_report_gives_the_finish_time_in_the_servers_zone(finished_job, monkeypatch):
    # a grower read "Finished ... UTC" while the schedules run on the server's local time
    from service.reports.outputs import ensure_report

    monkeypatch.setenv("TZ", "Australia/Sydney")
    time.tzset()
    try:
        settings, store, job = finished_job("north.las", {"n_trees": 2})
        text = ensure_report(store, settings, job).read_text()
        local = datetime.fromtimestamp(job["finished_at"]).astimezone()
        assert local.strftime("%Y-%m-%d %H:%M") in text and "(UTC+1100)" in text  # AEDT in November
    finally:
        monkeypatch.undo()
        time.tzset()
