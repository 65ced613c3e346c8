"""The job page's map data: WKB shapes, footprints, rows and gaps, local coordinates, and
browser sessions' expiry (hand-checkable cases)."""

from __future__ import annotations

import json
import struct

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from hypothesis import given, settings
from hypothesis import strategies as st

from service.reports.mapdata import build_map_data, footprints, parse_wkb, to_json
from service.sessions import SESSION_SECONDS, SessionStore


def _wkb(kind: int, body: bytes, order: str = "<") -> bytes:
    return (b"\x01" if order == "<" else b"\x00") + struct.pack(order + "I", kind) + body


def test_wkb_point_line_polygon_and_big_endian():
    assert parse_wkb(_wkb(1, struct.pack("<dd", 3.0, 4.0))) == [[3.0, 4.0]]
    line = _wkb(2, struct.pack("<I", 3) + struct.pack("<6d", 0, 0, 1, 0, 2, 1))
    assert parse_wkb(line) == [[0, 0, 1, 0, 2, 1]]
    ring = struct.pack(">I", 4) + struct.pack(">8d", 0, 0, 2, 0, 2, 2, 0, 0)
    assert parse_wkb(_wkb(3, struct.pack(">I", 1) + ring, ">")) == [[0, 0, 2, 0, 2, 2, 0, 0]]
    point_z = _wkb(1001, struct.pack("<ddd", 1.0, 2.0, 9.0))  # ISO 3D: z dropped
    assert parse_wkb(point_z) == [[1.0, 2.0]]
    assert parse_wkb(b"\x01\x02") == []  # cut off: nothing, not an exception


def test_footprint_is_the_hull_of_each_trees_points():
    square = np.array([[0, 0], [2, 0], [2, 2], [0, 2], [1, 1], [0.5, 1.5]], float)
    xy = np.vstack([square, square + [10, 0], [[5, 5], [6, 6]]])
    ids = np.array([1] * 6 + [2] * 6 + [3, 3])
    out = footprints(xy, ids, np.array([2, 1, 3, 4]))
    hull1 = np.array(out[1]).reshape(-1, 2)
    assert sorted(map(tuple, hull1)) == [(0, 0), (0, 2), (2, 0), (2, 2)]  # inner points dropped
    assert sorted(map(tuple, np.array(out[0]).reshape(-1, 2))) == [(10, 0), (10, 2), (12, 0), (12, 2)]
    assert out[2] is None and out[3] is None  # two points; no points


@given(st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50)), min_size=3, max_size=40))
@settings(max_examples=40, deadline=None)
def test_every_point_lies_inside_its_footprint(pts):
    xy = np.array(pts, float)
    hull = footprints(xy, np.ones(len(xy), int), np.array([1]))[0]
    if hull is None:  # collinear: no area
        return
    h = np.array(hull).reshape(-1, 2)
    edges = np.roll(h, -1, axis=0) - h
    cross = edges[:, 0, None] * (xy[None, :, 1] - h[:, 1, None]) - edges[:, 1, None] * (xy[None, :, 0] - h[:, 0, None])
    # counter-clockwise hull: no point right of any edge (up to the 1 cm rounding)
    assert (cross >= -0.02 * np.hypot(*edges.T)[:, None] * 2).all()


def _trees(path, n=3, **extra):
    cols = {
        "tree_id": pa.array(np.arange(1, n + 1), pa.int64()),
        "trunk_x": 500010.25 + np.arange(n) * 4.0,
        "trunk_y": np.full(n, 6000020.5),
        "height_m": np.array([3.0, np.nan, 4.0][:n]),
        "young": pa.array([False, True, False][:n]),
        **extra,
        "geometry": pa.array([b"\x01"] * n),
    }
    pq.write_table(pa.table(cols), path)
    return path


def test_map_data_in_local_metres_with_rows_and_gaps(tmp_path):
    trees = _trees(tmp_path / "trees.parquet", row=pa.array([1, 1, 1]), position=pa.array([1, 2, 4]))
    line = _wkb(2, struct.pack("<I", 2) + struct.pack("<4d", 500010.25, 6000020.5, 500022.25, 6000020.5))
    pq.write_table(pa.table({"row": [1], "n_trees": [3], "geometry": [line]}), tmp_path / "rows.parquet")
    slot = _wkb(1, struct.pack("<dd", 500022.25, 6000020.5))
    pq.write_table(pa.table({"row": [1], "position": [3], "x": [500022.25], "y": [6000020.5], "geometry": [slot]}),
                   tmp_path / "gaps.parquet")
    d = build_map_data(trees)
    assert d["origin"] == [500010.0, 6000020.0] and d["n_trees"] == 3
    assert d["x"] == [0.25, 4.25, 8.25] and d["y"] == [0.5, 0.5, 0.5]
    assert d["columns"]["height_m"] == [3.0, None, 4.0]  # NaN: not measured
    assert d["columns"]["young"] == [0, 1, 0] and "geometry" not in d["columns"]
    assert d["outlines"] is None  # no points: the page draws circles
    assert d["rows"] == [{"row": 1, "n_trees": 3, "line": [0.25, 0.5, 12.25, 0.5]}]
    assert d["gaps"] == [{"row": 1, "position": 3, "x": 12.25, "y": 0.5}]
    text = to_json(d)
    assert json.loads(text) == d and "NaN" not in text


def test_map_data_without_rows_or_gaps(tmp_path):
    d = build_map_data(_trees(tmp_path / "trees.parquet", n=2))
    assert d["rows"] is None and d["gaps"] is None and "row" not in d["columns"]


def test_json_for_a_script_element_has_no_markup():
    text = to_json({"title": "</script><!-- <script>"})
    assert "<" not in text and json.loads(text)["title"] == "</script><!-- <script>"


def test_a_session_expires_and_ends_at_sign_out(tmp_path):
    store = SessionStore(tmp_path / "sessions.sqlite")
    try:
        sid, sess = store.open("hash-of-token", now=1000.0)
        assert store.get(sid, now=1000.0 + SESSION_SECONDS - 1) == sess
        assert store.get(sid, now=1000.0 + SESSION_SECONDS) is None  # expired
        assert store.get(sid + "x", now=1001.0) is None  # unknown
        store.close_session(sid)
        assert store.get(sid, now=1001.0) is None  # signed out
        raw = (tmp_path / "sessions.sqlite").read_bytes()
        assert sid.encode() not in raw  # only its hash is kept
    finally:
        store.close()
