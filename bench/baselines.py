"""Baselines that the benchmarks (docs/benchmarks.md) compare against, run on the same data.

- ``closest_trunk``: every non-ground point goes to the nearest trunk in plan view
  (the paper's comparison method), with our trunks, so only segmentation differs.
- ``paper_as_published``: the paper's method as written: trunk finding by one graph
  search per canopy source sampled on a 4 m grid with minimum path length to the ground
  and local minima; segmentation by one search per trunk (A* in the paper; Dijkstra
  per source here, same paths); path counts summed over the per-trunk searches,
  S = log(p)/log(p_max) over the whole graph, thresholded at the median; points the
  graph does not reach stay unlabelled.

- ``paper_with_our_trunks``: the paper's segmentation and wood/leaf steps from our
  trunks, so the comparison of those steps does not depend on trunk finding.

All return a :class:`pipeline.blockresult.BlockResult` so they are evaluated like our method.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from pipeline.graph import build_graph, subtree_sizes
from pipeline.ground import classify_ground, ground_model
from pipeline.metrics import trunk_circles
from pipeline.params import PipelineParams
from pipeline.blockresult import BlockResult
from pipeline.process import process_points
from pipeline.voxels import voxelize

#: the paper's source sampling grid for trunk finding [m]
PAPER_SOURCE_GRID = 4.0
#: ground score minima closer than this are one trunk [m]
PAPER_TRUNK_CLUSTER = 1.0


def closest_trunk(
    xyz: np.ndarray,
    *,
    params: PipelineParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> BlockResult:
    """Our trunks and wood labels; segmentation by nearest trunk in plan view.

    Parameters
    ----------
    xyz : (n, 3) float64 [m]
    params : PipelineParams
    grid_origin : (3,) float

    Returns
    -------
    BlockResult
    """
    return nearest_trunk_labels(xyz, process_points(xyz, params=params, grid_origin=grid_origin))


def nearest_trunk_labels(xyz: np.ndarray, ours: BlockResult) -> BlockResult:
    """``ours`` with every non-ground point relabelled to the nearest trunk in plan view.

    The closest-trunk baseline from a result already computed on the same ``xyz``
    (so a caller scoring both does not run the pipeline twice).
    """
    tree_id = np.zeros(xyz.shape[0], np.int64)
    veg = ~ours.is_ground & (ours.height > 0)
    if ours.n_trees:
        _, j = cKDTree(ours.trunks[:, :2]).query(xyz[veg, :2])
        tree_id[veg] = j + 1
    return BlockResult(
        tree_id=tree_id,
        is_ground=ours.is_ground,
        is_wood=ours.is_wood & (tree_id > 0),
        wood_score=ours.wood_score,
        height=ours.height,
        trunks=ours.trunks,
        trunk_support=ours.trunk_support,
        trunk_diameter=ours.trunk_diameter,
    )


def _paper_trunks(nodes: np.ndarray, is_ground_node: np.ndarray, graph, grid_origin, node_height: np.ndarray | None = None,
                  source_min_height: float = 0.0) -> np.ndarray:
    """The paper's trunk finding; returns (k, 3) trunk node positions. Sources are taken
    among the non-ground nodes at least ``source_min_height`` [m] above the ground (0: all,
    as published)."""
    veg = np.flatnonzero(~is_ground_node)
    gnd = np.flatnonzero(is_ground_node)
    if source_min_height > 0 and node_height is not None:
        veg = veg[node_height[veg] >= source_min_height]
    if veg.size == 0 or gnd.size == 0:
        return np.zeros((0, 3))
    # one source per 4 m cell: the vegetation node nearest the cell centre
    cell = np.floor((nodes[veg] - np.asarray(grid_origin)) / PAPER_SOURCE_GRID).astype(np.int64)
    centre = (cell + 0.5) * PAPER_SOURCE_GRID + np.asarray(grid_origin)
    d = ((nodes[veg] - centre) ** 2).sum(1)
    _, inv = np.unique(cell, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    order = np.lexsort((d, inv))
    first = order[np.r_[True, inv[order][1:] != inv[order][:-1]]]
    sources = veg[first]
    # one search per source (as published), score = min path length over sources
    score = np.full(nodes.shape[0], np.inf)
    for s in sources:
        dist = csgraph.dijkstra(graph, directed=False, indices=int(s))
        np.minimum(score, dist, out=score)
    gs = score[gnd]
    reached = np.isfinite(gs)
    gnd, gs = gnd[reached], gs[reached]
    if gnd.size == 0:
        return np.zeros((0, 3))
    # local minima of the ground score within the cluster radius, then merge close ones
    tree = cKDTree(nodes[gnd, :2])
    nbrs = tree.query_ball_point(nodes[gnd, :2], PAPER_TRUNK_CLUSTER)
    is_min = np.array([gs[i] <= gs[nb].min() for i, nb in enumerate(nbrs)])
    mins = gnd[is_min]
    if mins.size == 0:
        return np.zeros((0, 3))
    labels = csgraph.connected_components(
        cKDTree(nodes[mins, :2]).sparse_distance_matrix(cKDTree(nodes[mins, :2]), PAPER_TRUNK_CLUSTER), directed=False
    )[1]
    out = np.array([nodes[mins[labels == c]].mean(0) for c in np.unique(labels)])
    return out


def paper_with_our_trunks(
    xyz: np.ndarray,
    *,
    params: PipelineParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> BlockResult:
    """The paper's segmentation and wood/leaf steps (one search per trunk, median
    threshold) started from our trunks: isolates those two steps from trunk finding."""
    ours = process_points(xyz, params=params, grid_origin=grid_origin)
    return paper_as_published(xyz, params=params, grid_origin=grid_origin, trunks=ours.trunks)


def paper_as_published(
    xyz: np.ndarray,
    *,
    params: PipelineParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    trunks: np.ndarray | None = None,
    source_min_height: float = 0.0,
) -> BlockResult:
    """The paper's method as written (see module docstring).

    Parameters
    ----------
    xyz : (n, 3) float64 [m]
    params : PipelineParams — voxel size, edge radius and ground parameters are used
    grid_origin : (3,) float
    trunks : (k, 3) float64, optional — start from these trunks instead of the paper's
        trunk finding
    source_min_height : float — trunk finding takes its sources only among nodes at least
        this high above the ground [m]; 0 (as published): any non-ground node, which on a
        block with grass is mostly grass (``python -m bench.paper_setting``)

    Returns
    -------
    BlockResult
    """
    n = xyz.shape[0]
    gm = ground_model(xyz, params=params.ground, grid_origin=grid_origin)
    height, is_ground = classify_ground(xyz, gm, params=params.ground)
    keep = height > -params.ground.outlier_depth
    idx = np.flatnonzero(keep)
    vox = voxelize(xyz[idx], voxel_size=params.graph.voxel_size, grid_origin=grid_origin)
    nodes = vox.centroids
    m = vox.n
    ground_frac = np.bincount(vox.point_voxel, weights=is_ground[idx].astype(float), minlength=m) / vox.counts
    is_ground_node = ground_frac > 0.5
    graph_all = build_graph(nodes, radius=params.graph.edge_radius)
    if trunks is None:
        node_height = np.bincount(vox.point_voxel, weights=height[idx], minlength=m) / vox.counts
        trunk_nodes = _paper_trunks(nodes, is_ground_node, graph_all, grid_origin, node_height, source_min_height)
    else:
        trunk_nodes = np.asarray(trunks)
    k = trunk_nodes.shape[0]

    # segmentation and path counts: one search per trunk over the tree graph (ground removed)
    veg = np.flatnonzero(~is_ground_node)
    sub = graph_all[veg][:, veg]
    best = np.full(veg.size, np.inf)
    owner = np.zeros(veg.size, np.int64)
    paths = np.zeros(veg.size)
    if k and veg.size:
        _, start = cKDTree(nodes[veg]).query(trunk_nodes)
        for t, s in enumerate(start):
            dist, pred = csgraph.dijkstra(sub, directed=False, indices=int(s), return_predecessors=True)
            pred = pred.astype(np.int64)
            pred[pred < 0] = -1
            reached = np.isfinite(dist)
            paths += np.where(reached, subtree_sizes(pred), 0.0)
            closer = dist < best
            best[closer] = dist[closer]
            owner[closer] = t + 1
    lp = np.log(np.maximum(paths, 1.0))
    s_score = lp / lp.max() if lp.size and lp.max() > 0 else np.zeros_like(lp)
    in_tree = owner > 0
    thr = float(np.median(s_score[in_tree])) if in_tree.any() else 1.0
    node_tree = np.zeros(m, np.int64)
    node_tree[veg] = owner
    node_score = np.zeros(m)
    node_score[veg] = s_score
    node_wood = (node_score > thr) & (node_tree > 0)

    tree_id = np.zeros(n, np.int64)
    is_wood = np.zeros(n, bool)
    wood_score = np.zeros(n, np.float32)
    pt_tree = node_tree[vox.point_voxel]
    tree_id[idx] = np.where(is_ground[idx], 0, pt_tree)
    is_wood[idx] = node_wood[vox.point_voxel] & (tree_id[idx] > 0)
    wood_score[idx] = node_score[vox.point_voxel]
    trunks = trunk_nodes.copy()
    if k:
        trunks[:, 2] = gm.height_at(trunks)
    return BlockResult(
        tree_id=tree_id,
        is_ground=is_ground,
        is_wood=is_wood,
        wood_score=wood_score,
        height=height.astype(np.float32),
        trunks=trunks,
        trunk_support=np.zeros(k),
        trunk_diameter=trunk_circles(xyz, tree_id, trunks, params=params.metrics)[1],
    )
