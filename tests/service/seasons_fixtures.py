"""Outputs of captures of one orchard block, made by hand with the columns a capture job
writes (issue #55's contract between the pipeline and the service: the change columns of
``trees.parquet``, ``tree_key``/``since`` in ``gaps.parquet``, ``history.parquet`` and the
``orchard:capture`` record), for the tests of the service's routes and pages, which do
not run the pipeline.

The block has two rows of trees 4 m apart along y = 0 and y = 5 (input CRS, offset by
``X0``/``Y0``). Capture 1 (``c1``, 2026-04-01): keys 1–7, all new (row 1 trees 1–4,
row 2 trees 1, 2 and 4: its tree 3 is an empty slot). Capture 2 (``c2``, 2026-07-01):
row 1 grew 0.30 m, row 2 0.05 m (it lags); key 3 (row 1 tree 3) is gone, key 8 is new
at row 2 tree 5 and key 9 a replanting in row 2's empty slot.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.parquet import write_gaps_parquet, write_trees_parquet

X0, Y0 = 500_000.0, 4_200_000.0
DATES = {"c1": "2026-04-01", "c2": "2026-07-01"}
GROWTH = {1: 0.30, 2: 0.05}  # height change per row in capture 2 [m]


def _first() -> list[dict]:
    trees = []
    key = 0
    for row in (1, 2):
        for pos in (1, 2, 3, 4):
            if row == 2 and pos == 3:
                continue  # an empty slot
            key += 1
            trees.append({"tree_key": key, "row": row, "position": pos, "height_m": 2.0 + 0.1 * key,
                          "crown_volume_m3": 3.0 + 0.2 * key, "trunk_diameter_m": 0.08 + 0.002 * key, "status": "new"})
    return trees


def captures() -> dict[str, dict]:
    """The two captures: ``{"c1": {...}, "c2": {...}}``, each with its ``trees`` (dicts),
    ``gaps`` (dicts), ``history`` (dicts) and ``record``."""
    first = _first()
    # capture 1: 7 trees (keys 1..7), row 2 tree 3 an empty slot
    c1_gaps = [{"row": 2, "position": 3, "tree_key": None, "since": None}]
    c1_hist = [{"capture": "c1", "captured_at": DATES["c1"], **{k: t[k] for k in ("tree_key", "row", "position", "height_m",
                "crown_volume_m3", "trunk_diameter_m", "status")}} for t in first]
    c1 = {"trees": [{**t, "height_change_m": None, "crown_volume_change_m3": None, "trunk_diameter_change_m": None,
                     "days_since_previous": None} for t in first], "gaps": c1_gaps, "history": c1_hist,
          "record": {"capture_id": "c1", "captured_at": DATES["c1"], "captured_at_source": "file", "previous_capture_id": None,
                     "registration": None, "counts": {"same": 0, "new": 7, "replanted": 0, "removed": 0}, "next_tree_key": 8}}
    # capture 2: key 3 gone, 8 new at row 2 tree 5, 9 replanted in row 2's empty slot
    c2_trees = []
    for t in first:
        if t["tree_key"] == 3:
            continue
        g = GROWTH[t["row"]]
        c2_trees.append({**t, "status": "same", "height_m": t["height_m"] + g, "crown_volume_m3": t["crown_volume_m3"] * 1.08,
                         "trunk_diameter_m": t["trunk_diameter_m"] + 0.004, "height_change_m": g,
                         "crown_volume_change_m3": t["crown_volume_m3"] * 0.08, "trunk_diameter_change_m": 0.004,
                         "days_since_previous": 91.0})
    for key, pos, status in ((8, 5, "new"), (9, 3, "replanted")):
        c2_trees.append({"tree_key": key, "row": 2, "position": pos, "height_m": 1.2, "crown_volume_m3": 0.4,
                         "trunk_diameter_m": 0.03, "status": status, "height_change_m": None, "crown_volume_change_m3": None,
                         "trunk_diameter_change_m": None, "days_since_previous": None})
    c2_gaps = [{"row": 1, "position": 3, "tree_key": 3, "since": "c1"}]
    c2_hist = c1_hist + [{"capture": "c2", "captured_at": DATES["c2"], **{k: t[k] for k in ("tree_key", "row", "position",
                          "height_m", "crown_volume_m3", "trunk_diameter_m", "status")}} for t in c2_trees]
    c2_hist.append({"capture": "c2", "captured_at": DATES["c2"], "tree_key": 3, "row": 1, "position": 3, "height_m": None,
                    "crown_volume_m3": None, "trunk_diameter_m": None, "status": "removed"})
    c2 = {"trees": c2_trees, "gaps": c2_gaps, "history": c2_hist,
          "record": {"capture_id": "c2", "captured_at": DATES["c2"], "captured_at_source": "file", "previous_capture_id": "c1",
                     "registration": {"dx": 1.2, "dy": -0.4, "rotation_deg": 0.8, "residual_m": 0.021, "n_matched": 6},
                     "counts": {"same": 6, "new": 1, "replanted": 1, "removed": 1}, "next_tree_key": 10}}
    return {"c1": c1, "c2": c2}


def _xy(row: int, pos: int) -> tuple[float, float]:
    return X0 + 4.0 * pos, Y0 + 5.0 * (row - 1)


def write_capture_outputs(out_dir: Path, which: str, *, with_history: bool = True) -> Path:
    """Write ``trees.parquet`` (its ``orchard:capture`` metadata too), ``gaps.parquet``
    and (``with_history``) ``history.parquet`` of capture ``which`` into ``out_dir``."""
    cap = captures()[which]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    trees = cap["trees"]
    xy = np.array([_xy(t["row"], t["position"]) for t in trees])
    cols: dict[str, np.ndarray] = {
        "tree_id": np.arange(1, len(trees) + 1, dtype=np.int64),
        "trunk_x": xy[:, 0], "trunk_y": xy[:, 1], "trunk_z": np.full(len(trees), 100.0),
        "height_m": np.array([t["height_m"] for t in trees]),
        "crown_diameter_m": np.full(len(trees), 2.0),
        "crown_volume_m3": np.array([t["crown_volume_m3"] for t in trees]),
        "trunk_diameter_m": np.array([t["trunk_diameter_m"] for t in trees]),
        "n_points": np.full(len(trees), 500, dtype=np.int64),
        "row": np.array([t["row"] for t in trees], dtype=np.int32),
        "position": np.array([t["position"] for t in trees], dtype=np.int32),
    }
    if with_history:
        cols["tree_key"] = np.array([t["tree_key"] for t in trees], dtype=np.int64)
        cols["status"] = np.array([t["status"] for t in trees])
        for name in ("height_change_m", "crown_volume_change_m3", "trunk_diameter_change_m", "days_since_previous"):
            cols[name] = np.array([np.nan if t[name] is None else t[name] for t in trees], dtype=np.float64)
    meta = {"orchard:capture": json.dumps(cap["record"])} if with_history else None
    write_trees_parquet(out / "trees.parquet", cols, crs_wkt=None, metadata=meta)
    gxy = np.array([_xy(g["row"], g["position"]) for g in cap["gaps"]])
    gaps = {"row": np.array([g["row"] for g in cap["gaps"]], dtype=np.int32),
            "position": np.array([g["position"] for g in cap["gaps"]], dtype=np.int32),
            "x": gxy[:, 0], "y": gxy[:, 1]}
    if with_history:
        gaps["tree_key"] = np.array([g["tree_key"] for g in cap["gaps"]], dtype=object)  # null: no removed tree
        gaps["since"] = np.array([g["since"] for g in cap["gaps"]], dtype=object)
    write_gaps_parquet(out / "gaps.parquet", gaps, crs_wkt=None)
    if with_history:
        hist = cap["history"]
        table = pa.table({
            "tree_key": pa.array([h["tree_key"] for h in hist], pa.int64()),
            "capture": pa.array([h["capture"] for h in hist], pa.string()),
            "captured_at": pa.array([h["captured_at"] for h in hist], pa.string()),
            "row": pa.array([h["row"] for h in hist], pa.int32()),
            "position": pa.array([h["position"] for h in hist], pa.int32()),
            "height_m": pa.array([h["height_m"] for h in hist], pa.float64()),
            "crown_volume_m3": pa.array([h["crown_volume_m3"] for h in hist], pa.float64()),
            "trunk_diameter_m": pa.array([h["trunk_diameter_m"] for h in hist], pa.float64()),
            "status": pa.array([h["status"] for h in hist], pa.string()),
        })
        pq.write_table(table, str(out / "history.parquet"))
    return out
