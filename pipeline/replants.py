"""Replants: young trees in a row's open slots, too low to pass as trees on their own.

A tree planted into a gap of an old row stands a third to half as tall as its
neighbours, below the height that tells a tree from a post, a bin or foliage touching
the ground (``min_tree_height``). The row model is the prior that lets it in: a
trunk-like contact group that stands on an open planting slot (an empty slot between two
trees of a row, or the slot beyond a row's end) is a tree when it is tall enough to be a
nursery tree and passes the tests of a trunk but its height.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.params import PipelineParams
from pipeline.rows import on_open_slot
from pipeline.trunks import TrunkDetection

#: a nursery tree planted into a gap stands at least this tall [m]; grass and weeds stay lower
MIN_REPLANT_HEIGHT = 0.7
#: a replant stands within this fraction of the in-row spacing of its slot's centre
SLOT_REACH = 0.2
#: contact nodes within this distance [m] of a replant's centre seed it in segmentation
SOURCE_RADIUS = 0.2


def rescue_replants(
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
        The detection with the replants appended (trunks ``k..``), marked in ``young``
        (a replant is exempt from the height test after segmentation); ``det`` itself
        when there is none.
    """
    cand = det.candidates
    if not params.rows.enabled or cand is None or det.k < 3 or not len(cand["x"]):
        return det
    tp = params.trunks
    low = (
        ~np.asarray(cand["accepted"], bool)
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
