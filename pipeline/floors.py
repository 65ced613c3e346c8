"""Size floors that follow the block: young and dormant blocks.

The mature trees' floors (a 2 m height, 150 canopy voxels) drop every newly planted
tree. A block's own trees set its floors instead: the contact groups that pass every
test at the lowest floors and *branch* (a post, a stake or a riser is one column; a
fence wire runs out at one height) give their median height and catchment, and a block
whose branching groups are as large as mature trees keeps the mature floors.
"""

from __future__ import annotations

import numpy as np

from pipeline.params import MATURE_FLOORS

#: a contact group below the mature trees' floors is a tree only if it branches: some of
#: its catchment above the grass (BRANCH_LOW [m]) lies between BRANCH_OFFSET and
#: BRANCH_REACH [m] of its centre (a stake or a post beside the stem does not), at least
#: BRANCH_LENGTH [m] of it in nodes, spread over BRANCH_EXTENT [m] of height (a fence's
#: wire runs out at one height: 0.00-0.08 m on generated blocks, young trees 0.06-1.3 m)
BRANCH_LOW = 0.3
BRANCH_OFFSET = 0.2
BRANCH_REACH = 0.8
BRANCH_LENGTH = 0.3
BRANCH_EXTENT = 0.1
#: ... and its low material is nearly free of box faces (a bin's corners branch out; the
#: low material of young trees on generated blocks is 0 % planar, the bin's groups 12-65 %)
BRANCH_MAX_PLANAR = 0.1
#: ... and drains at most this many times the canopy floor (4 times the median catchment
#: of the block's branching groups; young trees on generated blocks drain up to 2.2 times it)
BRANCH_MAX_SIZE = 16
#: floors from the block: the height floor is this share of the median height of the
#: block's branching contact groups, at least MIN_FLOOR_HEIGHT [m] (irrigation risers,
#: grass tufts) ...
FLOOR_HEIGHT_SHARE = 0.5
MIN_FLOOR_HEIGHT = 0.7
#: ... and the canopy floor this share of their median catchment, at least MIN_FLOOR_VOXELS
FLOOR_SIZE_SHARE = 0.25
MIN_FLOOR_VOXELS = 20
#: a block is one of young trees only while the flow of its branching groups passes the
#: contact band through a stem, not a curtain: their median cross-section (the trunk
#: width test's measure) at most YOUNG_MAX_WIDTH [m]. Young stems 0.18-0.21 m on generated
#: blocks, 0.31-0.32 m on the real young row; a cloud of random points 0.75-0.82 m
YOUNG_MAX_WIDTH = 0.5


def group_percentile(values: np.ndarray, group: np.ndarray, n_groups: int, q: float) -> np.ndarray:
    """q-th percentile (nearest rank) of ``values`` per group id in [0, n_groups); -inf if empty."""
    return group_percentiles(values, group, n_groups, (q,))[0]


def group_percentiles(values: np.ndarray, group: np.ndarray, n_groups: int, qs) -> np.ndarray:
    """:func:`group_percentile` at each of ``qs``, from one sort, (len(qs), n_groups)."""
    keep = group >= 0
    v, g = values[keep], group[keep]
    # by value, then by group in a stable sort: the order of np.lexsort((v, g)), from
    # two sorts several times faster (a quicksort of the floats, a radix sort of small
    # group ids). Values that compare equal are alike but for zeros' signs and NaNs'
    # payloads: with those a stable sort keeps them in their input order, as lexsort does.
    order = np.argsort(v, kind="stable" if (v == 0).any() or np.isnan(v).any() else None)
    by_group = g[order]
    if by_group.size and 0 <= int(by_group.min()) and int(by_group.max()) < 1 << 16:
        by_group = by_group.astype(np.uint16)
    order = order[np.argsort(by_group, kind="stable")]
    v, g = v[order], g[order]
    start = np.searchsorted(g, np.arange(n_groups))
    end = np.searchsorted(g, np.arange(n_groups), side="right")
    has = end > start
    out = np.full((len(qs), n_groups), -np.inf)
    for row, q in zip(out, qs):
        idx = start + np.floor((end - start - 1) * q / 100.0).astype(np.int64)
        row[has] = v[idx[has]]
    return out


def branches(nodes: np.ndarray, node_height: np.ndarray, node_group: np.ndarray, centre: np.ndarray,
              voxel_size: float, node_foot: np.ndarray | None = None) -> np.ndarray:
    """Groups whose catchment branches: at least BRANCH_LENGTH of nodes above BRANCH_LOW
    lie BRANCH_OFFSET to BRANCH_REACH [m] from the group's ``centre`` (g, 2), spread over at least
    BRANCH_EXTENT of height (10th to 90th percentile), and (given ``node_foot`` (m, 2), the
    ground contact each node drains to [m]) drain to the ground within BRANCH_OFFSET of
    the centre. A post, a stake or a riser is one column; a fence's wire runs out at one
    height; a second column beside one (a riser by a stake) stands on its own contact.
    Returns (g,) bool."""
    g = centre.shape[0]
    sel = np.flatnonzero((node_group >= 0) & (node_height >= BRANCH_LOW))
    grp = node_group[sel]
    r = np.hypot(*(nodes[sel, :2] - centre[grp]).T)
    out = (r > BRANCH_OFFSET) & (r <= BRANCH_REACH)
    if node_foot is not None:  # a branch drains down its stem
        out &= np.hypot(*(node_foot[sel] - centre[grp]).T) <= BRANCH_OFFSET
    sel, grp = sel[out], grp[out]
    many = np.bincount(grp, minlength=g) >= max(1, int(round(BRANCH_LENGTH / voxel_size)))
    hi, lo = group_percentiles(node_height[sel], grp, g, (90.0, 10.0))
    extent = np.zeros(g)
    extent[many] = hi[many] - lo[many]
    return extent >= BRANCH_EXTENT


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value below and above which half of the ``weights`` lie."""
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])


def block_floors(top: np.ndarray, support: np.ndarray, ok: np.ndarray,
                 width: np.ndarray | None = None) -> tuple[float | None, int | None]:
    """The size floors a block's trees ask for, from the contact groups ``ok`` that
    branch and pass every test of their own at the lowest floors: FLOOR_HEIGHT_SHARE of
    their median ``top`` [m] and FLOOR_SIZE_SHARE of their median ``support`` [voxels],
    each between its least value and the mature trees' floor (MATURE_FLOORS). (None,
    None) without such a group, where at least half of them reach both of the mature
    trees' floors (a block of grown trees), where weighted by
    the catchment their median height is and their median catchment is BRANCH_MAX_SIZE
    times the mature floor (a grown block with replants), or where the median of their
    flow cross-sections ``width`` [m] is over YOUNG_MAX_WIDTH (no stems: a cloud of
    random points): the mature trees' floors hold."""
    if not ok.any():
        return None, None
    height, size = MATURE_FLOORS["min_tree_height"], MATURE_FLOORS["min_canopy_voxels"]
    # the median group passes the mature trees' test, both floors at once: young trees
    # as tall as the height floor, their stakes and risers draining into them, pass each
    # floor alone at the median, and the mature floors would then drop half of them
    if np.median((top[ok] >= height) & (support[ok] >= size)):
        return None, None
    # or where most of the material drains into groups larger than any young tree: a grown
    # block with replants, whose many crown fragments and replants drain little (trellis
    # posts among young trees, with their wires, drain more than the trees but not that much)
    w = support[ok]
    if _weighted_median(top[ok], w) >= height and _weighted_median(support[ok], w) >= BRANCH_MAX_SIZE * size:
        return None, None
    if width is not None and np.median(width[ok]) > YOUNG_MAX_WIDTH:
        return None, None
    h = float(np.clip(FLOOR_HEIGHT_SHARE * np.median(top[ok]), MIN_FLOOR_HEIGHT, MATURE_FLOORS["min_tree_height"]))
    s = int(np.clip(round(FLOOR_SIZE_SHARE * np.median(support[ok])), MIN_FLOOR_VOXELS, MATURE_FLOORS["min_canopy_voxels"]))
    return h, s
