"""Wood/leaf classification from shortest-path counts.

The paper's score is S = log(p) / log(p_max), p the number of shortest paths through a
node (from the trunk to every node) and p_max its maximum over the graph, thresholded
at a fixed value. Path counts are subtree sizes of the segmentation's shortest-path
forest, so they cost one linear sweep instead of one search per target.

Our method ("combined") normalises the score per tree rather than over the whole block,
averages it over a neighbourhood (a trunk wider than a voxel carries its paths down a
narrow "highway" and the smoothing spreads it over the whole stem), and combines it with
local shape (branches are linear, foliage is scattered) in a fixed logistic model.
Narrow trees (tall spindles, hedges: a crown radius under about a third of the tree's
height) carry a much smaller share of wood than open vase trees, so one threshold
cannot serve both: their nodes are scored by a second logistic model, fitted on narrow
forms, and the two scores are blended by the tree's width; the narrowest (tall
spindles) by a third, fitted on spindles alone. Range noise blurs branches into
scattered shells, so the wide model is corrected by a second set of weights grown with
the block's estimated ground noise, over the node features and the shortest paths'
topology (depth, reach and point flow, read off one depth-first order of the forest).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from pipeline.enrichment import ShapeFeatures
from pipeline.graph import subtree_sizes
from pipeline.metrics import group_runs
from pipeline.params import MatterParams
from pipeline.rowpasses import row_max, row_sums, sparse_product

#: names of the columns of :func:`wood_features`
FEATURES = (
    "bias",
    "s_tree",
    "s_tree_mean",
    "s_tree_max",
    "linearity",
    "scattering",
    "verticality",
    "rel_density",
    "height_frac",
    "radial_frac",
    "neighbours",
    "tree_width",
    "tree_height",
)
#: the node features; the last two columns describe the node's tree
NODE_FEATURES = len(FEATURES) - 2
#: names of the columns of :func:`noise_features`, read by the noise correction only:
#: the node's path length over its tree's longest, its longest path onwards over its
#: tree's longest, the path score of points (not nodes), and over two steps of the
#: neighbourhood (about 0.5 m) the score of the summed path counts and the largest path score
NOISE_FEATURES = ("path_depth", "reach", "point_flow", "wide_flow", "wide_path_max")

# Logistic model of the "combined" score, one weight per FEATURES column, fitted by
# `python -m bench.fit_matter --seeds 4` on generated orchards never used for evaluation
# (seeds 1000+); refit and paste when the features change. The matching threshold is
# params.COMBINED_THRESHOLD. The neighbours column plays no part in it nor in the
# narrow and spindle models (all fitted before it came in for the noise correction).
COMBINED_WEIGHTS = np.array([-4.523, 1.337, 3.206, 5.642, 1.075, -1.547, 0.281, 0.045, -0.813, -2.692, 0.0, 0.0, 0.0])
#: the wide trees' model's correction for range noise, one weight per node feature and
#: per NOISE_FEATURES column, times :func:`noise_term` of the block's estimated ground
#: noise and :func:`noise_gate` (``python -m bench.fit_matter --seeds 2 --models noisy``:
#: vase blocks at sigma 0-0.1 m and spacings 3-8 m, seeds 1000+, fitted with
#: COMBINED_WEIGHTS held): range noise blurs branches into scattered shells, so the
#: local shape weighs differently and the paths' topology tells more (regularised at
#: 1e-6: at 1e-3 the path columns stay near zero)
NOISE_WEIGHTS = np.array([
    -12.56, -3.831, -0.924, -7.968, 2.114, -6.762, 0.133, -0.126, 2.184, -1.848, 1.906,
    -5.529, 5.293, -1.561, 20.884, 2.535,
])
#: estimated ground noise [m] below which the correction is off: clean scans' estimates
#: (terrain roughness) stay under it, and the wide model was fitted there
NOISE_FLOOR = 0.02
#: ... the noise [m] over which it grows by one NOISE_WEIGHTS ...
NOISE_SCALE = 0.1
#: ... and the noise [m] above which it grows no more: the training blocks' estimates
#: reach 0.11 (sigma 0.1 m), and a scan without a ground plane (a lone real tree) reads
#: far higher
NOISE_MAX = 0.12
#: the correction is for orchard trees (the training vases reach 5.5 m) up to about this
#: height [m], blended over NARROW_HEIGHT_BLEND: tall forest trees keep the wide model
NOISE_MAX_HEIGHT = 8.0
#: ... and for trees at least about this wide (the training vases measure 0.32 and more):
#: hedges, scored partly by the wide model, lost wood F1 to it, and high density's and
#: hedges' clean scans read 0.04-0.047 m of ground noise ...
NOISE_MIN_WIDTH = 0.33
#: ... blended over about this width on either side
NOISE_WIDTH_BLEND = 0.02
#: weights of the narrow trees' model: one per node feature, then one per node feature
#: times the tree's width (``python -m bench.fit_matter --seeds 2
#: --models narrow``, seeds 1000+, the narrow forms only; its bias shifted so that
#: params.COMBINED_THRESHOLD is its best threshold)
NARROW_WEIGHTS = np.array([
    -8.204, 1.402, 6.934, 2.595, 1.594, 1.146, 0.762, -1.01, -4.646, -1.359, 0.0,
    3.176, 1.534, 2.634, 3.56, 1.872, 0.981, 2.499, 3.93, 0.113, 0.452, 0.0,
])
#: weights of the tall spindles' own model, over the narrow model's columns (``python -m
#: bench.fit_matter --seeds 2 --models spindle``, seeds 1000+, spindle blocks only; its
#: bias shifted likewise): the hedges' larger share of wood (9 % against 2 %) pulled the
#: shared model's boundary away from the spindles' own
SPINDLE_WEIGHTS = np.array([
    -4.848, 2.085, 1.152, 2.843, 2.215, -1.827, 1.347, -0.496, -6.051, -5.282, 0.0,
    -0.002, 0.340, 0.191, 0.413, 0.356, -0.282, 0.210, 0.041, -0.905, -0.770, 0.0,
])
#: a narrow tree narrower than this (spindles measure 0.12-0.18, hedges 0.20-0.27) is
#: scored by the spindles' model ...
SPINDLE_WIDTH = 0.19
#: ... blended over about this width on either side
SPINDLE_BLEND = 0.005
#: a tree narrower than this (90th percentile of its material's distance from the trunk
#: over its height) is scored by the narrow trees' model ...
NARROW_WIDTH = 0.3
#: ... blended over about this width on either side ...
NARROW_BLEND = 0.03
#: ... and only up to this height [m]: the model was fitted on trained orchard trees
#: 2.5-3.5 m tall and is not carried over to tall trees (a leafless 20 m tree is narrow
#: too, and nearly all wood) ...
NARROW_MAX_HEIGHT = 6.0
#: ... blended over about this height on either side [m]
NARROW_HEIGHT_BLEND = 0.5


def path_counts(pred: np.ndarray) -> np.ndarray:
    """Number of shortest paths through each node, (m,) float64 (>= 1)."""
    return subtree_sizes(pred)


def _group_max(values: np.ndarray, group: np.ndarray) -> np.ndarray:
    """The largest of ``values`` (m,) in each group id of ``group`` (m,), and at least 0:
    (max id + 1,) float64 indexed by the id (0 for an id with no value)."""
    top = np.zeros(int(group.max()) + 1 if group.size else 1)
    np.maximum.at(top, group, values)
    return top


def log_score(counts: np.ndarray, group: np.ndarray | None = None) -> np.ndarray:
    """S = log(p) / log(p_max), with p_max over the whole array or per ``group``.

    Parameters
    ----------
    counts : (m,) float64, >= 1
    group : (m,) int64, optional — normalise within each group id (e.g. tree)

    Returns
    -------
    (m,) float64 in [0, 1]
    """
    lp = np.log(np.maximum(counts, 1.0))
    if group is None:
        top = lp.max() if lp.size else 1.0
        return lp / top if top > 0 else np.zeros_like(lp)
    denom = _group_max(lp, group)[group]
    return np.where(denom > 0, lp / np.where(denom > 0, denom, 1.0), 0.0)


def smooth(values: np.ndarray, adjacency: sparse.csr_matrix) -> np.ndarray:
    """Mean of ``values`` over each node's neighbourhood (adjacency with diagonal)."""
    deg = row_sums(adjacency)
    return sparse_product(adjacency, values) / np.maximum(deg, 1.0)


def neighbourhood_max(values: np.ndarray, adjacency: sparse.csr_matrix) -> np.ndarray:
    """Maximum of non-negative ``values`` over each node's neighbourhood (0 for a node
    without neighbours), (m,) float64."""
    # one reduction over each row's run of neighbours: scipy's row max of a copy of the
    # matrix holding the values took twice the time and three times the memory (the same
    # maxima: the implicit zeros it counts in never exceed non-negative values)
    return row_max(adjacency, values)


def _per_group(values: np.ndarray, group: np.ndarray, fn) -> np.ndarray:
    order, uniq, start, counts = group_runs(group)
    out = np.zeros(int(group.max()) + 1 if group.size else 1)
    for u, a, c in zip(uniq, start, counts):
        out[u] = fn(values[order[a : a + c]])
    return out


def wood_features(
    counts: np.ndarray,
    node_tree: np.ndarray,
    trunk_xy: np.ndarray,
    nodes: np.ndarray,
    node_height: np.ndarray,
    points_per_node: np.ndarray,
    shape: ShapeFeatures,
    adjacency: sparse.csr_matrix,
) -> np.ndarray:
    """Feature matrix of the combined wood score, columns named in ``FEATURES``.

    Parameters
    ----------
    counts : (m,) float64 — shortest-path counts (subtree sizes)
    node_tree : (m,) int64 — 0 = no tree
    trunk_xy : (k, 2) float64 [m]
    nodes : (m, 3) float64 [m]
    node_height : (m,) float64 — height above ground [m]
    points_per_node : (m,) int64
    shape : ShapeFeatures
    adjacency : (m, m) neighbourhood matrix with diagonal

    Returns
    -------
    (m, len(FEATURES)) float64
    """
    m = counts.shape[0]
    s_tree = log_score(counts, node_tree)
    t = np.maximum(node_tree - 1, 0)
    has_tree = node_tree > 0
    radial = np.zeros(m)
    if trunk_xy.shape[0]:
        radial = np.where(has_tree, np.hypot(*(nodes[:, :2] - trunk_xy[t]).T), 0.0)
    top_h = _group_max(node_height, node_tree)
    top_r = _group_max(radial, node_tree)
    med_c = _per_group(points_per_node.astype(np.float64), node_tree, np.median) if m else np.ones(1)
    # the crown's reach by its 90th percentile: a few stray nodes do not widen a tree
    reach = _per_group(radial, node_tree, lambda v: np.percentile(v, 90)) if m else np.zeros(1)
    width = reach / np.maximum(top_h, 1e-9)
    return np.column_stack(
        [
            np.ones(m),
            s_tree,
            smooth(s_tree, adjacency),
            neighbourhood_max(s_tree, adjacency),
            smooth(shape.linearity, adjacency),
            smooth(shape.scattering, adjacency),
            shape.verticality,
            np.log(np.maximum(points_per_node, 1) / np.maximum(med_c[node_tree], 1.0)),
            np.clip(node_height / np.maximum(top_h[node_tree], 1e-9), 0.0, 1.0),
            np.clip(radial / np.maximum(top_r[node_tree], 1e-9), 0.0, 1.0),
            np.log1p(shape.neighbours),
            width[node_tree],
            top_h[node_tree],
        ]
    )


def preorder(pred: np.ndarray) -> np.ndarray:
    """Depth-first order of the forest given by ``pred``, (m,) int64: each node's
    subtree is the run of its subtree size (:func:`path_counts`) from its position.

    Parameters
    ----------
    pred : (m,) int64, -1 at roots (and unreached nodes)

    Returns
    -------
    (m,) int64 — a permutation of the nodes
    """
    # Strategy: one csgraph depth-first search over the forest's child edges. The roots
    # hang off a chain of virtual nodes rather than one virtual root: csgraph rescans a
    # node's children each time it returns to it, quadratic in a root of thousands.
    m = pred.shape[0]
    child = np.flatnonzero(pred >= 0)
    roots = np.flatnonzero(pred < 0)
    k = roots.size
    if m == 0:
        return np.zeros(0, np.int64)
    chain = m + np.arange(k)
    rows = np.r_[pred[child], chain, chain[:-1]]
    cols = np.r_[child, roots, chain[1:]]
    g = sparse.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(m + k, m + k))
    order = csgraph.depth_first_order(g, m, directed=True, return_predecessors=False)
    return order[order < m].astype(np.int64)


def _run_max(values: np.ndarray, start: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Maximum of ``values[start : start + length]`` for each run (length >= 1), (r,) float64.

    A sparse table built one level at a time (level j: the maximum over 2**j values from
    each position), each run answered at the level of its length's highest power of two
    by two overlapping windows: O(m log m) whole-array work, whatever the runs' lengths.
    """
    out = values[start].astype(np.float64)
    if start.size == 0:
        return out
    level_of = np.floor(np.log2(length)).astype(np.int64)
    level = values.astype(np.float64)
    for j in range(1, int(level_of.max()) + 1):
        span = 1 << (j - 1)
        level = np.maximum(level[:-span], level[span:])
        at = np.flatnonzero(level_of == j)
        out[at] = np.maximum(level[start[at]], level[start[at] + length[at] - (1 << j)])
    return out


def path_reach(pred: np.ndarray, dist: np.ndarray, counts: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
    """Longest path onwards from each node in the shortest-path forest [m], (m,) float64.

    Parameters
    ----------
    pred : (m,) int64 — the forest, -1 at roots
    dist : (m,) float64 — path length from the root [m], inf if unreached
    counts : (m,) float64 — subtree sizes of ``pred`` (:func:`path_counts`)
    order : (m,) int64, optional — :func:`preorder` of ``pred``

    Returns
    -------
    (m,) float64 — the farthest node of the node's subtree less the node's own path length
    """
    # a branch carries paths that go on for metres, a leaf's end at once
    order = preorder(pred) if order is None else order
    d = np.where(np.isfinite(dist), dist, 0.0)
    pos = np.empty_like(order)
    pos[order] = np.arange(order.size)
    return _run_max(d[order], pos, counts.astype(np.int64)) - d


def noise_features(
    counts: np.ndarray,
    node_tree: np.ndarray,
    pred: np.ndarray,
    dist: np.ndarray,
    points_per_node: np.ndarray,
    adjacency: sparse.csr_matrix,
) -> np.ndarray:
    """Columns of the noise correction beyond the node features, named in NOISE_FEATURES.

    Parameters
    ----------
    counts : (m,) float64 — shortest-path counts (subtree sizes of ``pred``)
    node_tree : (m,) int64 — 0 = no tree
    pred : (m,) int64 — the segmentation's shortest-path forest, -1 at roots
    dist : (m,) float64 — path length from the trunk [m], inf if unreached
    points_per_node : (m,) int64
    adjacency : (m, m) neighbourhood matrix with diagonal (of :func:`wood_features`)

    Returns
    -------
    (m, len(NOISE_FEATURES)) float64
    """
    # Strategy: the path topology holds under noise. One depth-first order of the
    # forest lays every subtree out as a run, so the points a node's paths carry are a
    # difference of running sums and its reach one run maximum each. A branch blurred
    # into a shell splits its paths among parallel nodes: summed over two steps of the
    # neighbourhood (two sparse products, not a wider neighbour search) they come
    # together again.
    order = preorder(pred)
    pos = np.empty_like(order)
    pos[order] = np.arange(order.size)
    size = counts.astype(np.int64)
    run_points = np.r_[0, np.cumsum(points_per_node[order].astype(np.int64))]
    flow = (run_points[pos + size] - run_points[pos]).astype(np.float64)
    d = np.where(np.isfinite(dist), dist, 0.0)
    reach = path_reach(pred, dist, counts, order)
    return np.column_stack(
        [
            d / np.maximum(_group_max(d, node_tree)[node_tree], 1e-9),
            reach / np.maximum(_group_max(reach, node_tree)[node_tree], 1e-9),
            log_score(flow, node_tree),
            log_score(sparse_product(adjacency, sparse_product(adjacency, counts)), node_tree),
            neighbourhood_max(neighbourhood_max(log_score(counts, node_tree), adjacency), adjacency),
        ]
    )


def _logistic(z: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(z, -50, 50)))  # clipped: no overflow in exp


def narrow_features(features: np.ndarray) -> np.ndarray:
    """The narrow trees' model's columns from :func:`wood_features`: the node's
    features and the same times the tree's width, (m, 2 * NODE_FEATURES)."""
    base, width = features[:, :NODE_FEATURES], features[:, NODE_FEATURES : NODE_FEATURES + 1]
    out = np.empty((features.shape[0], 2 * NODE_FEATURES))
    out[:, :NODE_FEATURES] = base
    np.multiply(base, width, out=out[:, NODE_FEATURES:])  # no (m, NODE_FEATURES) temporary
    return out


def _shorter_than(height: np.ndarray, limit: float) -> np.ndarray:
    """Trees under ``limit`` [m]: 1 well below it, 0 well above, blended over NARROW_HEIGHT_BLEND."""
    return _logistic((limit - height) / NARROW_HEIGHT_BLEND)


def narrowness(width: np.ndarray, height: np.ndarray) -> np.ndarray:
    """Weight of the narrow trees' model for trees of ``width`` and ``height`` [m], (m,) in [0, 1]."""
    return _logistic((NARROW_WIDTH - width) / NARROW_BLEND) * _shorter_than(height, NARROW_MAX_HEIGHT)


def noise_term(noise: float) -> float:
    """Multiplier of NOISE_WEIGHTS for a block's estimated ground ``noise`` [m], >= 0."""
    return float(np.clip(noise, NOISE_FLOOR, NOISE_MAX) - NOISE_FLOOR) / NOISE_SCALE


def noise_gate(features: np.ndarray) -> np.ndarray:
    """Share of the noise correction each node of :func:`wood_features` takes, (m,) in
    [0, 1]: trees under about NOISE_MAX_HEIGHT and wider than about NOISE_MIN_WIDTH."""
    short = _shorter_than(features[:, NODE_FEATURES + 1], NOISE_MAX_HEIGHT)
    return short * _logistic((features[:, NODE_FEATURES] - NOISE_MIN_WIDTH) / NOISE_WIDTH_BLEND)


def combined_score(
    features: np.ndarray,
    *,
    weights: np.ndarray = COMBINED_WEIGHTS,
    narrow_weights: np.ndarray | None = None,
    spindle_weights: np.ndarray | None = None,
    noise: float = 0.0,
    noise_weights: np.ndarray = NOISE_WEIGHTS,
    noise_columns: np.ndarray | None = None,
) -> np.ndarray:
    """Wood probability per node from :func:`wood_features`, (m,) float64 in [0, 1].

    ``weights`` score wide trees, corrected by ``noise_weights`` for the block's
    estimated ground ``noise`` [m] (:func:`noise_term`, :func:`noise_gate`) over the
    node features and ``noise_columns`` (:func:`noise_features`; required when the
    correction acts); ``narrow_weights`` (default
    NARROW_WEIGHTS; all zeros: the wide trees' model everywhere) score narrow ones,
    blended by :func:`narrowness`; among those, ``spindle_weights`` (default
    SPINDLE_WEIGHTS; all zeros: the narrow model for every narrow tree) score the
    narrowest, blended by SPINDLE_WIDTH.
    """
    z = features @ weights
    k = noise_term(noise)
    if k > 0:
        if noise_columns is None:
            raise ValueError("noise_columns (noise_features) are needed where noise_term(noise) > 0")
        cols = np.column_stack([features[:, :NODE_FEATURES], noise_columns])
        z = z + k * noise_gate(features) * (cols @ noise_weights)
        del cols  # gone before the narrow model's columns are built
    wide = _logistic(z)
    nw = NARROW_WEIGHTS if narrow_weights is None else narrow_weights
    if not nw.any():
        return wide
    width = features[:, NODE_FEATURES]
    g = narrowness(width, features[:, NODE_FEATURES + 1])
    cols = narrow_features(features)
    narrow = _logistic(cols @ nw)
    sw = SPINDLE_WEIGHTS if spindle_weights is None else spindle_weights
    if sw.any():
        q = _logistic((SPINDLE_WIDTH - width) / SPINDLE_BLEND)
        narrow = (1.0 - q) * narrow + q * _logistic(cols @ sw)
    return (1.0 - g) * wide + g * narrow


def classify(
    score: np.ndarray,
    node_tree: np.ndarray,
    *,
    params: MatterParams,
) -> np.ndarray:
    """Wood mask per node: score at or above the threshold, and in a tree."""
    return (score >= params.effective_threshold()) & (node_tree > 0)
