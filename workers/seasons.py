"""A capture of a block against the block's previous capture: read the previous output
folder's state, register, key and match the merged trees, and give the change columns,
the gaps' removed trees and the cumulative ``history.parquet`` that
:func:`workers.outputs.write_outputs` writes with the other outputs as one set.

Every job runs it: without a previous capture, keys are 1..K in ``tree_id`` order and
every tree is ``new``. The state a next capture needs travels in the output folder:
``trees.parquet`` (keys, addresses, sizes; its ``orchard:capture`` metadata with the
next unused key, and ``orchard:unseen``: the trees carried unseen), ``gaps.parquet``
and ``history.parquet``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline.coverage import Coverage
from pipeline.parquet import read_parquet_columns
from pipeline.registration import Registration, register, size_descriptors
from pipeline.treekeys import BlockState, KeyAssignment, Trees, assign_keys, change, days_between, first_keys
from workers.captures import CAPTURE_KEY, Capture, capture_record  # noqa: F401 - capture_record: the contract's name

#: trees.parquet metadata: the trees carried unseen (JSON)
UNSEEN_KEY = "orchard:unseen"
#: the change columns of trees.parquet (null where there is no previous value)
CHANGE_COLUMNS = ("height_change_m", "crown_volume_change_m3", "trunk_diameter_change_m", "days_since_previous")
HISTORY_COLUMNS = ("tree_key", "capture", "captured_at", "row", "position", "height_m", "crown_volume_m3",
                   "trunk_diameter_m", "status")


@dataclass
class SeasonOutputs:
    """What a capture adds to a job's outputs."""

    trees: dict  # the trees table with tree_key, status, the change columns (and block addresses)
    layout: object  # the row layout with the gaps' tree_key / since and rows in the block's numbering
    history: dict  # history.parquet's columns
    metadata: dict  # trees.parquet's extra metadata (orchard:capture, orchard:unseen)
    registration: Registration | None
    seconds: float  # reading the previous folder, registration, matching, keys and history (not writing)


def read_state(previous: str) -> tuple[BlockState, dict]:
    """The block's state and history as the capture in ``previous`` left them.

    Raises InputError (a file of the folder is not readable).
    """
    folder = Path(previous)
    what = f"the previous capture's trees.parquet ({folder})"
    cols, meta = read_parquet_columns(folder / "trees.parquet", what=what)
    record = json.loads(meta.get(CAPTURE_KEY.encode(), b"null") or b"null") or {}
    n = len(cols["trunk_x"])
    key = np.asarray(cols["tree_key"], np.int64) if "tree_key" in cols else np.arange(1, n + 1, dtype=np.int64)
    cid = record.get("capture_id") or Path(meta.get(b"orchard:input", b"previous").decode()).stem
    day = record.get("captured_at") or datetime.fromtimestamp(
        os.path.getmtime(folder / "trees.parquet"), tz=timezone.utc).date().isoformat()
    zeros = np.zeros(n, np.int64)
    trees = Trees(np.c_[cols["trunk_x"], cols["trunk_y"]].astype(np.float64),
                  np.asarray(cols.get("row", zeros), np.int64), np.asarray(cols.get("position", zeros), np.int64),
                  np.asarray(cols["height_m"], np.float64), np.asarray(cols["crown_volume_m3"], np.float64),
                  np.asarray(cols["trunk_diameter_m"], np.float64))
    last_capture = np.full(n, cid, object)
    last_date = np.full(n, day, object)
    unseen = json.loads(meta.get(UNSEEN_KEY.encode(), b"[]") or b"[]")
    if unseen:
        u = {k: np.array([t[k] for t in unseen]) for k in unseen[0]}
        key = np.r_[key, u["tree_key"].astype(np.int64)]
        trees = Trees(np.r_[trees.xy, np.c_[u["x"], u["y"]].astype(np.float64)],
                      np.r_[trees.row, u["row"].astype(np.int64)], np.r_[trees.position, u["position"].astype(np.int64)],
                      np.r_[trees.height, u["height_m"].astype(float)], np.r_[trees.volume, u["crown_volume_m3"].astype(float)],
                      np.r_[trees.trunk, u["trunk_diameter_m"].astype(float)])
        last_capture = np.r_[last_capture, u["capture"].astype(object)]
        last_date = np.r_[last_date, u["captured_at"].astype(object)]
    empty = [np.zeros((0, 2), np.int64)]
    if (folder / "gaps.parquet").is_file():
        g, _ = read_parquet_columns(folder / "gaps.parquet", ["row", "position"], what=f"gaps.parquet of {folder}")
        empty.append(np.c_[g["row"], g["position"]].astype(np.int64))
    if (folder / "history.parquet").is_file():
        history, _ = read_parquet_columns(folder / "history.parquet", what=f"history.parquet of {folder}")
        gone = history["status"] == "removed"
        empty.append(np.c_[history["row"][gone], history["position"][gone]].astype(np.int64))
    else:  # an output folder of a release before keys: its trees are the block's first capture
        history = _history_rows(key[:n], cid, day, trees.row[:n], trees.position[:n], trees.height[:n],
                                trees.volume[:n], trees.trunk[:n], np.full(n, "new", object))
    next_key = int(record.get("next_tree_key") or (int(key.max(initial=0)) + 1))
    state = BlockState(cid, day, key, trees, last_capture, last_date, np.concatenate(empty), next_key)
    return state, history


def _history_rows(key, capture, day, row, position, height, volume, trunk, status) -> dict:
    k = len(key)
    return {"tree_key": np.asarray(key, np.int64), "capture": np.full(k, capture, object),
            "captured_at": np.full(k, day, object), "row": np.asarray(row, np.int32),
            "position": np.asarray(position, np.int32), "height_m": np.asarray(height, np.float64),
            "crown_volume_m3": np.asarray(volume, np.float64), "trunk_diameter_m": np.asarray(trunk, np.float64),
            "status": np.asarray(status, object)}


def _concat(parts: list[dict]) -> dict:
    parts = [p for p in parts if p is not None]
    return {c: np.concatenate([np.asarray(p[c]) for p in parts]).astype(parts[-1][c].dtype) for c in HISTORY_COLUMNS}


def current_trees(trees: dict) -> Trees:
    """The capture's trees (the merged trees table) as :class:`pipeline.treekeys.Trees`."""
    n = len(trees["trunk_x"])
    zeros = np.zeros(n, np.int64)
    return Trees(np.c_[trees["trunk_x"], trees["trunk_y"]].astype(np.float64),
                 np.asarray(trees.get("row", zeros), np.int64), np.asarray(trees.get("position", zeros), np.int64),
                 np.asarray(trees["height_m"], np.float64), np.asarray(trees["crown_volume_m3"], np.float64),
                 np.asarray(trees["trunk_diameter_m"], np.float64))


def season(trees: dict, layout, cells: np.ndarray | None, capture: Capture,
           stems: np.ndarray | None = None) -> SeasonOutputs:
    """The capture's keys, statuses, change, gaps and history against its previous capture.

    Parameters
    ----------
    trees : dict — the merged trees table (input CRS)
    layout : pipeline.rows.RowLayout or None
    cells : (c, 2) int64 or None — the 1 m cells the capture's points fall in (None: unknown, all covered)
    capture : Capture
    stems : (c, 2) float64, optional — centres of the capture's stem cells (input CRS,
        :func:`pipeline.coverage.stem_cells`): a previous tree whose stem still stands was
        missed, not removed

    Raises
    ------
    NoOverlapError (the captures do not overlap), InputError (the previous folder is unreadable)
    """
    t0 = time.perf_counter()
    cur = current_trees(trees)
    history = None
    state = None
    if capture.previous is not None:
        state, history = read_state(capture.previous)
    reg = None
    if state is None:
        keys = first_keys(cur)
        covered_state = np.zeros(0, bool)
    else:
        coverage = Coverage.from_cells(cells) if cells is not None and len(cells) else None
        covered = None if coverage is None else coverage.covered
        reg = register(cur.xy, state.trees.xy,
                       cur_size=size_descriptors(cur.height, cur.volume, cur.trunk),
                       prev_size=size_descriptors(state.trees.height, state.trees.volume, state.trees.trunk),
                       covered=covered, names=(capture.capture_id, state.capture_id))
        back = reg.transform.inverse(state.trees.xy)  # the state's trees in this capture's frame
        covered_state = np.ones(len(back), bool) if covered is None else covered(back)
        covered_state &= ~standing(back, stems)
        keys = assign_keys(cur, state, transform=reg.transform, gate=reg.gate, covered=covered_state)
    out = dict(trees)
    out["tree_key"] = keys.key
    out["status"] = keys.status.astype(str)
    if "row" in trees:
        out["row"] = keys.row.astype(np.int32)
        out["position"] = keys.position.astype(np.int32)
    if state is None:
        for c in CHANGE_COLUMNS:
            out[c] = np.full(len(cur), np.nan)
    else:
        out["height_change_m"] = change(cur.height, state.trees.height, keys.prev)
        out["crown_volume_change_m3"] = change(cur.volume, state.trees.volume, keys.prev)
        out["trunk_diameter_change_m"] = change(cur.trunk, state.trees.trunk, keys.prev)
        out["days_since_previous"] = days_between(capture.captured_at, state.last_date, keys.prev)
    layout = _layout(layout, keys, state, reg)
    rows = _history_rows(keys.key, capture.capture_id, capture.captured_at, keys.row, keys.position, cur.height,
                         cur.volume, cur.trunk, keys.status)
    removed = None
    if state is not None:
        r = keys.removed
        nan = np.full(len(r), np.nan)
        removed = _history_rows(state.key[r], capture.capture_id, capture.captured_at, state.trees.row[r],
                                state.trees.position[r], nan, nan, nan, np.full(len(r), "removed", object))
        history = {c: v[history["capture"] != capture.capture_id] for c, v in history.items()}  # a capture run again
    seconds = time.perf_counter() - t0
    record = {
        "capture_id": capture.capture_id,
        "captured_at": capture.captured_at,
        "captured_at_source": capture.captured_at_source,
        "previous_capture_id": None if state is None else state.capture_id,
        "registration": None if reg is None else reg.record(),
        "counts": keys.counts(),
        "next_tree_key": int(keys.next_key),
    }
    metadata = {CAPTURE_KEY: json.dumps(record), UNSEEN_KEY: json.dumps(_unseen(state, keys, reg))}
    return SeasonOutputs(out, layout, _concat([history, rows, removed]), metadata, reg, seconds)


#: a previous tree with a stem cell this close to its trunk [m] still stands (no trunk
#: was found for it this time: merged with a neighbour, or hidden); a cut tree leaves at
#: most a stump, below the stems' band
STANDING_RADIUS = 0.2


def standing(xy: np.ndarray, stems: np.ndarray | None) -> np.ndarray:
    """(p,) bool: positions (input CRS) with a stem cell within :data:`STANDING_RADIUS`."""
    if stems is None or not len(stems) or not len(xy):
        return np.zeros(len(xy), bool)
    d, _ = cKDTree(stems).query(xy, distance_upper_bound=STANDING_RADIUS)
    return np.isfinite(d)


def _unseen(state: BlockState | None, keys: KeyAssignment, reg: Registration | None) -> list[dict]:
    """The state's trees this capture did not cover, carried (positions in this capture's frame)."""
    if state is None or not len(keys.unseen):
        return []
    u = keys.unseen
    xy = reg.transform.inverse(state.trees.xy[u])
    return [{"tree_key": int(state.key[k]), "x": float(x), "y": float(y), "row": int(state.trees.row[k]),
             "position": int(state.trees.position[k]), "height_m": _num(state.trees.height[k]),
             "crown_volume_m3": _num(state.trees.volume[k]), "trunk_diameter_m": _num(state.trees.trunk[k]),
             "capture": str(state.last_capture[k]), "captured_at": str(state.last_date[k])}
            for k, (x, y) in zip(u, xy)]


def _num(v) -> float | None:
    return float(v) if np.isfinite(v) else None


def _layout(layout, keys: KeyAssignment, state: BlockState | None, reg: Registration | None):
    """The row layout in the block's numbering, its gaps with the removed trees (``tree_key``, ``since``)."""
    if layout is None:
        return None
    gaps = layout.gaps
    row, position = keys.row_map.address(gaps["row"], gaps["position"])
    g = {"row": row, "position": position, "x": np.asarray(gaps["x"], np.float64), "y": np.asarray(gaps["y"], np.float64)}
    tree_key = np.zeros(len(row), np.int64)
    has_key = np.zeros(len(row), bool)
    since = np.full(len(row), None, object)
    if state is not None and len(keys.removed):
        r = keys.removed
        at = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(row, position))}
        xy = reg.transform.inverse(state.trees.xy[r])
        extra = []
        for k, (x, y) in zip(r, xy):
            addr = (int(state.trees.row[k]), int(state.trees.position[k]))
            i = at.get(addr) if addr[0] > 0 else None
            if i is not None and not has_key[i]:
                tree_key[i], has_key[i], since[i] = state.key[k], True, state.last_capture[k]
            else:
                extra.append((addr[0], addr[1], x, y, state.key[k], state.last_capture[k]))
        if extra:
            e = list(zip(*extra))
            g = {"row": np.r_[g["row"], e[0]], "position": np.r_[g["position"], e[1]], "x": np.r_[g["x"], e[2]],
                 "y": np.r_[g["y"], e[3]]}
            tree_key = np.r_[tree_key, np.asarray(e[4], np.int64)]
            has_key = np.r_[has_key, np.ones(len(extra), bool)]
            since = np.r_[since, np.asarray(e[5], object)]
    order = np.lexsort((g["position"], g["row"]))
    g = {k: v[order] for k, v in g.items()}
    g["row"], g["position"] = g["row"].astype(np.int32), g["position"].astype(np.int32)
    g["tree_key"] = np.ma.masked_array(tree_key[order], mask=~has_key[order])
    g["since"] = since[order]
    rows = dict(layout.rows)
    rows["row"] = keys.row_map.address(rows["row"], np.zeros(len(rows["row"]), np.int64))[0].astype(np.int32)
    return dataclasses.replace(layout, rows=rows, gaps=g)


def nullable(trees: dict) -> dict:
    """The trees table as written: the change columns' unknown values (NaN) are nulls."""
    return {k: np.ma.masked_invalid(np.asarray(v, np.float64)) if k in CHANGE_COLUMNS else v for k, v in trees.items()}
