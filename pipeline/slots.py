"""Open planting slots, and the replants let in on them: the row model as a prior.

A replant, a young tree planted into a gap of an old row, stands a third to half as
tall as its neighbours, below the height that tells a tree from a post, a bin or
foliage touching the ground (``min_tree_height``). A trunk-like contact group that
stands on an open slot (an empty slot between two trees of a row, or the slot beyond a
row's end), is tall enough to be a nursery tree and passes the tests of a trunk but its
height, is a tree. This runs in each tile on the rows of the tile's trunks; a tile sees
the rows around each of its trunks far enough for a replant's two neighbours.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.params import PipelineParams, RowParams
from pipeline.rows import RowLayout, find_rows
from pipeline.trunks import TrunkDetection

#: a nursery tree planted into a gap stands at least this tall [m]; grass and weeds stay lower
MIN_REPLANT_HEIGHT = 0.7
#: a replant stands within this fraction of the in-row spacing of its slot's centre
SLOT_REACH = 0.2
#: contact nodes within this distance [m] of a replant's centre seed it in segmentation
SOURCE_RADIUS = 0.2


#: a row is evidence of a planting lattice from this many trees on (two trees with a gap
#: between them are as likely two trees of an irregular stand)
MIN_LATTICE_TREES = 4


def open_slots(layout: RowLayout) -> np.ndarray:
    """(o, 2) float64 centres [m] of the slots a tree could still stand in, in rows of at
    least :data:`MIN_LATTICE_TREES` trees: the empty slots between two trees of the row,
    and the slot beyond each of its ends."""
    long = layout.rows["n_trees"] >= MIN_LATTICE_TREES
    in_long = np.isin(layout.gaps["row"], layout.rows["row"][long])
    pts = [np.c_[layout.gaps["x"][in_long], layout.gaps["y"][in_long]]]
    # a row's line runs through its trees (a canopy row's, without trees, is no lattice)
    for line, s, is_long in zip(layout.lines, layout.rows["spacing_m"], long):
        if is_long and np.isfinite(s):
            for end, inner in ((line[-1], line[-3]), (line[0], line[2])):
                step = end - inner
                pts.append((end + s * step / np.hypot(*step))[None, :])
    return np.concatenate(pts).reshape(-1, 2)


def on_open_slot(tree_xy: np.ndarray, cand_xy: np.ndarray, *, params: RowParams | None = None,
                 reach: float = 0.2) -> np.ndarray:
    """Which open slot (:func:`open_slots`) of the rows of ``tree_xy`` each candidate
    stands on: a candidate there is more likely a tree (a replant, a thin trunk) than
    one elsewhere.

    Parameters
    ----------
    tree_xy : (k, 2) float64
        Trunks accepted so far [m].
    cand_xy : (c, 2) float64
        Candidates [m].
    params : RowParams, optional
    reach : float
        A candidate stands on a slot within this fraction of the block's spacing.

    Returns
    -------
    (c,) int64 index of the open slot, -1 where none (or fewer than three trees).
    """
    cand_xy = np.asarray(cand_xy, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(cand_xy), -1, dtype=np.int64)
    tree_xy = np.asarray(tree_xy, dtype=np.float64).reshape(-1, 2)
    if len(cand_xy) == 0 or len(tree_xy) < 3:
        return out
    lay = find_rows(tree_xy, params=params or RowParams())
    slots = open_slots(lay)
    spacing = np.nanmedian(lay.rows["spacing_m"]) if np.isfinite(lay.rows["spacing_m"]).any() else np.nan
    if not len(slots) or not np.isfinite(spacing):
        return out
    d, j = cKDTree(slots).query(cand_xy)
    return np.where(d <= reach * spacing, j, -1)


def rescue_on_open_slots(
    det: TrunkDetection,
    nodes: np.ndarray,
    node_height: np.ndarray,
    *,
    contact_top: float,
    params: PipelineParams,
) -> TrunkDetection:
    """Add the replants among the rejected contact groups to a detection.

    Parameters
    ----------
    det : TrunkDetection
        With ``candidates`` (every contact group's measurements).
    nodes : (m, 3) float64
        Node positions [m].
    node_height : (m,) float64
        Height of each node above the ground [m].
    contact_top : float
        Nodes below this height [m] are ground contacts.
    params : PipelineParams

    Returns
    -------
    TrunkDetection
        The detection with the replants appended (trunks ``k..``), marked in ``young`` (a
        replant is exempt from the height test after segmentation); ``det`` itself when
        there is none.
    """
    cand = det.candidates
    if not params.rows.enabled or cand is None or det.k < 3 or not len(cand["x"]):
        return det
    tp = params.trunks
    rejected = ~np.asarray(cand["accepted"], bool)
    low = (
        rejected
        & (cand["top"] >= MIN_REPLANT_HEIGHT)
        & (cand["top"] < tp.min_tree_height)
        & (cand["planar"] <= tp.max_planar_fraction)
        & (cand["width"] <= tp.max_trunk_width)
    )
    idx = np.flatnonzero(low)
    if not idx.size:
        return det
    cxy = np.c_[cand["x"], cand["y"]][idx]
    slot = on_open_slot(det.xy, cxy, params=params.rows, reach=SLOT_REACH)
    on = slot >= 0
    idx, cxy, slot = idx[on], cxy[on], slot[on]
    if not idx.size:
        return det
    # one replant per slot: the group with the most material
    order = np.lexsort((-cand["support"][idx], slot))
    first = np.r_[True, np.diff(slot[order]) != 0]
    pick = order[first]
    idx, cxy = idx[pick], cxy[pick]
    contact = np.flatnonzero(node_height < contact_top)
    if not contact.size:
        return det
    tree = cKDTree(nodes[contact, :2])
    src, src_t, keep = [], [], []
    for j, c in enumerate(cxy):
        near = tree.query_ball_point(c, SOURCE_RADIUS)
        if not near:
            d, n = tree.query(c)
            near = [n] if d <= 2 * SOURCE_RADIUS else []
        if near:
            src.append(contact[np.asarray(near, dtype=np.int64)])
            src_t.append(np.full(len(near), det.k + len(keep), dtype=np.int64))
            keep.append(j)
    if not keep:
        return det
    keep = np.asarray(keep)
    idx, cxy = idx[keep], cxy[keep]
    nodes_new = np.concatenate(src)
    trunk_new = np.concatenate(src_t)
    taken = np.isin(nodes_new, det.source_nodes)  # a node seeds one trunk
    out = TrunkDetection(
        np.r_[det.xy, cxy],
        np.r_[det.support, cand["support"][idx]],
        np.r_[det.width, cand["width"][idx]],
        np.r_[det.source_nodes, nodes_new[~taken]],
        np.r_[det.source_trunk, trunk_new[~taken]],
        det.candidates,
        det.spacing,
        np.r_[np.zeros(det.k, bool) if det.young is None else det.young, np.ones(len(cxy), bool)],
    )
    return out
