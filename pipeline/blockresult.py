"""What a run of the pipeline gives: the per-point labels and per-trunk data of one
block or buffered tile (`BlockResult`), read off the graph-level results
(`NodeAnalysis`) of `pipeline.process.analyse_nodes`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from pipeline import woodleaf
from pipeline.enrichment import ShapeFeatures
from pipeline.ground import GroundModel
from pipeline.metrics import trunk_circles
from pipeline.params import PipelineParams
from pipeline.posts import Posts, on_posts
from pipeline.segment import Segmentation, trunk_feet
from pipeline.trunks import TrunkDetection, young_block
from pipeline.voxels import Voxels

# Fixed tuning of the box, bark, post and spacing tests, set on generated orchards (the
# evidence: docs/method.md, "Fixed constants"). Lengths in metres; eigenvalues λ1 >= λ2 >= λ3.


#: ... and of their points, those within its radius plus this [m] (range noise) are
POST_SURFACE_MARGIN = 0.03


#: a stem circle's centre replaces the detected trunk position when it lies within a
#: diameter of it, and at least this [m] (farther, the fit found something else)
MIN_RECENTRE = 0.15


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
    spacing : float or None
        The in-row tree spacing the radii left unset followed [m]
        (:meth:`pipeline.params.TrunkParams.at_spacing`); None: not measured.
    trunk_young : (k,) bool or None
        Trunks let in as replants: too low to pass as trees, on an open planting slot.
    trunk_own_stem : (k,) bool or None
        Trunks with a stem of their own (a bole standing in a closed stand,
        :class:`pipeline.trunks.TrunkDetection`): the row prior never drops them.
    slot_evidence : dict or None
        What the block's decision on trees on open slots needs of this run
        (:func:`pipeline.slots.slot_evidence`), in the frame of the input xyz.
    slot_trees : (f, 3) float64 or None
        The trees on open slots this run let in (x, y, young;
        :func:`pipeline.slots.trees_on_slots`).
    """

    tree_id: np.ndarray
    is_ground: np.ndarray
    is_wood: np.ndarray
    wood_score: np.ndarray
    height: np.ndarray
    trunks: np.ndarray
    trunk_support: np.ndarray
    trunk_diameter: np.ndarray
    spacing: float | None = None
    trunk_young: np.ndarray | None = None
    trunk_own_stem: np.ndarray | None = None
    slot_evidence: dict | None = None
    slot_trees: np.ndarray | None = None

    @property
    def n_trees(self) -> int:
        return int(self.trunks.shape[0])


@dataclass(frozen=True)
class NodeAnalysis:
    """Intermediate graph-level results of one run (for baselines, fitting and debugging).

    ``veg_idx`` are the input points in the graph; ``vox.point_voxel`` maps them to nodes.
    """

    ground: GroundModel
    height: np.ndarray
    is_ground: np.ndarray
    veg_idx: np.ndarray
    vox: Voxels
    node_height: np.ndarray
    adjacency: sparse.csr_matrix
    features: ShapeFeatures
    graph: sparse.csr_matrix
    trunks: TrunkDetection
    segmentation: Segmentation
    posts: Posts | None = None
    on_post: np.ndarray | None = None
    slot_evidence: dict | None = None
    slot_trees: np.ndarray | None = None


def node_wood_score(a: NodeAnalysis, *, params: PipelineParams) -> np.ndarray:
    """Wood score per node, (m,) float64 in [0, 1], by ``params.matter.method``."""
    node_tree = a.segmentation.node_tree
    if not (node_tree > 0).any():  # no trees, no wood
        return np.zeros(node_tree.shape[0])
    p = woodleaf.path_counts(a.segmentation.paths.pred)
    if params.matter.method == "paper":
        return woodleaf.smooth(woodleaf.log_score(p), a.adjacency)
    x = woodleaf.wood_features(
        p,
        a.segmentation.node_tree,
        a.trunks.xy,
        a.vox.centroids,
        a.node_height,
        a.vox.counts,
        a.features,
        a.adjacency,
    )
    extra = None
    if woodleaf.noise_term(a.ground.noise) > 0:
        sp = a.segmentation.paths
        extra = woodleaf.noise_features(p, a.segmentation.node_tree, sp.pred, sp.dist, a.vox.counts, a.adjacency)
    return woodleaf.combined_score(x, noise=a.ground.noise, noise_columns=extra)


def block_result(xyz: np.ndarray, a: NodeAnalysis, *, params: PipelineParams) -> BlockResult:
    """Per-point labels, wood and trunk measurements from a node-level analysis of ``xyz``.

    :func:`process_points` is ``analyse_nodes`` followed by this; callers that also need
    the :class:`NodeAnalysis` (``bench.oracles``) run the analysis once and call both.

    Parameters
    ----------
    xyz : (n, 3) float64 [m] — the points ``a`` was computed from
    a : NodeAnalysis
    params : PipelineParams — the same parameters ``a`` was computed with

    Returns
    -------
    BlockResult
    """
    node_tree = a.segmentation.node_tree
    score = np.where(node_tree > 0, node_wood_score(a, params=params), 0.0)
    node_wood = woodleaf.classify(score, node_tree, params=params.matter)

    # each point's node (a node past the last for points in none, labelled 0): one
    # scatter, then one gather a label, instead of a gather and a scatter each
    m = node_tree.shape[0]
    point_node = np.full(xyz.shape[0], m, np.int32 if m < np.iinfo(np.int32).max else np.intp)
    point_node[a.veg_idx] = a.vox.point_voxel
    tree_id, is_wood, wood_score = (
        np.concatenate([v.astype(t, copy=False), np.zeros(1, t)])[point_node]
        for v, t in ((node_tree, np.int64), (node_wood, bool), (score, np.float32))
    )
    del point_node
    if a.on_post is not None and a.on_post.any():
        near, src = _post_foliage(xyz, a, params=params)
        tree_id[near] = node_tree[src]
        is_wood[near] = node_wood[src]
        wood_score[near] = score[src]
    # the bottom of each trunk fell below the ground tolerance: it takes its tree's labels back
    is_ground = a.is_ground.copy()
    foot, src = trunk_feet(
        xyz,
        tree_id,
        is_ground,
        a.height,
        a.trunks.xy,
        ground_top=a.ground.tolerance(params.ground),
        margin=params.segment.foot_margin,
        max_radius=params.metrics.max_trunk_radius,
    )
    tree_id[foot] = tree_id[src]
    is_wood[foot] = is_wood[src]
    wood_score[foot] = wood_score[src]
    is_ground[foot] = False
    trunks, diameter = _measured_trunks(xyz, tree_id, a, params=params)
    return BlockResult(
        tree_id=tree_id,
        is_ground=is_ground,
        is_wood=is_wood,
        wood_score=wood_score,
        height=a.height.astype(np.float32),
        trunks=trunks,
        trunk_support=a.trunks.support.astype(np.float64),
        trunk_diameter=diameter,
        spacing=a.trunks.spacing,
        trunk_young=a.trunks.young,
        trunk_own_stem=a.trunks.own_stem,
        slot_evidence=a.slot_evidence,
        slot_trees=a.slot_trees,
    )


def _post_foliage(xyz: np.ndarray, a: NodeAnalysis, *, params: PipelineParams) -> tuple[np.ndarray, np.ndarray]:
    """The points of post voxels that are foliage touching the post, and the tree node
    (within ``fragment_reach``) whose labels each takes: (p,) point and (p,) node indices.

    A post's voxels also hold that foliage; the post's own points stay unlabelled (0).
    """
    node_tree = a.segmentation.node_tree
    near = a.veg_idx[a.on_post[a.vox.point_voxel]]
    near = near[~on_posts(xyz[near], a.height[near], a.posts, margin=POST_SURFACE_MARGIN)]
    tree_nodes = np.flatnonzero((node_tree > 0) & ~a.on_post)
    if not (near.size and tree_nodes.size):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d, j = cKDTree(a.vox.centroids[tree_nodes]).query(xyz[near], distance_upper_bound=params.segment.fragment_reach)
    hit = np.isfinite(d)
    return near[hit], tree_nodes[j[hit]]


def _measured_trunks(xyz: np.ndarray, tree_id: np.ndarray, a: NodeAnalysis, *,
                     params: PipelineParams) -> tuple[np.ndarray, np.ndarray]:
    """(k, 3) trunk positions [m] (x, y, ground z) and (k,) stem diameters [m] (NaN where
    not measured) of the detected trunks, given the points' tree labels."""
    k = a.trunks.k
    trunks = np.zeros((k, 3))
    trunks[:, :2] = a.trunks.xy
    trunks[:, 2] = a.ground.height_at(a.trunks.xy) if k else np.zeros(0)
    centres, diameter = trunk_circles(xyz, tree_id, trunks, params=params.metrics, height=a.height)
    # where the stem's circle was measured, its centre is the trunk's position (the
    # detection's flow-weighted centroid of voxels sits off the stem by a few cm)
    shift = np.hypot(*(centres - trunks[:, :2]).T) if k else np.zeros(0)
    moved = np.isfinite(diameter) & (shift <= np.maximum(diameter, MIN_RECENTRE))
    if moved.any():
        trunks[moved, :2] = centres[moved]
        trunks[moved, 2] = a.ground.height_at(centres[moved])
    if young_block(a.trunks, params.trunks):
        # a young stem's stake, as thick as the stem, widens its circle: the diameter is
        # that of one of the two sections, the position stays between them, as neither
        # the slice nor the flow tells which is the stem (pipeline.stemslice)
        diameter = trunk_circles(xyz, tree_id, trunks, params=params.metrics, height=a.height, stakes=True)[1]
    return trunks, diameter
