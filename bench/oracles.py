"""How much of the v-measure gap can a better trunk or wood step close? Oracles.

    python -m bench.oracles [--seeds 2]

On the issue's two accuracy settings (the paper's: sigma 0.02 m, 5 m spacing; high
density: 2.5 m x 4.5 m with low foliage) it prints the v-measure on true tree points of

- ``ours``: the pipeline as shipped;
- ``closest trunk``: every point to the horizontally nearest found trunk;
- ``wood oracle``: shortest paths on our voxel graph from the *true* wood voxels, each
  carrying its *true* tree: what geodesic segmentation gives with perfect trunks and
  perfect wood;
- ``voxel oracle``: every 0.1 m voxel takes its majority true tree: the ceiling of any
  method that labels voxels of this size;
- ``direction paths``: our trunks and graph, but paths that follow branch continuity, the
  way raycloudtools' ``rayextract trees`` connects points: an edge costs its squared
  length divided by the squared cosine of its turn from the path's direction so far,
  times ``1 + gravity * lateral**2`` (lateral distance from the trunk). Such costs depend
  on the path taken, so scipy's Dijkstra cannot compute them; ``direction_paths`` is a
  plain label-setting search for this measurement only. Nodes ours leaves at 0 stay 0;
- ``skeleton paths``: shortest paths from our trunk seeds over a point-scale graph
  (edges within ``SKELETON_RADIUS``, one point per ``SKELETON_CELL`` cube) of only the
  *true* wood and twig points (the simulator's ``twig`` kind: branches thinner than
  wood), each point then taking the trunk of its nearest reached skeleton point:
  geodesic segmentation with perfect twig detection. Only points ours put in a tree are
  relabelled;
- ``skeleton direction paths``: the same with direction-continuous paths over the
  skeleton (``direction_paths`` with a smoothed heading, no gravity): perfect twig
  detection and paths that keep to a twig where twigs of two trees cross;
- ``twig oracle``: every tree point takes the true tree of its nearest true wood or twig
  point: what knowing each twig's tree would give.

A second table says what the contested material is: the share of each kind of tree
point (all, wood, twig, leaf) lying beyond the midpoint towards another trunk (closer,
horizontally, to another tree's trunk base than to its own; see ``midpoint_ratio``).

A third table says where ours goes wrong (``error_breakdown``): the share of true tree
points in a found tree that stands for another tree or in none, the v-measure with
either kind put right, and the share wrong in each band of ``midpoint_ratio``.

A fourth table asks whether cutting the graph could help: the share of edges joining
voxels of two different true trees (by majority), the v-measure of our shortest-path
segmentation on the whole graph and with exactly those edges cut (``edge_cut_scores``),
with each edge's length scaled up by the score of an imagined classifier of those edges
of ROC AUC 0.75, 0.85 or 0.95 (``noisy_edge_scores``; what a learned edge weight would
need), and how well three local features mark those edges (ROC AUC): the longer edge,
the more scattered of its two nodes, and fewer point contacts (pairs of points of its
two voxels within ``CONTACT_RADIUS``).

A fifth table says whether twigs could be found at all: how well the linearity of each
tree point's neighbourhood (``TWIG_RADIUS``) tells twig and wood points from leaf points,
as the area under the ROC curve (``twig_visibility``; 0.5 = no better than chance).

Evaluation seeds (< 1000) only. Prints Markdown tables.
"""

from __future__ import annotations

import argparse
import heapq
import math
from itertools import pairwise

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree
from scipy.stats import mannwhitneyu, norm

from bench.baselines import nearest_trunk_labels
from pipeline.enrichment import shape_features
from simulator.scoring.scores import v_measure
from pipeline.graph import build_graph, shortest_paths
from pipeline.params import PipelineParams
from pipeline.blockresult import NodeAnalysis, block_result
from pipeline.process import analyse_nodes
from pipeline.segment import segment_nodes
from simulator.orchard import LEAF, TWIG, Orchard
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

SKELETON_RADIUS = 0.12
"""Edge length of the point-scale skeleton graph [m] (0.08 leaves a fifth of it unreached)."""

SKELETON_CELL = 0.03
"""The skeleton keeps one point per cube of this size [m]."""

SKELETON_SMOOTHING = 0.85
"""``smoothing`` of the skeleton's direction paths."""

CONTACT_RADIUS = 0.04
"""Two points of neighbouring voxels this close [m] are a contact of the edge between them."""

TWIG_RADIUS = 0.08
"""Neighbourhood radius of the twig-visibility test [m]."""

SETTINGS = {
    "paper setting (σ 0.02 m, 5 m × 6 m)": dict(rows=2, trees_per_row=4, noise=0.02, spacing=5.0, row_spacing=6.0),
    "high density (2.5 m × 4.5 m, low foliage)": dict(rows=2, trees_per_row=5, spacing=2.5, row_spacing=4.5, low_foliage=True),
}


def direction_paths(
    graph: sparse.csr_matrix,
    nodes: np.ndarray,
    seeds: np.ndarray,
    seed_trunk: np.ndarray,
    trunk_xy: np.ndarray,
    *,
    gravity: float = 0.3,
    smoothing: float | None = None,
) -> np.ndarray:
    """Trunk (0-based, -1 = unreached) of each node by direction-continuous paths.

    Label-setting search from all seeds at once. The direction of a path at a node is
    from its grandparent (parent, or straight up at a seed) to it, or, with
    ``smoothing`` s in [0, 1), the running average s * (direction at the parent) +
    (1 - s) * (last edge's direction), which noisy point-scale paths need; an edge of
    length d turning by angle a from it costs d**2 / max(cos a, 0.001)**2, scaled by
    ``1 + gravity * r**2`` with r the node's horizontal distance from its trunk.
    """
    n = nodes.shape[0]
    pos = nodes.tolist()
    indptr, indices = graph.indptr.tolist(), graph.indices.tolist()
    txy = trunk_xy.tolist()
    score = [math.inf] * n
    parent = [-1] * n
    trunk = [-1] * n
    done = [False] * n
    heading = [(0.0, 0.0, 1.0)] * n
    heap = []
    for s, t in zip(seeds.tolist(), seed_trunk.tolist()):
        score[s], trunk[s] = 0.0, t
        heap.append((0.0, s))
    heapq.heapify(heap)
    while heap:
        sc, u = heapq.heappop(heap)
        if done[u]:
            continue
        done[u] = True
        pu = pos[u]
        dx, dy, dz = heading[u]
        if smoothing is None and parent[u] >= 0:
            back = parent[parent[u]] if parent[parent[u]] >= 0 else parent[u]
            dx, dy, dz = (pu[i] - pos[back][i] for i in range(3))
            norm = math.sqrt(dx * dx + dy * dy + dz * dz) or 1.0
            dx, dy, dz = dx / norm, dy / norm, dz / norm
        t = trunk[u]
        scale = 1.0 + gravity * ((pu[0] - txy[t][0]) ** 2 + (pu[1] - txy[t][1]) ** 2)
        for k in range(indptr[u], indptr[u + 1]):
            v = indices[k]
            if done[v]:
                continue
            pv = pos[v]
            ex, ey, ez = pv[0] - pu[0], pv[1] - pu[1], pv[2] - pu[2]
            d2 = ex * ex + ey * ey + ez * ez
            if d2 == 0.0:
                continue
            cos = max(0.001, (ex * dx + ey * dy + ez * dz) / math.sqrt(d2))
            new = sc + d2 / (cos * cos) * scale
            if new < score[v]:
                score[v], parent[v], trunk[v] = new, u, t
                if smoothing is not None:
                    d = math.sqrt(d2)
                    hx, hy, hz = (smoothing * a + (1.0 - smoothing) * e / d for a, e in ((dx, ex), (dy, ey), (dz, ez)))
                    norm = math.sqrt(hx * hx + hy * hy + hz * hz) or 1.0
                    heading[v] = (hx / norm, hy / norm, hz / norm)
                heapq.heappush(heap, (new, v))
    return np.array(trunk, np.int64)


def midpoint_ratio(xy: np.ndarray, tree_id: np.ndarray, trunk_xy: np.ndarray) -> np.ndarray:
    """Where each tree point lies between its own trunk and the nearest other one.

    d_own / (d_own + d_other) with horizontal distances to its own tree's trunk base
    (``tree_id`` k is ``trunk_xy[k-1]``) and to the nearest other trunk: below 0.5 the
    point is nearer its own trunk, above 0.5 it reaches into a neighbour's side. NaN for
    points of no tree, 0 when there is only one trunk.
    """
    out = np.full(tree_id.shape[0], np.nan)
    idx = np.flatnonzero(tree_id > 0)
    if trunk_xy.shape[0] < 2 or idx.size == 0:
        out[idx] = 0.0
        return out
    own = tree_id[idx] - 1
    d_own = np.linalg.norm(xy[idx] - trunk_xy[own], axis=1)
    # of the two nearest trunks, the first that is not the point's own
    d2, j2 = cKDTree(trunk_xy).query(xy[idx], k=2)
    d_other = np.where(j2[:, 0] == own, d2[:, 1], d2[:, 0])
    out[idx] = d_own / np.maximum(d_own + d_other, 1e-12)
    return out


def overlap_shares(o: Orchard) -> dict[str, float]:
    """Share of all, wood, twig and leaf tree points beyond the midpoint (ratio > 0.5)."""
    r = midpoint_ratio(o.xyz[:, :2], o.tree_id, o.trunks[:, :2])
    tree = o.tree_id > 0
    kinds = {"all": tree, "wood": tree & o.is_wood, "twig": tree & (o.kind == TWIG), "leaf": tree & (o.kind == LEAF)}
    return {k: float((r[m] > 0.5).mean()) if m.any() else 0.0 for k, m in kinds.items()}


def twig_visibility(xyz: np.ndarray, is_twig: np.ndarray, is_leaf: np.ndarray, radius: float = TWIG_RADIUS) -> float:
    """ROC AUC of neighbourhood linearity for twig (or wood) against leaf points.

    Linearity (λ1-λ2)/λ1 of each point's neighbours within ``radius`` [m] among ``xyz``;
    the AUC is the probability that a random twig point is more linear than a random
    leaf point (ties count half): 1 = twigs stand out, 0.5 = they do not.
    """
    lin = shape_features(xyz, radius=radius).linearity
    return auc(lin[is_twig], lin[is_leaf])


def auc(x: np.ndarray, y: np.ndarray) -> float:
    """ROC AUC: the probability that a random value of ``x`` exceeds a random value of
    ``y`` (ties count half); NaN when either is empty."""
    if x.size == 0 or y.size == 0:
        return float("nan")
    return float(mannwhitneyu(x, y).statistic) / (x.size * y.size)


def cross_edges(graph: sparse.spmatrix, majority: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each edge of a symmetric ``graph`` once (``i < j``), and whether it joins two trees.

    Returns ``i``, ``j`` and a bool mask ``cross`` over them: both nodes belong to a tree
    (``majority`` > 0, the true tree of most of each node's points) and not the same one.
    Edges touching a node of no tree are never cross edges.
    """
    g = sparse.triu(sparse.coo_matrix(graph), k=1).tocoo()
    i, j = g.row.astype(np.int64), g.col.astype(np.int64)
    cross = (majority[i] > 0) & (majority[j] > 0) & (majority[i] != majority[j])
    return i, j, cross


def point_labels(a: NodeAnalysis, node_labels: np.ndarray, n: int) -> np.ndarray:
    """Each of the ``n`` input points takes its node's label, (n,) int64; points not in
    the graph (ground, below it) take 0."""
    out = np.zeros(n, np.int64)
    out[a.veg_idx] = node_labels[a.vox.point_voxel]
    return out


def edge_cut_scores(
    o: Orchard, xyz: np.ndarray, a: NodeAnalysis, majority: np.ndarray, params: PipelineParams
) -> dict[str, float]:
    """Could cutting the graph's edges between trees fix the segmentation? See the module doc.

    ``majority`` is the true tree of most of each node's points. Every v-measure (true
    tree points) comes from the same ``segment_nodes`` call on our trunks, so they differ
    only by the edges' weights (without the box-surface exclusion, hence "all edges" may differ
    slightly from ``ours``). ``classifier t`` is the best v-measure over
    ``CLASSIFIER_GAINS`` with edge lengths scaled by ``noisy_edge_scores`` of AUC ``t``
    (the gain picked on the block itself, which flatters it). The feature AUCs compare
    edges joining two trees against edges within one tree.
    """
    i, j, cross = cross_edges(a.graph, majority)
    both = (majority[i] > 0) & (majority[j] > 0)
    tree = o.tree_id > 0
    pv = a.vox.point_voxel
    det = a.trunks
    out = {"cross share": float(cross.sum() / max(both.sum(), 1))}
    w = np.asarray(a.graph.tocsr()[i, j]).ravel()

    def score(weight: np.ndarray) -> float:
        """v-measure of our segmentation on the graph's edges with these weights (inf = cut)."""
        keep = np.isfinite(weight)
        g = sparse.coo_matrix((weight[keep], (i[keep], j[keep])), shape=a.graph.shape)
        seg = segment_nodes(
            a.vox.centroids, (g + g.T).tocsr(), source_nodes=det.source_nodes, source_trunk=det.source_trunk,
            trunk_xy=det.xy, node_height=a.node_height, params=params.segment,
        )
        return v_measure(o.tree_id[tree], point_labels(a, seg.node_tree, o.tree_id.shape[0])[tree])

    out["all edges"] = score(w)
    out["cross edges cut"] = score(np.where(cross, np.inf, w))
    rng = np.random.default_rng(0)
    for target in CLASSIFIER_AUCS:
        p = noisy_edge_scores(cross, target, rng)
        out[f"classifier {target}"] = max(score(w * (1.0 + b * p**2)) for b in CLASSIFIER_GAINS)
    pairs = cKDTree(xyz[a.veg_idx]).query_pairs(CONTACT_RADIUS, output_type="ndarray")
    vi, vj = pv[pairs[:, 0]], pv[pairs[:, 1]]
    apart = vi != vj
    lo, hi = np.minimum(vi[apart], vj[apart]), np.maximum(vi[apart], vj[apart])
    contacts = sparse.coo_matrix((np.ones(lo.size), (lo, hi)), shape=a.graph.shape).tocsr()
    nodes, scattering = a.vox.centroids, a.features.scattering
    feats = {
        "longer": np.linalg.norm(nodes[i] - nodes[j], axis=1),
        "more scattered": np.maximum(scattering[i], scattering[j]),
        "fewer contacts": -np.asarray(contacts[i, j]).ravel(),
    }
    for name, f in feats.items():
        out[f"auc {name}"] = auc(f[both & cross], f[both & ~cross])
    return out


CLASSIFIER_AUCS = (0.75, 0.85, 0.95)
"""ROC AUCs of the imagined edge classifiers in ``edge_cut_scores``."""

CLASSIFIER_GAINS = (1.0, 4.0, 16.0)
"""An edge of classifier score p costs ``1 + gain * p**2`` times its length; the best gain counts."""


def noisy_edge_scores(cross: np.ndarray, target_auc: float, rng: np.random.Generator) -> np.ndarray:
    """Scores in (0, 1) of an imagined classifier of cross edges with ROC AUC ``target_auc``.

    Binormal: a cross edge scores N(d, 1), any other N(0, 1), with d = √2·Φ⁻¹(AUC), so a
    random cross edge outscores a random other edge with probability ``target_auc``;
    then mapped through Φ(z - d/2) to (0, 1) (monotone, so the AUC is unchanged).
    """
    d = math.sqrt(2.0) * norm.ppf(target_auc)
    z = rng.standard_normal(cross.shape[0]) + d * cross
    return norm.cdf(z - d / 2)


RATIO_BANDS = (0.0, 0.3, 0.4, 0.5, 0.6, 1.0)
"""Bands of ``midpoint_ratio`` in the error table (0.5 = the midpoint between two trunks)."""

BAND_NAMES = tuple(f"{lo}-{hi}" for lo, hi in pairwise(RATIO_BANDS))


def error_breakdown(true_tree: np.ndarray, pred_tree: np.ndarray, ratio: np.ndarray) -> dict[str, float]:
    """Where a segmentation of true tree points goes wrong.

    Each predicted tree stands for the true tree most of its points belong to; a point
    is *wrong* when its predicted tree stands for another tree, *unlabelled* when its
    predicted tree is 0. Returns the v-measure as it is, with every wrong point and with
    every unlabelled point given the predicted tree that stands for its true tree (or a
    tree of its own where none does), the shares of wrong and unlabelled points, and per
    ``RATIO_BANDS`` band (``ratio`` from :func:`midpoint_ratio`) its points and the
    share of them that are wrong (keys ``"band a-b points"``, ``"band a-b wrong"``).

    Parameters
    ----------
    true_tree, pred_tree : (n,) int64 — true and predicted tree of each true tree point
    ratio : (n,) float64
    """
    k = int(pred_tree.max()) + 1
    counts = np.zeros((k, int(true_tree.max()) + 1), np.int64)
    np.add.at(counts, (pred_tree, true_tree), 1)
    stands_for = counts.argmax(axis=1)
    stands_for[0] = -1
    unlabelled = pred_tree == 0
    wrong = ~unlabelled & (stands_for[pred_tree] != true_tree)
    # the predicted tree that stands for each true tree (the largest such), else a new id
    fix = np.arange(counts.shape[1]) + k
    for p in np.argsort(counts.max(axis=1))[::-1]:
        if p > 0 and fix[stands_for[p]] >= k:
            fix[stands_for[p]] = p
    out = {"v-measure": v_measure(true_tree, pred_tree), "wrong": float(wrong.mean()), "unlabelled": float(unlabelled.mean())}
    for name, m in (("wrong right", wrong), ("unlabelled right", unlabelled)):
        pred = pred_tree.copy()
        pred[m] = fix[true_tree[m]]
        out[f"v-measure, {name}"] = v_measure(true_tree, pred)
    for name, (lo, hi) in zip(BAND_NAMES, pairwise(RATIO_BANDS)):
        band = (ratio >= lo) & ((ratio < hi) | (hi == RATIO_BANDS[-1]))
        out[f"band {name} points"] = float(band.sum())
        out[f"band {name} wrong"] = float(wrong[band].mean()) if band.any() else 0.0
    return out


def oracle_scores(o: Orchard, params: PipelineParams) -> dict[str, float]:
    xyz = o.xyz - np.floor(o.xyz.min(axis=0))
    tree = o.tree_id > 0
    out = {}
    a = analyse_nodes(xyz, params=params)
    result = block_result(xyz, a, params=params)
    for name, r in (("ours", result), ("closest trunk", nearest_trunk_labels(xyz, result))):
        out[name] = v_measure(o.tree_id[tree], r.tree_id[tree])
    ratio = midpoint_ratio(o.xyz[:, :2], o.tree_id, o.trunks[:, :2])
    errors = error_breakdown(o.tree_id[tree], result.tree_id[tree], ratio[tree])
    out.update({f"errors: {key}": v for key, v in errors.items()})
    pv = a.vox.point_voxel
    t = o.tree_id[a.veg_idx]
    counts = np.zeros((a.vox.n, int(o.tree_id.max()) + 1))
    np.add.at(counts, (pv, t), 1)
    majority = counts.argmax(axis=1)
    wood = np.bincount(pv, weights=o.is_wood[a.veg_idx], minlength=a.vox.n) > 0.5 * a.vox.counts
    seeds = np.flatnonzero(wood & (majority > 0))
    sp = shortest_paths(a.graph, seeds)
    node = np.where(sp.source >= 0, majority[np.maximum(sp.source, 0)], 0)
    det, ours = a.trunks, a.segmentation.node_tree
    trunk = direction_paths(a.graph.tocsr(), a.vox.centroids, det.source_nodes, det.source_trunk, det.xy)
    directed = np.where(ours > 0, np.where(trunk >= 0, trunk + 1, ours), 0)
    for name, lab in (("wood oracle", node), ("voxel oracle", majority), ("direction paths", directed)):
        out[name] = v_measure(o.tree_id[tree], point_labels(a, lab, o.tree_id.shape[0])[tree])

    skeleton = o.is_wood | (o.kind == TWIG)
    _, j = cKDTree(xyz[skeleton]).query(xyz[tree], workers=-1)
    out["twig oracle"] = v_measure(o.tree_id[tree], o.tree_id[skeleton][j])

    ours_pt = point_labels(a, ours, o.tree_id.shape[0])
    seed_trunk = np.full(a.vox.n, -1)
    seed_trunk[det.source_nodes] = det.source_trunk
    point_trunk = np.full(o.tree_id.shape[0], -1)
    point_trunk[a.veg_idx] = seed_trunk[pv]
    sk = np.flatnonzero((skeleton & (ours_pt > 0)) | (point_trunk >= 0))
    _, first = np.unique(np.floor(xyz[sk] / SKELETON_CELL).astype(np.int64), axis=0, return_index=True)
    sk = sk[np.sort(first)]
    graph = build_graph(xyz[sk], radius=SKELETON_RADIUS).tocsr()
    seeds = np.flatnonzero(point_trunk[sk] >= 0)
    sp = shortest_paths(graph, seeds)
    plain = np.where(sp.source >= 0, point_trunk[sk[np.maximum(sp.source, 0)]], -1)
    directed = direction_paths(graph, xyz[sk], seeds, point_trunk[sk[seeds]], det.xy, gravity=0.0, smoothing=SKELETON_SMOOTHING)
    for name, sk_trunk in (("skeleton paths", plain), ("skeleton direction paths", directed)):
        reached = sk_trunk >= 0
        _, j = cKDTree(xyz[sk[reached]]).query(xyz[ours_pt > 0], workers=-1)
        pred = ours_pt.copy()
        pred[ours_pt > 0] = sk_trunk[reached][j] + 1
        out[name] = v_measure(o.tree_id[tree], pred[tree])
    out.update({f"edges: {key}": v for key, v in edge_cut_scores(o, xyz, a, majority, params).items()})
    return out


EDGE_COLS = ("cross share", "all edges", "cross edges cut", *(f"classifier {t}" for t in CLASSIFIER_AUCS),
             "auc longer", "auc more scattered", "auc fewer contacts")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=2, help="evaluation seeds 0..N-1 per setting")
    args = ap.parse_args(argv)
    params = PipelineParams()
    visible = []
    cols = ("ours", "closest trunk", "direction paths", "wood oracle", "skeleton paths", "skeleton direction paths",
            "twig oracle", "voxel oracle")
    kinds = ("all", "wood", "twig", "leaf")
    _header(cols)
    shares, errors, edges = [], [], []
    error_cols = ("wrong", "unlabelled", "v-measure", "v-measure, wrong right", "v-measure, unlabelled right",
                  *BAND_NAMES)
    for label, sim in SETTINGS.items():
        for seed in range(args.seeds):
            o = simulate_orchard(SimulationParams(seed=seed, **sim))
            s = oracle_scores(o, params)
            print(f"| {label} | {seed} | " + " | ".join(f"{s[c]:.3f}" for c in cols) + " |", flush=True)
            errors.append(f"| {label} | {seed} | " + " | ".join(_error_cell(s, c) for c in error_cols) + " |")
            edges.append(f"| {label} | {seed} | {100 * s['edges: cross share']:.2f} % | "
                         + " | ".join(f"{s['edges: ' + c]:.3f}" for c in EDGE_COLS[1:]) + " |")
            s = overlap_shares(o)
            tree = o.tree_id > 0
            twig_auc = twig_visibility(o.xyz[tree], (o.is_wood | (o.kind == TWIG))[tree], (o.kind == LEAF)[tree])
            visible.append(f"| {label} | {seed} | {twig_auc:.3f} |")
            shares.append(f"| {label} | {seed} | " + " | ".join(f"{100 * s[k]:.1f} %" for k in kinds) + " |")
    print("\nShare of tree points beyond the midpoint towards another trunk:\n")
    _header(kinds)
    print("\n".join(shares))
    print("\nWhere ours goes wrong (true tree points; a found tree stands for the true tree most of its points"
          " belong to): share in a tree standing for another (wrong) or in none (unlabelled); v-measure as is and"
          " with either kind put right; share wrong, of all points in each band of midpoint ratio (0.5 = midway"
          " to the nearest other trunk):\n")
    _header(("wrong", "unlabelled", "v-measure", "wrong put right", "unlabelled put right", *(f"ratio {b}" for b in BAND_NAMES)))
    print("\n".join(errors))
    print("\nEdges joining two trees' voxels: their share of the edges within trees, v-measure of the same"
          " shortest-path segmentation on all edges, with them cut, and with each edge's length scaled by"
          f" 1 + gain * p^2 (best gain of {CLASSIFIER_GAINS}) where p is the score of an imagined classifier of"
          " them with the given ROC AUC, and the ROC AUC of local features marking them:\n")
    _header(("share of edges", "v-measure, all edges", "v-measure, cross edges cut",
             *(f"v-measure, classifier AUC {t}" for t in CLASSIFIER_AUCS), "AUC edge length",
             "AUC larger scattering", "AUC fewer point contacts"))
    print("\n".join(edges))
    print(f"\nTwig and wood points against leaf points by neighbourhood linearity ({TWIG_RADIUS} m), ROC AUC:\n")
    _header(("AUC",))
    print("\n".join(visible))


def _error_cell(s: dict[str, float], col: str) -> str:
    if col in ("wrong", "unlabelled"):
        return f"{100 * s['errors: ' + col]:.2f} %"
    if col.startswith("v-measure"):
        return f"{s['errors: ' + col]:.4f}"
    return f"{100 * s[f'errors: band {col} wrong']:.1f} % of {s[f'errors: band {col} points']:,.0f}"


def _header(cols: tuple[str, ...]) -> None:
    print("| setting | seed | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))


if __name__ == "__main__":
    main()
