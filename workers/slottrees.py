"""Trees on open planting slots in a tiled job, decided on the whole block's rows.

A tile's own rows end at its buffer, and a decision on them may differ from the untiled
one near its edges (:mod:`pipeline.slots`). So each tile first decides on its own rows
and reports its core's evidence and the trees it let in; the job joins the evidence,
decides once for the block, and runs again only the tiles that let in other trees
within their buffered box than the block's decision gives them, with the block's trees.
A tile's summary records the trees it ran with: a resumed job runs again only the
tiles that differ.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.params import PipelineParams
from pipeline.slots import SAME_GROUP, trees_on_slots

#: the job record's and a tile summary's key for the trees on open slots (x, y in the
#: block's local frame [m], young)
SLOT_KEY = "slot_trees"


def block_slot_trees(summaries: list[dict], params: PipelineParams) -> np.ndarray:
    """(f, 3) float64: the trees on open slots the block's rows let in (x, y [m], local
    frame; young), from the tiles' ``slot_evidence`` (each tile reports its core's)."""
    ev = [s["slot_evidence"] for s in summaries if s.get("slot_evidence") is not None]
    if not ev:
        return np.zeros((0, 3))
    keys = ["trunks", "xy", "support", "full"] + (["trunk_support"] if all("trunk_support" in e for e in ev) else [])
    joined = {k: np.concatenate([e[k] for e in ev]) for k in keys}
    joined["trunks"] = joined["trunks"].reshape(-1, 2)
    joined["xy"] = joined["xy"].reshape(-1, 2)
    return trees_on_slots(joined, params=params.rows)


def trees_in_tile(trees, tile: dict, origin) -> np.ndarray:
    """The ``trees`` ((f, 3): x, y [m] local frame, young) inside a tile's buffered box
    (``tile``: its index entry, with ``buffered`` in the input CRS)."""
    trees = np.asarray(trees, dtype=np.float64).reshape(-1, 3)
    x0, y0, x1, y1 = np.asarray(tile["buffered"], dtype=np.float64) - np.r_[origin[:2], origin[:2]]
    inside = (x0 < trees[:, 0]) & (trees[:, 0] < x1) & (y0 < trees[:, 1]) & (trees[:, 1] < y1)
    return trees[inside]


def same_trees(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two sets of trees on open slots are the same trees: as many, each within
    SAME_GROUP of one of the other of the same kind (a tile places a contact group its
    neighbour also holds a few mm off)."""
    a, b = np.asarray(a, np.float64).reshape(-1, 3), np.asarray(b, np.float64).reshape(-1, 3)
    if len(a) != len(b):
        return False
    if not len(a):
        return True
    d, j = cKDTree(b[:, :2]).query(a[:, :2])
    return bool((d <= SAME_GROUP).all() and len(set(j.tolist())) == len(a) and (a[:, 2] == b[j, 2]).all())


def tiles_to_run_again(tiles: list[dict], summaries: list[dict], trees: np.ndarray, origin) -> list[dict]:
    """The tiles whose results were made with other trees on open slots than the block's
    ``trees`` give them (a tile without a summary is not listed: it has not run yet)."""
    done = {s["tile_id"]: s for s in summaries}
    again = []
    for t in tiles:
        s = done.get(t["id"])
        if s is not None and not same_trees(s.get(SLOT_KEY, np.zeros((0, 3))), trees_in_tile(trees, t, origin)):
            again.append(t)
    return again
