"""The per-block pipeline: ground → voxel graph → trunks → segmentation → wood/leaf.

`process_points` is what a dask task runs on a buffered tile and what a single-block
run runs on the whole block. It composes the kernels; it reads no files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from pipeline import woodleaf
from pipeline.blockresult import BlockResult, NodeAnalysis, block_result
from pipeline.enrichment import ShapeFeatures, neighbourhood_matrix, shape_features
from pipeline.graph import bridge_floating, build_graph, node_pairs, reweight, without_nodes
from pipeline.ground import GroundModel, classify_ground, ground_model
from pipeline.params import PipelineParams, TrunkParams
from pipeline.passes import indices_where
from pipeline.rowpasses import kept_entries
from pipeline.posts import Posts, find_posts, on_posts
from pipeline.slots import let_in, slot_evidence, trees_on_slots
from pipeline.segment import (
    Segmentation,
    curved_patches,
    faces,
    flat_patches,
    hard_surfaces,
    planar_patches,
    segment_nodes,
    standing,
)
from pipeline.stems import STEM_SLICE_HEIGHT, STEM_SLICES
from pipeline.trunks import (
    MIN_FLOOR_HEIGHT,
    TrunkDetection,
    box_like_trees,
    detect_trunks,
    drop_trunks,
    low_trees,
    young_block,
)
from pipeline.voxels import Voxels, rows_by_column, voxelize

# Fixed tuning of the box, bark, post and spacing tests, set on generated orchards (the
# evidence: docs/method.md, "Fixed constants"). Lengths in metres; eigenvalues λ1 >= λ2 >= λ3.

#: a node is on a planar surface (box, vehicle, wall) at this planarity or more ...
PLANAR_MIN = 0.55
#: ... and this scattering or less
PLANAR_MAX_SCATTER = 0.06
#: ground noise [m] in which box faces blur over several voxel layers and the box tests
#: of trunk detection take a looser planar test (above it no test tells faces from foliage)
NOISY_BOX_NOISE = (0.055, 0.085)
#: the looser test: spread in two directions (λ2/λ1) at least this ...
NOISY_PLANAR_MIN_SPREAD = 0.7
#: ... and thin in the third (λ3/λ1) at most this
NOISY_PLANAR_MAX_SCATTER = 0.35
#: a face blurred by range noise still spreads in two directions as wide as the
#: neighbourhood (λ2/λ1) at least this ...
BLURRED_MIN_SPREAD = 0.8
#: ... and in the third (λ3/λ1) at most this, at any noise up to about 0.08 m ...
BLURRED_MAX_SCATTER = 0.5
#: ... and foliage passes that node by node too, but forms no connected patch of this
#: many times ``surface_area`` (a vehicle's side does, at every noise) ...
BLURRED_AREA_RATIO = 4.0
#: ... of neighbours whose normals agree this well (|cos|): leaves touching a face stay out ...
BLURRED_MIN_COS = 0.9
#: ... whose normals point one way (largest eigenvalue of their mean outer product; a
#: vehicle's blurred faces 0.97-0.99, thick bark 0.53, a dense crown's envelope less) ...
BLURRED_MIN_ALIGN = 0.9
#: ... and of which the strict test sees at most this share as a face: a sharp face stops
#: short of its edges, where leaves touch it, and its margin cuts less crown (on clean
#: scans a vehicle's blurred patches are 55-92 % sharp, at range noise 0.03 m 0-25 %)
BLURRED_MAX_SHARP = 0.4
#: the box tests count planar nodes only in connected patches of at least this surface
#: [m²] (a box face is far larger; sparsely scanned bark is planar only in small patches)
MIN_FACE_AREA = 0.1
#: a planar patch is bark, not a face, when its normals spread at least this (middle
#: eigenvalue of their mean outer product) around an axis ...
BARK_MIN_SPREAD = 0.05
#: ... at most this far away [m] (the thickest trunk's radius, with room) ...
BARK_MAX_RADIUS = 0.75
#: ... and its normal lines pass within this fraction of that radius of the axis
BARK_MAX_RESIDUAL = 0.25
#: scattering (λ3/λ1) of fully leafy material (woody nodes measure about 0.05-0.1)
LEAFY_SCATTERING = 0.3
#: trellis posts are looked for only on scans whose ground noise [m] is below this (about
#: 0.03 m of range noise): noisier scans blur a post into a column of foliage
POST_MAX_NOISE = 0.05
#: the post test's radius [m] where ``max_post_radius`` is left unset (a trellis post is
#: 5-7 cm in radius) ...
AUTO_POST_RADIUS = 0.08
#: ... its posts kept only where, without them, the trees stand at least this far apart
#: in the row [m]: between tall spindles and SHD hedges (0.8-1.5 m, whose straight
#: leaders can pass for posts) and the closest vase rows (2.5 m)
AUTO_POST_MIN_SPACING = 1.8
#: ... and only where no two of them stand closer than this share of that spacing: a
#: trellis has at most one post in a gap, while the bare leaders of tall spindles that
#: pass for posts stand one slot apart
AUTO_POST_MIN_GAP = 0.75
#: the trees' spacing is measured only on scans whose ground noise [m] is below this: on
#: noisier ones shoot bundles drain like trunks and the spacing comes out too short
SPACING_MAX_NOISE = 0.05
#: graph nodes within a post's radius plus this [m] of its axis are the post's ...
POST_NODE_MARGIN = 0.05
#: rounds of dropping box-like or low "trees" and segmenting their material again
DROP_ROUNDS = 3
#: the foot test reads the ground points above this share of the ground layer's height
FOOT_LAYER_SHARE = 0.5
#: on a block of young trees, a trunk with a large planar surface (a bin's, a vehicle's, a
#: wall's) within this [m] horizontally is that object's edge or wheel, not a tree
YOUNG_SURFACE_REACH = 0.3


def face_nodes(voxel_size: float) -> int:
    """Least nodes of a planar patch the box tests count: MIN_FACE_AREA in voxels of
    ``voxel_size`` [m] (10 at 0.1 m)."""
    return int(round(MIN_FACE_AREA / voxel_size**2))


def _not_on_slot(drop: np.ndarray, det: TrunkDetection) -> np.ndarray:
    """``drop`` less the trunks let in on open planting slots: a replant is low by nature,
    and a full tree let in beside a stronger neighbour may keep little of its height."""
    return drop if det.on_slot is None else drop[~det.on_slot[drop]]


def _floors(det: TrunkDetection, params: PipelineParams) -> TrunkParams:
    """The trunk parameters with the size floors ``det`` used (the block's, where unset)."""
    return params.trunks.at_floors(*(det.floors or (None, None)))


def _low_floor(det: TrunkDetection, params: PipelineParams) -> TrunkParams:
    """The trunk parameters for the height test of segmented trees: the height floor
    ``det`` used, but on a block of young trees (its floors, left unset, below the
    mature trees') the least floor: a short young tree's material sits just above the
    block's floor, and segmentation can trim its top; the vehicles this test is for are
    turned down before on such blocks (:func:`pipeline.trunks.detect_trunks`)."""
    tp = _floors(det, params)
    return tp.model_copy(update={"min_tree_height": MIN_FLOOR_HEIGHT}) if young_block(det, params.trunks) else tp


def grass_nodes(nodes: np.ndarray, node_height: np.ndarray, trunk_xy: np.ndarray, *, params) -> np.ndarray:
    """Nodes lower than ``params.grass_height`` [m] above the ground and farther than
    ``params.grass_clearance`` [m] horizontally from every trunk ``trunk_xy`` (k, 2):
    grass, weeds and the feet of clutter, (m,) bool. Shortest paths running over them
    carried crowns out over the grass and into a vehicle's wheels; a tree's own material
    reaches that low only at its foot (drooping shoots end above 0.2 m)."""
    low = node_height < params.grass_height
    if not low.any() or not len(trunk_xy):
        return low
    idx = np.flatnonzero(low)
    near = np.isfinite(cKDTree(trunk_xy).query(nodes[idx, :2], distance_upper_bound=params.grass_clearance)[0])
    low[idx[near]] = False
    return low


def _without_edges_within(graph: sparse.csr_matrix, mask: np.ndarray) -> sparse.csr_matrix:
    """``graph`` without the edges whose two ends are both in ``mask`` (m,) bool: a path
    may end in such a node but not run on through it."""
    if not mask.any():
        return graph
    g = graph.tocsr()
    indices = g.indices
    out = kept_entries(g, lambda rows, lo, hi: ~(mask[rows] & mask[indices[lo:hi]]))
    out.sum_duplicates()  # as scipy leaves a matrix built from coordinates: canonical
    return out


def _beside(xy: np.ndarray, other: np.ndarray, reach: float) -> np.ndarray:
    """Indices of the points ``xy`` (k, 2) with a point of ``other`` (o, 2) within ``reach`` [m]."""
    if not len(xy) or not len(other):
        return np.zeros(0, np.int64)
    d, _ = cKDTree(other).query(xy, distance_upper_bound=reach)
    return np.flatnonzero(np.isfinite(d))


def blurred_planar(feats: ShapeFeatures) -> np.ndarray:
    """Nodes that may lie on a face, sharp or blurred by range noise, (m,) bool: spread
    in two directions as wide as the neighbourhood and thinner in the third. Foliage
    passes too, node by node; only large connected patches of them are faces
    (:func:`surface_nodes`)."""
    spread = feats.planarity + feats.scattering  # λ2/λ1
    return (spread >= BLURRED_MIN_SPREAD) & (feats.scattering <= BLURRED_MAX_SCATTER)


def noisy_planar(feats: ShapeFeatures, *, noise: float) -> np.ndarray:
    """Nodes on a box face blurred by range noise, (m,) bool; all False unless the
    block's estimated ground ``noise`` [m] is in ``NOISY_BOX_NOISE``."""
    lo, hi = NOISY_BOX_NOISE
    if not lo <= noise < hi:
        return np.zeros(feats.scattering.shape, bool)
    spread = feats.planarity + feats.scattering  # λ2/λ1
    return (spread >= NOISY_PLANAR_MIN_SPREAD) & (feats.scattering <= NOISY_PLANAR_MAX_SCATTER)


def _stem_points(xyz, height, is_ground, ground_top: float, *, on: bool) -> dict:
    """Non-ground points in the STEM_SLICES slices just above the ground layer, with
    their slice, for :func:`pipeline.trunks.stem_contrast` (empty dict when off)."""
    if not on:
        return {}
    top = STEM_SLICES * STEM_SLICE_HEIGHT

    def test(s: slice) -> np.ndarray:
        rel = height[s] - ground_top
        return ~is_ground[s] & (rel >= 0) & (rel < top)

    sel = indices_where(height.shape[0], test)
    rel = height[sel] - ground_top
    return {"stem_xy": xyz[sel, :2], "stem_slice": (rel // STEM_SLICE_HEIGHT).astype(np.int64)}


@dataclass(frozen=True)
class _NodeGraph:
    """The vegetation's voxel graph and what is read off it before trunks are looked for."""

    ground: GroundModel
    height: np.ndarray
    is_ground: np.ndarray
    vegetation: np.ndarray
    veg_idx: np.ndarray
    vox: Voxels
    node_height: np.ndarray
    adjacency: sparse.csr_matrix
    features: ShapeFeatures
    graph: sparse.csr_matrix
    leafiness: np.ndarray

    @property
    def nodes(self) -> np.ndarray:
        return self.vox.centroids


@dataclass(frozen=True)
class _Faces:
    """Planar patches of the graph and the box tests' views of them."""

    patch: np.ndarray
    size: np.ndarray
    standing_face: np.ndarray
    box_planar: np.ndarray
    blurred_patch: np.ndarray
    blurred_size: np.ndarray
    blurred_flat: np.ndarray


def _node_graph(xyz: np.ndarray, *, params: PipelineParams, grid_origin, ground_stats, raw_ground) -> _NodeGraph:
    """Ground model, vegetation voxels, their shape features and the bridged graph."""
    gm = ground_model(xyz, params=params.ground, grid_origin=grid_origin, stats=ground_stats, raw=raw_ground)
    height, is_ground = classify_ground(xyz, gm, params=params.ground)
    vegetation = ~is_ground & (height > 0)
    veg_idx = np.flatnonzero(vegetation)
    # column-major: voxelize's passes and sums run down each column (the same voxels)
    vox = voxelize(rows_by_column(xyz, veg_idx), voxel_size=params.graph.voxel_size, grid_origin=grid_origin)
    nodes = vox.centroids
    node_height = np.bincount(vox.point_voxel, weights=height[veg_idx], minlength=vox.n) / np.maximum(vox.counts, 1)
    radius = params.matter.smoothing_radius
    # one neighbour search serves both radii
    pairs = node_pairs(nodes, max(radius, params.graph.edge_radius))
    adjacency = neighbourhood_matrix(nodes, radius=radius, candidates=pairs)
    feats = shape_features(nodes, radius=radius, adjacency=adjacency)
    edge_scale = feats.matrix() if params.graph.weighting == "enriched" else None
    graph = build_graph(nodes, radius=params.graph.edge_radius, edge_scale=edge_scale, candidates=pairs)
    del pairs
    graph = bridge_floating(
        graph,
        nodes,
        node_height,
        floating_height=params.segment.floating_height,
        max_gap=params.graph.max_gap,
        min_nodes=params.segment.min_fragment,
    )
    leafiness = np.clip(woodleaf.smooth(feats.scattering, adjacency) / LEAFY_SCATTERING, 0.0, 1.0)
    return _NodeGraph(gm, height, is_ground, vegetation, veg_idx, vox, node_height, adjacency, feats, graph, leafiness)


def _faces(g: _NodeGraph, *, params: PipelineParams) -> _Faces:
    """Flat patches (connected planar nodes, without the curved bark of thick trunks) and
    the faces the box tests count."""
    feats = g.features
    planar = (feats.planarity >= PLANAR_MIN) & (feats.scattering <= PLANAR_MAX_SCATTER)
    min_face = face_nodes(params.graph.voxel_size)
    patch, size = _flat_patches(g, planar, min_face)
    blurred_patch, blurred_size = _flat_patches(g, blurred_planar(feats), min_face, min_cos=BLURRED_MIN_COS)
    # box tests: planar nodes in patches of MIN_FACE_AREA or more; the catchment's test
    # also counts blurred faces on noisy scans, whatever their patches (they break into
    # small ones), and cutting surfaces out of the graph needs the strict test
    face = faces(patch, size, min_face)
    # a segmented tree's box test counts only faces standing above the grass: flat grass
    # tops under a thin trunk (a spindle's leader) made up most of its little low material
    standing_face = face & standing(patch, size, g.node_height, min_top=params.segment.floating_height)
    box_planar = face | noisy_planar(feats, noise=g.ground.noise)
    blurred_flat = flat_patches(feats.normal, blurred_patch, blurred_size, min_align=BLURRED_MIN_ALIGN)
    return _Faces(patch, size, standing_face, box_planar, blurred_patch, blurred_size, blurred_flat)


def _flat_patches(g: _NodeGraph, planar: np.ndarray, min_face: int, *,
                  min_cos: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Connected patches of ``planar`` nodes (neighbours' normals agreeing to ``min_cos``,
    if given), without the curved ones (the bark of a thick trunk) of at least
    ``min_face`` nodes: (m,) patch of each node (-1: none), (c,) sizes."""
    normal = None if min_cos is None else g.features.normal
    patch, size = planar_patches(g.graph, planar, normal, 0.0 if min_cos is None else min_cos)
    bark = curved_patches(
        g.nodes, g.features.normal, patch, size,
        min_nodes=min_face, min_spread=BARK_MIN_SPREAD, max_radius=BARK_MAX_RADIUS, max_residual=BARK_MAX_RESIDUAL,
    )
    if bark.any():
        patch = np.where((patch >= 0) & bark[np.maximum(patch, 0)], -1, patch)
    return patch, size


def _mostly_blurred(patch: np.ndarray, size: np.ndarray, sharp: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """``patch`` (m,) without the patches of which more than BLURRED_MAX_SHARP are
    ``sharp`` (m,) bool nodes, nor those not ``flat`` (c,) bool (-1 for their nodes)."""
    on = patch >= 0
    if not on.any():
        return patch
    n_sharp = np.bincount(patch[on], weights=sharp[on].astype(np.float64), minlength=size.shape[0])
    drop = (n_sharp > BLURRED_MAX_SHARP * np.maximum(size, 1)) | ~flat
    return np.where(on & drop[np.maximum(patch, 0)], -1, patch)


def surface_nodes(nodes: np.ndarray, node_height: np.ndarray, f: _Faces, *, params: PipelineParams) -> np.ndarray:
    """Nodes of hard surfaces standing above the grass and those next to them, (m,) bool
    (:func:`pipeline.segment.hard_surfaces`): sharp faces of ``surface_area``, and
    faces blurred by range noise (:func:`blurred_planar`) of BLURRED_AREA_RATIO times it
    that the strict test does not see. On noisy scans no strict test finds a vehicle's
    faces; a part of them is enough to cut it out of the crown it stands under, as the
    margin takes its edges and what floats beside it stands with it
    (:func:`pipeline.segment.segment_nodes`).
    """
    min_nodes = int(round(params.segment.surface_area / params.graph.voxel_size**2))
    kw = dict(margin=params.segment.surface_margin, min_top=params.segment.floating_height)
    sharp = hard_surfaces(nodes, f.patch, f.size, node_height, min_nodes=min_nodes, **kw)
    blurred_patch = _mostly_blurred(f.blurred_patch, f.blurred_size, faces(f.patch, f.size, min_nodes), f.blurred_flat)
    blurred = hard_surfaces(nodes, blurred_patch, f.blurred_size, node_height,
                            min_nodes=int(round(BLURRED_AREA_RATIO * min_nodes)), **kw)
    return sharp | blurred


def _one_post_per_gap(xy: np.ndarray, spacing: float) -> bool:
    """Whether the posts at ``xy`` (p, 2) [m] stand at least AUTO_POST_MIN_GAP of the
    trees' ``spacing`` [m] from each other."""
    if len(xy) < 2:
        return True
    d, _ = cKDTree(xy).query(xy, k=2)
    return bool(d[:, 1].min() >= AUTO_POST_MIN_GAP * spacing)


def _find_trunks(xyz: np.ndarray, g: _NodeGraph, f: _Faces, *, params: PipelineParams,
                 slot_trees: np.ndarray | None) -> tuple[TrunkDetection, Posts | None, np.ndarray, dict, np.ndarray]:
    """Trunks from one multi-source search to the ground, trellis posts cut out, trees on
    open planting slots let in; returns (detection, posts, on_post, slot evidence, slot trees)."""
    gm, nodes, node_height = g.ground, g.nodes, g.node_height
    # drainage to the ground prefers woody paths: leafy (scattered) nodes cost more
    drainage = reweight(g.graph, 1.0 + params.trunks.leaf_cost * g.leafiness)
    ground_top = gm.tolerance(params.ground)
    stem_points = _stem_points(xyz, g.height, g.is_ground, ground_top, on=params.trunks.stem_ratio > 0)
    foot_xy = None
    if params.trunks.min_foot_ratio > 0:
        foot_top = FOOT_LAYER_SHARE * ground_top
        foot_xy = xyz[indices_where(xyz.shape[0], lambda s: g.is_ground[s] & (g.height[s] > foot_top)), :2]

    # radii left unset follow the spacing only where it can be measured
    measure_spacing = gm.noise < SPACING_MAX_NOISE

    def detect(drainage: sparse.csr_matrix, spacing: float | None = None) -> TrunkDetection:
        return detect_trunks(
            nodes,
            node_height,
            drainage,
            planar=f.box_planar,
            scattering=g.features.scattering,
            ground_top=ground_top,
            foot_xy=foot_xy,
            **stem_points,
            spacing=spacing,
            voxel_size=params.graph.voxel_size,
            measure_spacing=measure_spacing,
            params=params.trunks,
        )

    det = detect(drainage)
    # trellis posts drain crowns like trunks: cut them out of the graph and detect again
    on_post = np.zeros(g.vox.n, bool)
    posts = None
    auto = params.trunks.max_post_radius is None
    post_radius = AUTO_POST_RADIUS if auto else params.trunks.max_post_radius
    if post_radius > 0 and gm.noise < POST_MAX_NOISE and det.candidates is not None:
        cand = det.candidates
        # a post's catchment ends below the post height; a bole drains the crown above it
        tall = (cand["top"] >= _floors(det, params).min_tree_height) & (cand["top"] < params.trunks.max_post_height)
        tall &= ~np.asarray(cand.get("own_stem", False), bool)  # a bole of a stand taller than any post
        posts = find_posts(
            xyz, g.height, np.c_[cand["x"], cand["y"]][tall], max_radius=post_radius,
            max_height=params.trunks.max_post_height, among=g.vegetation,
        )
        on_post = on_posts(nodes, node_height, posts, margin=POST_NODE_MARGIN)
        if on_post.any():
            again = detect(without_nodes(drainage, on_post))  # the spacing measured again, without the posts
            wide = again.spacing is not None and again.spacing >= AUTO_POST_MIN_SPACING
            # a trellis among young trees has end posts a gap from the last gap's post, and
            # its young whips are no tall spindles' leaders
            if auto and not (wide and (young_block(again, params.trunks) or _one_post_per_gap(posts.xy, again.spacing))):
                # close rows, or "posts" closer than a trellis sets them: tall spindles' straight leaders
                posts, on_post = None, np.zeros(g.vox.n, bool)
            else:
                det = again
    # the row model as a prior: replants and full trees on open planting slots
    evidence = slot_evidence(det, params=params)
    if slot_trees is None:
        slot_trees = trees_on_slots(evidence, params=params.rows)
    det = let_in(det, slot_trees, nodes, node_height, contact_top=ground_top + params.trunks.contact_height)
    return det, posts, on_post, evidence, slot_trees


def _segment_trees(g: _NodeGraph, f: _Faces, det: TrunkDetection, on_post: np.ndarray, *,
                   params: PipelineParams) -> tuple[TrunkDetection, Segmentation]:
    """Segmentation from one multi-source search from the trunks; "trees" that turn out
    box-like or low (a vehicle) are dropped and their material segmented again."""
    nodes, node_height = g.nodes, g.node_height
    surfaces = on_post | surface_nodes(nodes, node_height, f, params=params)
    if _low_floor(det, params).min_tree_height < _floors(det, params).min_tree_height:
        # on a block of young trees a bin's edges and a vehicle's wheels stand like young
        # trees, and their faces are cut out (below) before the box test of segmented trees
        # could see them: a young tree stands clear of such surfaces
        det = drop_trunks(det, _beside(det.xy, nodes[surfaces & ~on_post, :2], YOUNG_SURFACE_REACH))
    seg_graph = g.graph
    if params.segment.leaf_cost > 0:
        seg_graph = reweight(g.graph, 1.0 + params.segment.leaf_cost * g.leafiness)

    def segment(det: TrunkDetection) -> Segmentation:
        return segment_nodes(
            nodes,
            _without_edges_within(seg_graph, grass_nodes(nodes, node_height, det.xy, params=params.segment)),
            source_nodes=det.source_nodes,
            source_trunk=det.source_trunk,
            trunk_xy=det.xy,
            node_height=node_height,
            params=params.segment.at_spacing(det.spacing),
            exclude=surfaces,
        )

    seg = segment(det)
    for _ in range(DROP_ROUNDS):  # dropping a box-like or low "tree" (a vehicle) re-segments its material
        drop = np.union1d(
            # the box test reads the material below a grown tree's height, where a vehicle's body is
            box_like_trees(seg.node_tree, node_height, nodes=nodes, trunk_xy=det.xy, planar=f.standing_face,
                           params=params.trunks.at_floors()),
            _not_on_slot(low_trees(seg.node_tree, node_height, det.k, params=_low_floor(det, params)), det),
        )
        if drop.size == 0:
            break
        det = drop_trunks(det, drop)
        seg = segment(det)
    return det, seg


def analyse_nodes(
    xyz: np.ndarray,
    *,
    params: PipelineParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ground_stats: tuple[float, float] | None = None,
    slot_trees: np.ndarray | None = None,
    raw_ground: GroundModel | None = None,
) -> NodeAnalysis:
    """Ground, voxel graph, trunks and segmentation at the node level.

    Parameters
    ----------
    xyz : (n, 3) float64 [m], local frame
    params : PipelineParams
    grid_origin : (3,) float
    ground_stats : (shift, noise), optional
        The block's ground statistics (:func:`pipeline.ground.ground_stats`) for a tile.
    slot_trees : (f, 3) float64, optional
        The trees on open planting slots the whole block's rows let in (x, y [m],
        young; :func:`pipeline.slots.trees_on_slots`), given to a tile run again with
        them. None: decided on the rows of ``xyz`` itself.
    raw_ground : GroundModel, optional
        :func:`pipeline.ground.raw_ground_model` of ``xyz`` with ``params.ground`` and
        ``grid_origin``, already fitted: not fitted again.

    Returns
    -------
    NodeAnalysis
    """
    # Strategy: ground model → vegetation voxels → one graph → trunks from one
    # multi-source search to the ground → segmentation from one multi-source search
    # from the trunks.
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError("xyz must have shape (n, 3)")
    g = _node_graph(xyz, params=params, grid_origin=grid_origin, ground_stats=ground_stats, raw_ground=raw_ground)
    f = _faces(g, params=params)
    det, posts, on_post, evidence, slot_trees = _find_trunks(xyz, g, f, params=params, slot_trees=slot_trees)
    det, seg = _segment_trees(g, f, det, on_post, params=params)
    return NodeAnalysis(g.ground, g.height, g.is_ground, g.veg_idx, g.vox, g.node_height, g.adjacency, g.features,
                        g.graph, det, seg, posts, on_post, evidence, np.asarray(slot_trees, np.float64).reshape(-1, 3))


def process_points(
    xyz: np.ndarray,
    *,
    params: PipelineParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ground_stats: tuple[float, float] | None = None,
    slot_trees: np.ndarray | None = None,
    raw_ground: GroundModel | None = None,
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
    ground_stats : (shift, noise), optional
        The whole block's ground statistics; tiles of one block pass the same values, so
        that their ground models are lifted alike. Default: estimated from ``xyz``.
    slot_trees : (f, 3) float64, optional
        For a tile run again: the trees on open slots the block's rows let in (see
        :func:`analyse_nodes`). None: decided on the rows of ``xyz``.
    raw_ground : GroundModel, optional
        The raw terrain model of ``xyz``, already fitted (see :func:`analyse_nodes`).

    Returns
    -------
    BlockResult
    """
    a = analyse_nodes(xyz, params=params, grid_origin=grid_origin, ground_stats=ground_stats, slot_trees=slot_trees,
                      raw_ground=raw_ground)
    return block_result(xyz, a, params=params)
