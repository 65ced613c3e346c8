"""Parquet outputs: GeoParquet trees (WKB points, geo metadata), streamed points; lossless round trips."""

from __future__ import annotations

import json
import struct

import numpy as np
import pyarrow.parquet as pq
import pyproj
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pipeline.parquet import PointsParquetWriter, read_trees_parquet, write_trees_parquet
from las_blocks import EASTING, NORTHING


def _tree_columns(k, rng):
    cols = {
        "tree_id": np.arange(1, k + 1, dtype=np.int64),
        "trunk_x": rng.uniform(0, 100, k) + EASTING,
        "trunk_y": rng.uniform(0, 100, k) + NORTHING,
        "trunk_z": rng.uniform(50, 60, k),
    }
    for name in ("height_m", "crown_diameter_m", "crown_area_m2", "crown_volume_m3", "trunk_diameter_m", "wood_fraction"):
        cols[name] = rng.uniform(0, 10, k)
    cols["n_points"] = rng.integers(0, 10_000, k).astype(np.int64)
    return cols


@pytest.mark.parametrize("epsg", [28356, None])
def test_trees_geoparquet(tmp_path, epsg):
    cols = _tree_columns(12, np.random.default_rng(3))
    wkt = pyproj.CRS.from_epsg(epsg).to_wkt() if epsg else None
    write_trees_parquet(tmp_path / "trees.parquet", cols, crs_wkt=wkt)
    table = pq.read_table(tmp_path / "trees.parquet")
    geo = json.loads(table.schema.metadata[b"geo"])
    assert geo["version"] == "1.1.0" and geo["primary_column"] == "geometry"
    col = geo["columns"]["geometry"]
    assert col["encoding"] == "WKB" and col["geometry_types"] == ["Point"]
    if epsg:
        assert pyproj.CRS.from_json_dict(col["crs"]).to_epsg() == epsg
    else:
        assert col["crs"] is None
    assert col["bbox"] == [cols["trunk_x"].min(), cols["trunk_y"].min(), cols["trunk_x"].max(), cols["trunk_y"].max()]
    for wkb, x, y in zip(table.column("geometry").to_pylist(), cols["trunk_x"], cols["trunk_y"]):
        assert struct.unpack("<BIdd", wkb) == (1, 1, x, y)
    back, _ = read_trees_parquet(tmp_path / "trees.parquet")
    for name, values in cols.items():
        assert back[name].dtype == values.dtype and np.array_equal(back[name], values)


def test_trees_geoparquet_empty(tmp_path):
    write_trees_parquet(tmp_path / "t.parquet", _tree_columns(0, np.random.default_rng(0)), crs_wkt=None)
    assert pq.read_table(tmp_path / "t.parquet").num_rows == 0


_float = st.floats(allow_nan=False, allow_infinity=False, width=64, min_value=-1e7, max_value=1e7)


@settings(max_examples=25, deadline=None)
@given(
    k=st.integers(0, 30),
    seed=st.integers(0, 2**32 - 1),
    xs=hnp.arrays(np.float64, 30, elements=_float),
)
def test_trees_parquet_round_trip_property(tmp_path_factory, k, seed, xs):
    path = tmp_path_factory.mktemp("trees") / "trees.parquet"
    cols = _tree_columns(k, np.random.default_rng(seed))
    cols["trunk_x"] = xs[:k]
    write_trees_parquet(path, cols, crs_wkt=None)
    back, geo = read_trees_parquet(path)
    for name, values in cols.items():
        assert np.array_equal(back[name], values)
    wkb = pq.read_table(path).column("geometry").to_pylist()
    assert [struct.unpack("<BIdd", w)[2:] for w in wkb] == list(zip(cols["trunk_x"], cols["trunk_y"]))


@settings(max_examples=25, deadline=None)
@given(
    sizes=st.lists(st.integers(0, 200), min_size=1, max_size=5),
    seed=st.integers(0, 2**32 - 1),
    scores=st.lists(st.floats(width=32, allow_nan=False), min_size=1, max_size=5),
)
def test_points_parquet_round_trip_property(tmp_path_factory, sizes, seed, scores):
    path = tmp_path_factory.mktemp("points") / "points.parquet"
    rng = np.random.default_rng(seed)
    parts = []
    with PointsParquetWriter(path, row_group_size=64) as w:
        for i, m in enumerate(sizes):
            part = (
                rng.integers(0, 2**64 - 1, m, dtype=np.uint64, endpoint=True),
                rng.integers(-(2**63), 2**63 - 1, m, dtype=np.int64),
                rng.random(m) < 0.5,
                rng.random(m) < 0.5,
                np.full(m, scores[i % len(scores)], dtype=np.float32),
            )
            w.write(*part)
            parts.append(part)
    table = pq.read_table(path)
    assert table.schema.names == ["point_index", "tree_id", "is_ground", "is_wood", "wood_score"]
    for j, name in enumerate(table.schema.names):
        expect = np.concatenate([p[j] for p in parts])
        got = table.column(name).to_numpy()
        assert got.dtype == expect.dtype and np.array_equal(got, expect)


def test_points_writer_aborts_cleanly(tmp_path):
    with pytest.raises(ValueError):
        with PointsParquetWriter(tmp_path / "points.parquet") as w:
            w.write([1], [1], [True], [False], [0.5])
            raise ValueError("stop")
    assert list(tmp_path.iterdir()) == []


def test_points_parquet_stores_the_point_index_delta_encoded(tmp_path):
    path = tmp_path / "points.parquet"
    n = 100_000
    with PointsParquetWriter(path) as w:
        w.write(np.arange(n), np.zeros(n, np.int64), np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, np.float32))
    column = pq.ParquetFile(path).metadata.row_group(0).column(0)
    assert column.path_in_schema == "point_index" and "DELTA_BINARY_PACKED" in column.encodings
    assert column.total_compressed_size < n // 10  # a counter costs next to nothing, not 8 bytes a row
