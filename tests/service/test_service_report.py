"""The per-tree report: subsampled map with the right tree ids, escaped HTML, the table."""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from service.report import sample_points, trees_records, write_report, write_trees_csv
from service_fixtures import write_las


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
    assert "<script>" not in text and "&lt;script&gt;" in text and "&lt;b&gt;" in text
    assert text.count("<tr>") == 3 and "data:image/png;base64," in text
    assert (tmp_path / "map.png").read_bytes()[:4] == b"\x89PNG"
    assert "–" in text  # the NaN trunk diameter
    rows = trees_records(trees)
    assert rows[1]["trunk_diameter_m"] is None and "geometry" not in rows[0]
    csv = write_trees_csv(trees, tmp_path / "trees.csv").read_text().splitlines()
    assert csv[0].split(",")[0] == '"tree_id"' and len(csv) == 3 and "geometry" not in csv[0]
    assert not math.isnan(rows[0]["trunk_diameter_m"])
