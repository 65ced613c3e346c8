"""Trunk detection without priors.

The paper searches from many canopy sources to the ground and takes the ground entry
points with the lowest path lengths as trunks. The same idea in one search: a single
multi-source Dijkstra from every low node (a possible ground contact) over the voxel
graph. Every node's shortest path down ends in one contact; the number of nodes whose
path ends there (the contact's subtree size in the shortest-path forest) is its
*catchment*. A trunk is where a whole canopy drains to the ground: contacts are grouped
by non-maximum suppression, and a group is a trunk when its catchment is large, reaches
tree height, is not box-like (planar), the flow into it passes through a compact,
trunk-sized cross-section (hanging foliage drains through wide curtains; fence posts
drain nothing above them), and its stem stands out above the ground layer about as
clearly as its neighbours' (shoots hanging into the grass beside a trunk do not).
Groups that are no trunks themselves (too wide, or such shoots) pass their catchment to
the trunk beside them before neighbouring trunks' catchments are compared.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from pipeline.floors import (
    BRANCH_MAX_PLANAR,
    BRANCH_MAX_SIZE,
    MIN_FLOOR_HEIGHT,
    MIN_FLOOR_VOXELS,
    block_floors,
    branches,
    group_percentile,
)
from pipeline.graph import shortest_paths, subtree_sizes
from pipeline.neighbours import BOLE_ABOVE_POST, COLUMN_MIN_STEM, accept, own_stems
from pipeline.params import MATURE_FLOORS, SPACING_RADII, TrunkParams
from pipeline.spacing import estimate_spacing
from pipeline.stems import STEM_SLICES, foot_ratio, stem_contrast

# Fixed tuning of trunk detection (lengths in metres; node counts scale with the voxel size).

#: a ground contact is a candidate when it drains a path at least this long (3 nodes at
#: 0.1 m voxels): single stray contacts drain nothing
MIN_CONTACT_DRAIN = 0.3
#: the flow's cross-section is measured in this band [m] above the contact band (a
#: trunk's flow passes it compactly, hanging foliage's as a wide curtain)
FLOW_BAND = 0.4
#: a group's height is this percentile of its nodes' heights (the maximum would follow
#: single noisy points above a fence post)
TOP_PERCENTILE = 95.0
#: groupings with a radius from the measured spacing: the spacing is measured again on
#: the finer grouping, at most this many times
SPACING_ROUNDS = 2
#: a trunk's segmentation sources are its contact nodes within half its width, at least
#: SOURCE_MIN_RADIUS [m], plus SOURCE_MARGIN [m] of its centre
SOURCE_MIN_RADIUS = 0.15
SOURCE_MARGIN = 0.1
#: the box test of a segmented tree counts its material within this [m] of the trunk (a
#: crown overhanging a vehicle stays a tree)
BOX_TEST_RADIUS = 1.0


def min_contact_drain(voxel_size: float) -> int:
    """MIN_CONTACT_DRAIN in graph nodes of ``voxel_size`` [m]."""
    return int(round(MIN_CONTACT_DRAIN / voxel_size))


@dataclass(frozen=True)
class TrunkDetection:
    """Detected trunks.

    Attributes
    ----------
    xy : (k, 2) float64 — trunk centre [m]
    support : (k,) float64 — catchment (graph nodes draining through the trunk)
    width : (k,) float64 — flow-weighted cross-section width near the ground [m]
    source_nodes : (s,) int64 — graph nodes that seed each trunk in segmentation
    source_trunk : (s,) int64 — trunk (0-based) of each source node
    candidates : dict or None — every contact group's measurements (diagnostics)
    spacing : float or None — the in-row tree spacing the radii followed [m]
    young : (k,) bool or None — trunks let in as replants (:mod:`pipeline.slots`)
    on_slot : (k,) bool or None — trunks let in on an open planting slot, replants or
        full-grown (:mod:`pipeline.slots`): the rows vouch for them
    floors : (min_tree_height [m], min_canopy_voxels) or None — the size floors the
        detection used (None: no detection ran)
    own_stem : (k,) bool or None — trunks with a stem of their own (:func:`pipeline.neighbours.own_stems`):
        the row prior at the merge never drops them
    """

    xy: np.ndarray
    support: np.ndarray
    width: np.ndarray
    source_nodes: np.ndarray
    source_trunk: np.ndarray
    candidates: dict | None = None
    spacing: float | None = None
    young: np.ndarray | None = None
    on_slot: np.ndarray | None = None
    floors: tuple[float, int] | None = None
    own_stem: np.ndarray | None = None

    @property
    def k(self) -> int:
        return int(self.xy.shape[0])


def young_block(det: TrunkDetection, params: TrunkParams) -> bool:
    """Whether ``det`` read the block as one of young trees: its height floor, left unset
    in ``params``, below the mature trees'."""
    return params.min_tree_height is None and det.floors is not None and \
        det.floors[0] < MATURE_FLOORS["min_tree_height"]


def _suppress(xy: np.ndarray, score: np.ndarray, radius: float) -> np.ndarray:
    """Greedy non-maximum suppression: label of the strongest point within ``radius``.

    Returns (c,) int64 cluster id per point (the index of its leader).
    """
    order = np.argsort(-score, kind="stable")
    leader = np.full(xy.shape[0], -1, np.int64)
    tree = cKDTree(xy)
    for i in order:
        if leader[i] >= 0:
            continue
        nb = np.asarray(tree.query_ball_point(xy[i], radius), dtype=np.int64)
        nb = nb[leader[nb] < 0]
        leader[nb] = i
    return leader


@dataclass(frozen=True)
class _Drained:
    """The drainage to the ground contacts, shared by every clustering radius.

    cand : (c,) int64 — contact nodes draining MIN_CONTACT_DRAIN or more; size : (m,) subtree size
    of each node; source : (m,) contact each node drains to (-1: none); reached : (m,)
    bool; n_planar, n_low : (m,) planar and all nodes below tree height draining to each
    contact; contact_top : float — top of the contact band [m].
    """

    cand: np.ndarray
    size: np.ndarray
    source: np.ndarray
    reached: np.ndarray
    n_planar: np.ndarray
    n_low: np.ndarray
    contact_top: float
    voxel_size: float


def _groups(
    nodes: np.ndarray, node_height: np.ndarray, d: _Drained, scattering: np.ndarray | None, *, radius: float, params: TrunkParams,
    branch_test: bool = False,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Contact groups of one clustering ``radius`` [m] and each group's own measurements.

    Returns
    -------
    groups : (g,) int64 — each group's leader (index into ``d.cand``)
    gidx : (c,) int64 — the group of each contact of ``d.cand``
    candidates : dict of (g,) arrays — centre ``x``, ``y`` [m], ``support``, ``top``,
        ``planar``, ``width`` [m], ``branches`` (:func:`pipeline.floors.branches`), ``fits`` (the size,
        height and box tests; with ``branch_test``, a group below the mature trees'
        floors must also branch), ``unbranched`` (failed only that) and flow diagnostics
    """
    m = nodes.shape[0]
    cand, size, reached = d.cand, d.size, d.reached
    contact_top = d.contact_top
    leader = _suppress(nodes[cand, :2], size[cand], radius)
    groups, gidx = np.unique(leader, return_inverse=True)
    g_support = np.bincount(gidx, weights=size[cand])
    group_of_contact = np.full(m, -1, np.int64)
    group_of_contact[cand] = gidx
    node_group = np.where(reached, group_of_contact[np.maximum(d.source, 0)], -1)
    g_top = group_percentile(node_height, node_group, groups.size, TOP_PERCENTILE)
    g_planar = np.bincount(gidx, weights=d.n_planar[cand]) / np.maximum(np.bincount(gidx, weights=d.n_low[cand]), 1)
    fits = (g_support >= params.min_canopy_voxels) & (g_top >= params.min_tree_height) & (g_planar <= params.max_planar_fraction)

    # cross-section of the flow just above the contact band: nodes whose path ends in the
    # group, in the band [contact_top, contact_top + FLOW_BAND], weighted by the flow
    # (subtree size) they carry
    band = reached & (node_height >= contact_top) & (node_height < contact_top + FLOW_BAND)
    bn = np.flatnonzero(band)
    bg = group_of_contact[d.source[bn]]
    keep = bg >= 0
    bn, bg = bn[keep], bg[keep]
    wgt = size[bn]
    wsum = np.bincount(bg, weights=wgt, minlength=groups.size)
    cx = np.bincount(bg, weights=wgt * nodes[bn, 0], minlength=groups.size) / np.maximum(wsum, 1e-12)
    cy = np.bincount(bg, weights=wgt * nodes[bn, 1], minlength=groups.size) / np.maximum(wsum, 1e-12)
    r2 = (nodes[bn, 0] - cx[bg]) ** 2 + (nodes[bn, 1] - cy[bg]) ** 2
    rms = np.sqrt(np.bincount(bg, weights=wgt * r2, minlength=groups.size) / np.maximum(wsum, 1e-12))
    width = 2.0 * rms + d.voxel_size  # + one voxel: the centroids sit inside the bark surface
    has_band = wsum > 0
    # trees whose flow has no band nodes (tiny trunks under the contact height): use the leader
    lx = nodes[cand[groups], 0]
    ly = nodes[cand[groups], 1]
    cx = np.where(has_band, cx, lx)
    cy = np.where(has_band, cy, ly)
    width = np.where(has_band, width, d.voxel_size)
    sc = scattering if scattering is not None else np.zeros(m)
    band_scatter = np.bincount(bg, weights=wgt * sc[bn], minlength=groups.size) / np.maximum(wsum, 1e-12)
    band_max = np.zeros(groups.size)
    np.maximum.at(band_max, bg, wgt)
    main_xy, stem_width = _main_column(nodes[bn, :2], bg, wgt, groups.size, d.voxel_size)
    if branch_test:
        # a young stem's flow is a few voxels wide: a riser or a stake beside it that took
        # over part of it would pull the flow's centroid off the stem
        main = np.hypot(*(nodes[bn, :2] - main_xy[bg]).T) <= 0.5 * stem_width[bg]
        msum = np.bincount(bg[main], weights=wgt[main], minlength=groups.size)
        cx = np.where(msum > 0, np.bincount(bg[main], weights=(wgt * nodes[bn, 0])[main], minlength=groups.size)
                      / np.maximum(msum, 1e-12), cx)
        cy = np.where(msum > 0, np.bincount(bg[main], weights=(wgt * nodes[bn, 1])[main], minlength=groups.size)
                      / np.maximum(msum, 1e-12), cy)
    branched = branches(nodes, node_height, node_group, np.column_stack([cx, cy]), d.voxel_size,
                        node_foot=nodes[np.maximum(d.source, 0), :2])
    unbranched = np.zeros(groups.size, bool)
    if branch_test:
        mature = (g_support >= MATURE_FLOORS["min_canopy_voxels"]) & (g_top >= MATURE_FLOORS["min_tree_height"])
        unbranched = fits & ~branched & ~mature
        # and shows no box face (a bin's corners branch out, thin young stems form no planar patches)
        # and drains no more than a young tree of the block: a vehicle's underside drains
        # like several (6 times the median young tree on generated blocks)
        young = (g_planar <= BRANCH_MAX_PLANAR) & (g_support <= BRANCH_MAX_SIZE * params.min_canopy_voxels)
        fits &= ~unbranched & (mature | young)
    candidates = {
        "x": cx, "y": cy, "support": g_support, "top": g_top, "planar": g_planar, "width": width,
        "stem_width": np.where(has_band, stem_width, d.voxel_size), "branches": branched,
        "unbranched": unbranched,
        "band_flow": wsum, "band_scatter": band_scatter,
        "band_nodes": np.bincount(bg, minlength=groups.size), "band_max": band_max, "fits": fits,
    }
    return groups, gidx, candidates


def _main_column(xy: np.ndarray, group: np.ndarray, weight: np.ndarray, n_groups: int,
                 voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Each group's main column in the band above the contacts: the band node of ``xy``
    (b, 2) [m] of ``group`` (b,) carrying the most flow ``weight`` (b,), and the width [m]
    around it: twice the flow-weighted median distance of the group's band nodes from it,
    plus one voxel. Returns (n_groups, 2) and (n_groups,); zeros and one voxel for a
    group without band nodes."""
    # a thin column beside a stem (an irrigation riser by a young tree) takes over part
    # of the tree's flow where a feather touches it: the flow's RMS spans both columns,
    # while half the flow stays within the stem's own cross-section
    centre = np.zeros((n_groups, 2))
    width = np.full(n_groups, voxel_size)
    if not len(group):
        return centre, width
    heaviest = np.lexsort((-weight, group))
    first = heaviest[np.r_[0, np.flatnonzero(np.diff(group[heaviest])) + 1]]
    centre[group[first]] = xy[first]
    dist = np.hypot(*(xy - centre[group]).T)
    order = np.lexsort((dist, group))
    g, dist, w = group[order], dist[order], weight[order]
    cum = np.cumsum(w)
    start = np.searchsorted(g, np.arange(n_groups))
    end = np.searchsorted(g, np.arange(n_groups), side="right")
    has = end > start
    before = np.where(start > 0, cum[np.maximum(start - 1, 0)], 0.0)
    half = before + 0.5 * (cum[np.maximum(end - 1, 0)] - before)
    idx = np.searchsorted(cum, half)  # the first node of the group reaching half its flow
    width[has] = 2.0 * dist[np.minimum(idx[has], end[has] - 1)] + voxel_size
    return centre, width


def detect_trunks(
    nodes: np.ndarray,
    node_height: np.ndarray,
    graph: sparse.csr_matrix,
    *,
    planar: np.ndarray,
    scattering: np.ndarray | None = None,
    ground_top: float = 0.0,
    foot_xy: np.ndarray | None = None,
    stem_xy: np.ndarray | None = None,
    stem_slice: np.ndarray | None = None,
    spacing: float | None = None,
    measure_spacing: bool = True,
    voxel_size: float,
    params: TrunkParams,
) -> TrunkDetection:
    """Find one trunk per tree.

    The radii of ``params`` left unset follow the block's in-row tree spacing
    (:meth:`TrunkParams.at_spacing`): the given ``spacing``, else the one measured
    (:func:`pipeline.spacing.estimate_spacing`) on the trunk-like contact groups of a
    grouping with the free-standing trees' cluster radius (or the one given), grouped
    again with a smaller radius where the spacing measured asks for one.

    Parameters
    ----------
    nodes : (m, 3) float64 — node positions [m] (non-ground voxel centroids)
    node_height : (m,) float64 — height of each node above the ground [m]
    graph : (m, m) csr_matrix — the voxel graph over ``nodes``
    planar : (m,) bool — nodes on planar (box-like) surfaces
    scattering : (m,) float64, optional — shape scattering of each node (diagnostics)
    ground_top : float — height [m] up to which points were classified ground; contacts
        lie within ``params.contact_height`` above it
    foot_xy : (f, 2) float64, optional — points in the upper half of the ground layer
        [m], for the foot test (``params.min_foot_ratio``)
    stem_xy : (p, 2) float64, optional — non-ground points in the STEM_SLICES slices
        above the ground layer [m], and stem_slice : (p,) int64 their slice, for the stem
        test (``params.stem_ratio``); without them the test is off
    spacing : float, optional — the block's in-row tree spacing [m], if known (a tile
        passes the one measured before); None: measured here when a radius needs it
    measure_spacing : bool — False: no spacing is measured (noisy scans), the radii left
        unset take the free-standing trees' values (the satellite radius shrunk on a block
        of young trees)
    voxel_size : float — edge of the voxels the nodes are centroids of [m]
    params : TrunkParams

    Returns
    -------
    TrunkDetection, with ``candidates`` holding every contact group's measurements and
    ``spacing`` the spacing the radii followed (None: none measured).
    """
    # Strategy: drain every node to its ground contact once; the floors follow the block's
    # trees and the radii its spacing, each measured on a grouping of those contacts; then
    # every group passes its own tests and the tests between neighbours.
    empty = TrunkDetection(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64))
    drained = _drain(nodes, node_height, graph, planar=planar, ground_top=ground_top, voxel_size=voxel_size,
                     params=params)
    if drained is None:
        return empty
    params, branch_test = _floors_of_block(nodes, node_height, drained, scattering, params)
    if spacing is None and measure_spacing and params.needs_spacing():
        spacing = _measured_spacing(nodes, node_height, drained, scattering, params, branch_test)
    params = _radii(params, spacing, branch_test)
    groups, gidx, candidates = _groups(nodes, node_height, drained, scattering, radius=params.cluster_radius, params=params,
                                       branch_test=branch_test)
    ok, support = _trunk_tests(candidates, nodes, node_height, foot_xy=foot_xy, stem_xy=stem_xy, stem_slice=stem_slice,
                               params=params)
    sel = np.flatnonzero(ok)
    xy = np.column_stack([candidates["x"][sel], candidates["y"][sel]])
    src, src_t = _sources(nodes, drained.cand, groups, gidx, candidates, sel)
    return TrunkDetection(xy, support[sel], candidates["width"][sel], src, src_t, candidates, spacing,
                          floors=(params.min_tree_height, params.min_canopy_voxels), own_stem=candidates["own_stem"][sel])


def _drain(
    nodes: np.ndarray, node_height: np.ndarray, graph: sparse.csr_matrix, *, planar: np.ndarray, ground_top: float,
    voxel_size: float, params: TrunkParams,
) -> _Drained | None:
    """Every node drained to its nearest ground contact (one multi-source search from
    the contact band), with each contact's catchment; None without a candidate contact."""
    m = nodes.shape[0]
    contact_top = ground_top + params.contact_height
    contact = np.flatnonzero(node_height < contact_top)
    if m == 0 or contact.size == 0:
        return None
    sp = shortest_paths(graph, contact)
    size = subtree_sizes(sp.pred)
    reached = sp.source >= 0

    # per contact: catchment, and planar nodes draining into it
    catch = size[contact]
    # box-like objects: the planar share of the low part of the catchment (below tree
    # height, where a vehicle's body is and overhanging foliage mostly is not)
    low = reached & (node_height < params.at_floors().min_tree_height)
    n_planar = np.bincount(sp.source[low], weights=planar[low].astype(np.float64), minlength=m)
    n_low = np.bincount(sp.source[low], minlength=m).astype(np.float64)

    cand = contact[catch >= min_contact_drain(voxel_size)]
    if cand.size == 0:
        return None
    return _Drained(cand, size, sp.source, reached, n_planar, n_low, contact_top, voxel_size)


def _floors_of_block(
    nodes: np.ndarray, node_height: np.ndarray, drained: _Drained, scattering: np.ndarray | None, params: TrunkParams,
) -> tuple[TrunkParams, bool]:
    """``params`` with the size floors the block's trees ask for, and whether they are a
    young block's (then groups below the mature floors must branch)."""
    if not params.needs_floors():
        return params, False
    # the floors follow the block's trees: measured on the groups of the free-standing
    # trees' (or the given) cluster radius that branch and pass every other test of
    # their own at the lowest floors
    loose = params.at_floors(MIN_FLOOR_HEIGHT, MIN_FLOOR_VOXELS)
    _, _, probe = _groups(nodes, node_height, drained, scattering, radius=loose.at_spacing(None).cluster_radius,
                          params=loose)
    ok = probe["fits"] & probe["branches"] & (probe["width"] <= params.max_trunk_width)
    floors = block_floors(probe["top"], probe["support"], ok, probe["stem_width"])
    return params.at_floors(*floors), floors[0] is not None  # a block of young trees


def _measured_spacing(
    nodes: np.ndarray, node_height: np.ndarray, drained: _Drained, scattering: np.ndarray | None, params: TrunkParams,
    branch_test: bool,
) -> float | None:
    """The in-row tree spacing [m] measured on the trunk-like contact groups."""
    # a first grouping with the free-standing trees' (or the given) cluster radius
    # keeps the bark of a trunk up to about that thick in one group; where it measures
    # trees closer than that, trunks may share groups: group again with the radius
    # that spacing gives, and measure once more
    radius = params.at_spacing(None).cluster_radius
    spacing = None
    for _ in range(SPACING_ROUNDS):
        _, _, probe = _groups(nodes, node_height, drained, scattering, radius=radius, params=params,
                              branch_test=branch_test)
        strong = probe["fits"] & (probe["width"] <= params.max_trunk_width)
        spacing = estimate_spacing(np.column_stack([probe["x"], probe["y"]])[strong], probe["support"][strong])
        if params.at_spacing(spacing).cluster_radius >= radius:
            break
        radius = params.at_spacing(spacing).cluster_radius
    return spacing


def _radii(params: TrunkParams, spacing: float | None, young: bool) -> TrunkParams:
    """``params`` with the radii left unset following ``spacing`` [m] (and, on a block of
    ``young`` trees, the satellite radius their size)."""
    young_satellites = young and params.satellite_radius is None
    params = params.at_spacing(spacing)
    if young_satellites:
        # a satellite is a crown's foliage touching down: its reach follows the trees' size
        # as well as their spacing (young, dormant trees have no foliage to reach 2 m out)
        shrink = (params.min_tree_height / MATURE_FLOORS["min_tree_height"]) ** SPACING_RADII["trunks"]["satellite_radius"][1]
        params = params.model_copy(update={"satellite_radius": params.satellite_radius * shrink})
    return params


def _trunk_tests(
    candidates: dict, nodes: np.ndarray, node_height: np.ndarray, *, foot_xy: np.ndarray | None,
    stem_xy: np.ndarray | None, stem_slice: np.ndarray | None, params: TrunkParams,
) -> tuple[np.ndarray, np.ndarray]:
    """The groups that are trunks: each group's own tests (size, height, box, width,
    foot), then the tests between neighbours (:func:`pipeline.neighbours.accept`). Adds ``foot``, ``stem``,
    ``bole`` (a column to above the tallest post: no post), ``own_stem``, ``pooled_support`` and ``accepted``
    to ``candidates``.

    Returns (g,) bool accepted and (g,) float64 pooled catchment."""
    cx, cy, width, g_support, fits = (candidates[k] for k in ("x", "y", "width", "support", "fits"))
    ok = fits & (width <= params.max_trunk_width)
    centre = np.column_stack([cx, cy])
    foot = foot_ratio(centre, foot_xy)
    candidates["foot"] = foot
    ok &= foot >= params.min_foot_ratio
    stem = np.full(cx.size, np.nan)
    if params.stem_ratio > 0:
        stem[ok] = stem_contrast(centre[ok], stem_xy, stem_slice, n_slices=STEM_SLICES)
    candidates["stem"] = stem
    own = np.zeros(cx.size, bool)
    # a bole: its catchment goes on above where a trellis post would end (no orchard form
    # of the simulator reaches that high: on orchards these tests are as before)
    tall = ok & (candidates["top"] >= params.max_post_height)
    if ok.any() and np.median(candidates["top"][ok]) >= params.max_post_height:
        # a stand of trees taller than any post: a dominated tree's catchment may end lower
        tall = ok.copy()
    own[tall] = own_stems(centre[tall], nodes, node_height) & (stem[tall] >= COLUMN_MIN_STEM)
    # or a column unbroken from the ground to above the tallest post, whatever its stem
    # score and wherever its catchment ends (taller neighbours drain the interlocking crowns
    # above a dominated stem): a bole, no post, and never a neighbour's shoots or satellite
    bole = np.zeros(cx.size, bool)
    bole[ok] = own_stems(centre[ok], nodes, node_height, top=params.max_post_height + BOLE_ABOVE_POST)
    candidates["bole"] = bole
    candidates["own_stem"] = own | bole
    ok, support = accept(centre, g_support, stem, ok, fits & (width > params.max_trunk_width), params, own | bole)
    candidates["pooled_support"] = support
    candidates["accepted"] = ok.copy()
    return ok, support


def _sources(
    nodes: np.ndarray, cand: np.ndarray, groups: np.ndarray, gidx: np.ndarray, candidates: dict, sel: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Segmentation sources of the accepted groups ``sel``: each group's contact nodes
    near its centre, and its leader. Returns (s,) int64 nodes and (s,) int64 trunk of each."""
    centre = np.column_stack([candidates["x"], candidates["y"]])
    width = candidates["width"]
    remap = np.full(groups.size, -1, np.int64)
    remap[sel] = np.arange(sel.size)
    t_of_cand = remap[gidx]
    near = t_of_cand >= 0
    d2 = ((nodes[cand, :2] - centre[gidx]) ** 2).sum(1)
    near &= d2 <= (np.maximum(width[gidx] / 2, SOURCE_MIN_RADIUS) + SOURCE_MARGIN) ** 2
    src = cand[near]
    src_t = t_of_cand[near]
    # the leader always seeds its trunk
    lead_nodes = cand[groups[sel]]
    src = np.concatenate([src, lead_nodes])
    src_t = np.concatenate([src_t, np.arange(sel.size)])
    src, first = np.unique(src, return_index=True)
    return src, src_t[first]


def box_like_trees(
    node_tree: np.ndarray,
    node_height: np.ndarray,
    *,
    nodes: np.ndarray,
    trunk_xy: np.ndarray,
    planar: np.ndarray,
    params: TrunkParams,
    radius: float = BOX_TEST_RADIUS,
) -> np.ndarray:
    """Trees (0-based) whose segmented material near the trunk and low down is too planar.

    The object-level twin of the catchment test in :func:`detect_trunks`: a vehicle
    wheel may drain little by itself, but once segmented its "tree" is the vehicle's
    body. Only material below ``min_tree_height`` and within ``radius`` [m] of the
    trunk counts, so a real tree whose crown overhangs a vehicle is kept.

    Returns
    -------
    (j,) int64 indices of trunks to drop.
    """
    k = trunk_xy.shape[0]
    low = (node_tree > 0) & (node_height < params.at_floors().min_tree_height)
    idx = np.flatnonzero(low)
    t = node_tree[idx] - 1
    near = ((nodes[idx, :2] - trunk_xy[t]) ** 2).sum(1) <= radius**2
    idx, t = idx[near], t[near]
    n_low = np.bincount(t, minlength=k).astype(np.float64)
    n_pl = np.bincount(t, weights=planar[idx].astype(np.float64), minlength=k)
    return np.flatnonzero(n_pl > params.max_planar_fraction * np.maximum(n_low, 1))


def low_trees(node_tree: np.ndarray, node_height: np.ndarray, k: int, *, params: TrunkParams) -> np.ndarray:
    """Trees (0-based) whose segmented material fails the height test of
    :func:`detect_trunks`: its TOP_PERCENTILE lies below ``min_tree_height``.

    The catchment passed the test, but segmentation can leave a "tree" much lower: the
    surfaces of a vehicle under a crown are cut out of the graph after detection, and
    what is left of such a trunk's catchment is grass and a wheel.

    Returns
    -------
    (j,) int64 indices of trunks to drop.
    """
    top = group_percentile(node_height, np.asarray(node_tree, dtype=np.int64) - 1, k, TOP_PERCENTILE)
    return np.flatnonzero(top < params.at_floors().min_tree_height)  # unset: the mature trees' floor


def drop_trunks(det: TrunkDetection, drop: np.ndarray) -> TrunkDetection:
    """The detection without the trunks in ``drop`` (0-based), renumbered."""
    keep = np.ones(det.k, bool)
    keep[drop] = False
    remap = np.cumsum(keep) - 1
    src_keep = keep[det.source_trunk]
    return TrunkDetection(
        det.xy[keep],
        det.support[keep],
        det.width[keep],
        det.source_nodes[src_keep],
        remap[det.source_trunk[src_keep]],
        det.candidates,
        det.spacing,
        None if det.young is None else det.young[keep],
        None if det.on_slot is None else det.on_slot[keep],
        det.floors,
        None if det.own_stem is None else det.own_stem[keep],
    )
