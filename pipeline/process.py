"""The per-block pipeline: ground → voxel graph → trunks → segmentation → wood/leaf.

`process_points` is what a dask task runs on a buffered tile and what a single-block
run runs on the whole block. It composes the kernels; it reads no files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline import matter
from pipeline.enrichment import neighbourhood_matrix, shape_features
from pipeline.graph import build_graph
from pipeline.ground import classify_ground, ground_model
from pipeline.metrics import trunk_diameters
from pipeline.params import PipelineParams
from pipeline.segment import segment_nodes
from pipeline.trunks import detect_trunks
from pipeline.voxels import voxelize

#: neighbourhood radius of the shape features, in voxels
FEATURE_RADIUS_VOXELS = 2.5
#: a node is on a planar surface (box, vehicle, wall) above this planarity ...
PLANAR_MIN = 0.55
#: ... and below this scattering
PLANAR_MAX_SCATTER = 0.06


@dataclass(frozen=True)
class BlockResult:
    """Per-point labels and per-trunk data for one block or buffered tile.

    Attributes
    ----------
    tree_id : (n,) int64
        0 = not a tree (ground, clutter); k >= 1 is the tree whose trunk is ``trunks[k-1]``.
    is_ground : (n,) bool
    is_wood : (n,) bool
        Always False where ``tree_id == 0``.
    wood_score : (n,) float32
        In [0, 1]; the score that was thresholded to give ``is_wood``.
    height : (n,) float32
        Height above the ground surface [m].
    trunks : (k, 3) float64
        Trunk base (centre of the trunk where it meets the ground), in the frame of the input xyz.
    trunk_support : (k,) float64
        Number of graph nodes whose shortest path to the ground ends in this trunk
        (a confidence, used to break ties when tiles disagree).
    trunk_diameter : (k,) float64
        Trunk diameter at ``params.metrics.trunk_height`` [m]; NaN when not measurable.
    """

    tree_id: np.ndarray
    is_ground: np.ndarray
    is_wood: np.ndarray
    wood_score: np.ndarray
    height: np.ndarray
    trunks: np.ndarray
    trunk_support: np.ndarray
    trunk_diameter: np.ndarray

    @property
    def n_trees(self) -> int:
        return int(self.trunks.shape[0])


def process_points(
    xyz: np.ndarray,
    *,
    params: PipelineParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> BlockResult:
    """Run the whole per-block pipeline on one point cloud.

    Parameters
    ----------
    xyz : (n, 3) float64
        Point coordinates [m] in a local frame (input coordinates minus a block origin).
    params : PipelineParams
    grid_origin : (3,) float
        Origin of the voxel and ground grids in the same frame. Tiles of one block pass
        the same value so that their grids line up and results agree across tiles.

    Returns
    -------
    BlockResult
    """
    # Strategy: ground model → vegetation voxels → one graph → trunks from one
    # multi-source search to the ground → segmentation from one multi-source search from
    # the trunks → wood score from the subtree sizes of that search's forest.
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError("xyz must have shape (n, 3)")
    n = xyz.shape[0]
    gm = ground_model(xyz, params=params.ground, grid_origin=grid_origin)
    height, is_ground = classify_ground(xyz, gm, params=params.ground)
    veg = ~is_ground & (height > 0)
    veg_idx = np.flatnonzero(veg)

    vox = voxelize(xyz[veg_idx], voxel_size=params.graph.voxel_size, grid_origin=grid_origin)
    nodes = vox.centroids
    m = vox.n
    node_height = np.bincount(vox.point_voxel, weights=height[veg_idx], minlength=m) / np.maximum(vox.counts, 1)
    adjacency = neighbourhood_matrix(nodes, radius=FEATURE_RADIUS_VOXELS * params.graph.voxel_size)
    feats = shape_features(nodes, radius=FEATURE_RADIUS_VOXELS * params.graph.voxel_size, adjacency=adjacency)
    edge_scale = feats.matrix() if params.graph.weighting == "enriched" else None
    graph = build_graph(nodes, radius=params.graph.edge_radius, edge_scale=edge_scale)
    planar = (feats.planarity >= PLANAR_MIN) & (feats.scattering <= PLANAR_MAX_SCATTER)

    det = detect_trunks(nodes, node_height, graph, planar=planar, params=params.trunks)
    seg = segment_nodes(
        nodes,
        graph,
        source_nodes=det.source_nodes,
        source_trunk=det.source_trunk,
        trunk_xy=det.xy,
        params=params.segment,
    )
    node_tree = seg.node_tree
    score = node_wood_score(seg, node_tree, feats, vox.counts, node_height, adjacency, params=params)
    node_wood = matter.classify(score, node_tree, params=params.matter)

    tree_id = np.zeros(n, np.int64)
    is_wood = np.zeros(n, bool)
    wood_score = np.zeros(n, np.float32)
    tree_id[veg_idx] = node_tree[vox.point_voxel]
    is_wood[veg_idx] = node_wood[vox.point_voxel]
    wood_score[veg_idx] = np.where(node_tree > 0, score, 0.0)[vox.point_voxel]

    k = det.k
    trunks = np.zeros((k, 3))
    trunks[:, :2] = det.xy
    trunks[:, 2] = gm.height_at(det.xy) if k else np.zeros(0)
    diam = trunk_diameters(xyz, tree_id, trunks, params=params.metrics)
    return BlockResult(
        tree_id=tree_id,
        is_ground=is_ground,
        is_wood=is_wood,
        wood_score=wood_score,
        height=height.astype(np.float32),
        trunks=trunks,
        trunk_support=det.support.astype(np.float64),
        trunk_diameter=diam,
    )


def node_wood_score(seg, node_tree, feats, counts, node_height, adjacency, *, params: PipelineParams) -> np.ndarray:
    """Wood score per node, (m,) float64 in [0, 1], by ``params.matter.method``."""
    p = matter.path_counts(seg.paths.pred)
    if params.matter.method == "paper":
        return matter.log_score(p)
    s_tree = matter.log_score(p, node_tree)
    top = np.zeros(int(node_tree.max()) + 1 if node_tree.size else 1)
    np.maximum.at(top, node_tree, node_height)
    hfrac = np.where(top[node_tree] > 0, node_height / np.maximum(top[node_tree], 1e-9), 0.0)
    return matter.combined_score(s_tree, feats, counts, np.clip(hfrac, 0, 1), adjacency)
