"""Individual-tree segmentation by shortest path from all trunks at once."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from pipeline.graph import ShortestPaths, shortest_paths, without_nodes
from pipeline.metrics import group_runs, tree_circles
from pipeline.nearby import CellIndex, near_centres
from pipeline.passes import indices_where
from pipeline.params import SegmentParams
from pipeline.refine import refine_contested

# Fixed tuning of segmentation (lengths in metres).

#: rounds in which small floating fragments may join a tree through fragments that joined
#: the round before (each round reaches ``fragment_reach`` farther into a sparse rim)
RIM_ROUNDS = 10
#: a tree's height, for its reach, is that of the highest node this close [m] to its
#: trunk, whatever tree that node is given to: within PATH_MARGIN, so a tile holds all of
#: them for every trunk whose material can reach its core (tiled equals untiled)
HEIGHT_ZONE = 1.0
#: a fragment the search did not reach joins a tree only if its nearest node lies within
#: this many times the tree's reached crown radius (its farthest reached node from its
#: trunk, horizontally) of the trunk: a sparse crown's own fragments start within 1.42
#: times it (the AdTree row), a fence wire or a post's top beside a hedge 3.4-4.7 times
#: (docs/limits.md)
FRAGMENT_SPREAD = 2.0
#: the reached crown radius counts as at least this [m] for FRAGMENT_SPREAD: a tree whose
#: search reached little more than its trunk (a sparse scan) still takes the fragments of
#: its crown
MIN_REACHED_RADIUS = 1.0
#: a trunk's circle for its foot is fitted to its points in a slice this thick [m] just
#: above the ground layer
FOOT_SLICE = 0.25


@dataclass(frozen=True)
class Segmentation:
    """Tree of each graph node.

    Attributes
    ----------
    node_tree : (m,) int64 — 0 = no tree, k = trunk k-1
    paths : ShortestPaths — the multi-source shortest-path forest rooted at the trunks
    reached : (m,) bool — nodes the graph search reached (the rest were labelled by distance)
    """

    node_tree: np.ndarray
    paths: ShortestPaths
    reached: np.ndarray


def segment_nodes(
    nodes: np.ndarray,
    graph: sparse.csr_matrix,
    *,
    source_nodes: np.ndarray,
    source_trunk: np.ndarray,
    trunk_xy: np.ndarray,
    node_height: np.ndarray,
    params: SegmentParams,
    exclude: np.ndarray | None = None,
) -> Segmentation:
    """Give every node to the trunk it reaches by the shortest path.

    One multi-source Dijkstra from every trunk's source nodes: each node goes to the
    trunk whose path to it is shortest (the paper's rule, without a search per trunk).
    Nodes farther than their tree's reach horizontally from their trunk are dropped
    (paths that leak into other objects): ``crown_radius``, or ``crown_per_height``
    times the tree's height for a taller tree, up to ``max_crown_radius``
    (:func:`tree_reach`). Nodes the search does not reach are labelled
    by distance, the paper's proposed fix, per connected fragment: a fragment floating
    above ``floating_height`` is canopy the graph could not bridge (sparse scans) and
    takes the tree of the nearest labelled node; a fragment standing on the ground is a
    separate object (fence post, vehicle, grass) and only its nodes within
    ``unreached_radius`` of a tree join it, and so does a floating fragment that
    touched an excluded node (what is left of a vehicle or a bin once its faces are cut
    out: its roof, its edges). Either way within the tree's reach, and within
    ``FRAGMENT_SPREAD`` times the radius of the tree's reached crown of its trunk (a
    fence wire beside a row's end tree is no part of it). A floating fragment of at
    least ``min_fragment`` nodes goes whole to the tree most of its nodes took (a
    sparsely scanned limb is not split where it passes into a neighbour's crown), but
    for nodes beyond that tree's reach.
    Fragments smaller than ``min_fragment`` nodes are outliers and stay unlabelled,
    unless they float within ``fragment_reach`` of a labelled node (sparse leaves at the
    crown's rim, which the scanner saw only once), or of such a fragment that has joined
    (up to ``RIM_ROUNDS`` links: the rim of a sparsely scanned crown).

    Parameters
    ----------
    nodes : (m, 3) float64 [m]
    graph : (m, m) csr_matrix
    source_nodes : (s,) int64 — seed nodes
    source_trunk : (s,) int64 — 0-based trunk of each seed
    trunk_xy : (k, 2) float64 [m]
    node_height : (m,) float64 — height above ground [m]
    params : SegmentParams — radii set from the block's spacing
        (:meth:`SegmentParams.at_spacing`); any still unset take their caps
    exclude : (m,) bool, optional — nodes that are never tree material (see
        ``hard_surfaces``): no path passes through them and they stay 0

    Returns
    -------
    Segmentation
    """
    params = params.at_spacing(None)  # radii still unset: the free-standing trees' values
    on_object = None
    if exclude is not None and exclude.any():
        exclude = exclude.copy()
        exclude[source_nodes] = False  # a trunk's seeds stay, whatever stands beside it
        on_object = _beside_excluded(graph, exclude)
        graph = without_nodes(graph, exclude)
    sp = shortest_paths(graph, source_nodes)
    node_tree, reached = _path_labels(sp, source_nodes, source_trunk)
    reach = tree_reach(nodes, node_height, trunk_xy, params=params)
    if trunk_xy.shape[0]:
        node_tree, reached = _within_reach(nodes, node_tree, reached, trunk_xy, reach)
    if params.method == "refined":
        node_tree = refine_contested(graph, node_tree, sp.dist, margin=params.contest_margin)
    node_tree = _label_unreached(nodes, graph, node_tree, trunk_xy, node_height, reach, params=params, exclude=exclude,
                                 on_object=on_object)
    return Segmentation(node_tree, sp, reached)


def _path_labels(sp: ShortestPaths, source_nodes: np.ndarray, source_trunk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tree of each node (1-based, 0 = unreached) by the trunk its shortest path starts
    at, and the nodes reached, (m,) int64 and (m,) bool."""
    trunk_of_node = np.full(sp.source.shape[0], -1, np.int64)
    trunk_of_node[source_nodes] = source_trunk
    node_tree = np.zeros(sp.source.shape[0], np.int64)
    reached = sp.source >= 0
    node_tree[reached] = trunk_of_node[sp.source[reached]] + 1
    return node_tree, reached


def tree_reach(nodes: np.ndarray, node_height: np.ndarray, trunk_xy: np.ndarray, *, params: SegmentParams) -> np.ndarray:
    """How far [m] each tree's material may reach from its trunk, horizontally, (k,) float64.

    ``crown_radius``, or ``crown_per_height`` times the tree's height where that is
    more (a wide old tree), never more than ``max_crown_radius`` (which sets the tile
    buffer). The height is that of the highest node within HEIGHT_ZONE of the trunk.
    """
    height = np.zeros(trunk_xy.shape[0])
    # only nodes tall enough to reach beyond crown_radius can change a reach (none when
    # the cap allows no more, as by default): the search skips the rest of the block
    tall = np.zeros(0, np.int64)
    if params.crown_per_height > 0 and params.max_crown_radius > params.crown_radius:
        tall = np.flatnonzero(node_height > params.crown_radius / params.crown_per_height)
    if trunk_xy.shape[0] and tall.size:
        near = cKDTree(nodes[tall, :2]).query_ball_point(trunk_xy, HEIGHT_ZONE)
        height = np.array([node_height[tall[i]].max() if len(i) else 0.0 for i in near])
    reach = np.maximum(params.crown_radius, params.crown_per_height * height)
    return np.minimum(reach, params.max_crown_radius)


def _within_crown(nodes: np.ndarray, idx: np.ndarray, tree: np.ndarray, trunk_xy: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Nodes ``idx`` lie within ``reach`` [tree - 1] (horizontally) of trunk ``tree`` (1-based), (i,) bool."""
    return ((nodes[idx, :2] - trunk_xy[tree - 1]) ** 2).sum(1) <= reach[tree - 1] ** 2


def _within_reach(nodes, node_tree, reached, trunk_xy, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``node_tree`` and ``reached`` without the nodes farther than their tree's ``reach``
    [m] horizontally from their trunk (paths that leak into other objects)."""
    node_tree, reached = node_tree.copy(), reached.copy()
    idx = np.flatnonzero(reached)
    idx = idx[~_within_crown(nodes, idx, node_tree[idx], trunk_xy, reach)]
    node_tree[idx] = 0
    reached[idx] = False
    return node_tree, reached


def _join_nearest(nodes, node_tree, trunk_xy, cand: np.ndarray, lab: np.ndarray, bound, reach: float,
                  crown_reach: np.ndarray) -> np.ndarray:
    """Give each node of ``cand`` the tree of its nearest node of ``lab`` where that lies
    within ``bound`` [m] (scalar or per node; searched up to ``reach``) and the node lies
    within its tree's ``crown_reach`` (per tree) of its trunk; labels ``node_tree`` in
    place and returns the nodes that joined."""
    tree_of = cKDTree(nodes[lab])
    bound = np.broadcast_to(np.minimum(bound, reach), cand.shape)
    d, j = np.full(cand.shape, np.inf), np.zeros(cand.shape, np.int64)
    # one search per distinct bound: a node far from every tree is given up on at its
    # own bound, not at the widest one (the same nearest node wherever one is in reach)
    for b in np.unique(bound[bound >= 0]):
        sel = np.flatnonzero(bound == b)
        d[sel], j[sel] = tree_of.query(nodes[cand[sel]], distance_upper_bound=b * (1 + 1e-9) + 1e-12)
    hit = np.isfinite(d) & (d <= bound)
    tree = node_tree[lab[j[hit]]]
    ok = _within_crown(nodes, cand[hit], tree, trunk_xy, crown_reach)  # the fallback must also respect the crown reach
    node_tree[cand[hit][ok]] = tree[ok]
    return cand[hit][ok]


def _fragment_majority(nodes, node_tree, joined: np.ndarray, comp: np.ndarray, vote: np.ndarray, trunk_xy,
                       crown_reach: np.ndarray) -> None:
    """Give the ``joined`` nodes of each fragment (``comp`` of each node) that may
    ``vote`` the tree most of them joined, where they lie within its ``crown_reach``
    (per tree) of its trunk; relabels ``node_tree`` in place."""
    idx = joined[vote[joined]]
    if idx.size == 0:
        return
    pairs, count = np.unique(np.c_[comp[idx], node_tree[idx]], axis=0, return_counts=True)
    # most nodes first, then the lower tree: one winner per fragment, whatever the nodes' order
    pairs = pairs[np.lexsort((pairs[:, 1], -count, pairs[:, 0]))]
    first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
    winner = np.zeros(comp.max(initial=-1) + 1, np.int64)
    winner[pairs[first, 0]] = pairs[first, 1]
    tree = winner[comp[idx]]
    ok = (tree != node_tree[idx]) & _within_crown(nodes, idx, tree, trunk_xy, crown_reach)
    node_tree[idx[ok]] = tree[ok]


def _reached_radius(nodes: np.ndarray, node_tree: np.ndarray, trunk_xy: np.ndarray) -> np.ndarray:
    """Farthest labelled node of each tree from its trunk, horizontally [m], at least
    MIN_REACHED_RADIUS, (k,) float64."""
    out = np.full(trunk_xy.shape[0], MIN_REACHED_RADIUS)
    idx = np.flatnonzero(node_tree > 0)
    t = node_tree[idx] - 1
    np.maximum.at(out, t, np.hypot(*(nodes[idx, :2] - trunk_xy[t]).T))
    return out


def _drop_far_fragments(nodes, node_tree, joined: np.ndarray, comp: np.ndarray, trunk_xy, limit: np.ndarray) -> np.ndarray:
    """Unlabel (in ``node_tree``, in place) the ``joined`` nodes of each fragment (``comp``
    of each node) whose nearest node to the trunk of the tree they joined lies farther
    than ``limit`` [tree - 1] [m] from it, horizontally; returns the nodes that stay."""
    t = node_tree[joined] - 1
    d = np.hypot(*(nodes[joined, :2] - trunk_xy[t]).T)
    _, part = np.unique(np.c_[comp[joined], t], axis=0, return_inverse=True)
    part = part.ravel()
    nearest = np.full(part.max(initial=-1) + 1, np.inf)
    np.minimum.at(nearest, part, d)
    far = nearest[part] > limit[t]
    node_tree[joined[far]] = 0
    return joined[~far]


def _beside_excluded(graph: sparse.csr_matrix, exclude: np.ndarray) -> np.ndarray:
    """Nodes not in ``exclude`` with an edge to one that is, (m,) bool."""
    touch = np.asarray(graph @ exclude.astype(np.float64)).ravel() > 0
    return touch & ~exclude


def _label_unreached(nodes, graph, node_tree, trunk_xy, node_height, reach: np.ndarray, *, params: SegmentParams,
                     exclude: np.ndarray | None, on_object: np.ndarray | None = None) -> np.ndarray:
    """``node_tree`` with the nodes the search did not reach labelled by distance, per
    connected fragment (see :func:`segment_nodes`)."""
    node_tree = node_tree.copy()
    labelled = node_tree > 0
    todo = np.flatnonzero(~labelled if exclude is None else ~labelled & ~exclude)
    if not (todo.size and labelled.any()):
        return node_tree
    _, comp = csgraph.connected_components(graph[todo][:, todo], directed=False)
    low = np.full(comp.max() + 1, np.inf)
    np.minimum.at(low, comp, node_height[todo])
    floating = low[comp] > params.floating_height
    if on_object is not None and on_object[todo].any():
        # a fragment left of a cut-out object stands with it, however high it floats
        part_of_object = np.zeros(comp.max() + 1, bool)
        part_of_object[comp[on_object[todo]]] = True
        floating &= ~part_of_object[comp]
    widest = float(reach.max(initial=0.0))
    bound = np.where(floating, widest, params.unreached_radius)
    big = np.bincount(comp)[comp] >= params.min_fragment
    # a small fragment is an outlier unless it floats right beside a tree (a lone leaf at the rim)
    bound = np.where(big, bound, np.where(floating, params.fragment_reach, -1.0))
    spread = FRAGMENT_SPREAD * _reached_radius(nodes, node_tree, trunk_xy)
    joined = _join_nearest(nodes, node_tree, trunk_xy, todo, np.flatnonzero(labelled), bound,
                           max(widest, params.unreached_radius), reach)
    fragment = np.full(node_tree.size, -1, np.int64)  # each unreached node's fragment
    fragment[todo] = comp
    # a floating fragment is one piece of canopy (a sparsely scanned limb): it goes whole
    # to the tree most of its nodes are nearest, not split where it passes into a
    # neighbour's crown
    vote = np.zeros(node_tree.size, bool)
    vote[todo[big & floating]] = True
    _fragment_majority(nodes, node_tree, joined, fragment, vote, trunk_xy, reach)
    joined = _drop_far_fragments(nodes, node_tree, joined, fragment, trunk_xy, spread)
    # small floating fragments also join through fragments that have just joined (a
    # sparsely scanned crown's rim: a chain of lone leaves). The nodes labelled before
    # a round are all beyond fragment_reach of the rest, so each round only searches
    # the nodes that joined in the round before.
    rim = todo[~big & floating]
    for _ in range(RIM_ROUNDS):
        rim = rim[node_tree[rim] == 0]
        if rim.size == 0 or joined.size == 0:
            break
        joined = _join_nearest(nodes, node_tree, trunk_xy, rim, joined, params.fragment_reach, params.fragment_reach,
                               reach)
    return node_tree


def planar_patches(graph: sparse.csr_matrix, planar: np.ndarray, normal: np.ndarray | None = None,
                   min_cos: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Connected sets of planar nodes over ``graph``.

    With ``normal`` (m, 3) unit normals, two planar neighbours connect only where their
    normals agree (|cos| at least ``min_cos``): a face does not run on into leaves
    touching it.

    Returns
    -------
    patch : (m,) int64 — patch of each node, -1 for nodes that are not planar
    size : (c,) int64 — nodes per patch
    """
    patch = np.full(planar.shape[0], -1, np.int64)
    idx = np.flatnonzero(planar)
    if idx.size == 0:
        return patch, np.zeros(0, np.int64)
    sub = graph[idx][:, idx]
    if normal is not None:
        sub = sub.tocoo()
        n = normal[idx]
        keep = np.abs((n[sub.row] * n[sub.col]).sum(axis=1)) >= min_cos
        sub = sparse.csr_matrix((sub.data[keep], (sub.row[keep], sub.col[keep])), shape=sub.shape)
    _, comp = csgraph.connected_components(sub, directed=False)
    patch[idx] = comp
    return patch, np.bincount(comp)


def curved_patches(
    nodes: np.ndarray,
    normals: np.ndarray,
    patch: np.ndarray,
    size: np.ndarray,
    *,
    min_nodes: int,
    min_spread: float,
    max_radius: float,
    max_residual: float,
) -> np.ndarray:
    """Patches that are part of a cylinder (the bark of a thick trunk), (c,) bool.

    A thick trunk's bark is locally flat, so it passes the planarity test, and its
    patches are as large as a box's face. A face's normals are all parallel; a
    cylinder's turn around its axis and, seen along the axis, all point away from it.
    A patch is curved when its normals spread around an axis (the middle eigenvalue of
    their mean outer product is at least ``min_spread``) and, in the cross-section
    across that axis, the lines along its normals pass within ``max_residual`` times the
    radius of one centre, at most ``max_radius`` away. Two faces meeting at a corner
    spread their normals too, but their normal lines are parallel within each face and
    meet no common centre.

    Parameters
    ----------
    nodes : (m, 3) float64 [m]
    normals : (m, 3) float64 — unit normal of each node (sign arbitrary)
    patch, size : from :func:`planar_patches`
    min_nodes : int — smaller patches are not tested (False)
    min_spread : float — least middle eigenvalue of the normals' mean outer product
    max_radius : float — widest cylinder [m]
    max_residual : float — largest RMS distance of the normal lines from the centre,
        as a fraction of the radius

    Returns
    -------
    (c,) bool
    """
    out = np.zeros(size.shape[0], bool)
    idx = np.flatnonzero(faces(patch, size, min_nodes))
    if idx.size == 0:
        return out
    order, ids, start, _ = group_runs(patch[idx])
    idx = idx[order]
    for pid, part in zip(ids, np.split(idx, start[1:])):
        n = normals[part]
        w, v = np.linalg.eigh(n.T @ n / part.size)
        if w[1] < min_spread:
            continue  # one direction: a flat face
        across = v[:, 1:]  # the cross-section plane, normal to the axis v[:, 0]
        q = (nodes[part] - nodes[part].mean(axis=0)) @ across
        n2 = n @ across
        n2 /= np.maximum(np.linalg.norm(n2, axis=1, keepdims=True), 1e-12)
        off_line = np.eye(2)[None] - n2[:, :, None] * n2[:, None, :]  # projects off each normal line
        centre = np.linalg.lstsq(off_line.sum(axis=0), np.einsum("kij,kj->i", off_line, q), rcond=None)[0]
        d = q - centre
        residual = np.sqrt((np.einsum("kij,kj->ki", off_line, d) ** 2).sum(axis=1).mean())
        radius = np.linalg.norm(d, axis=1).mean()
        out[pid] = radius <= max_radius and residual <= max_residual * radius
    return out


def flat_patches(normals: np.ndarray, patch: np.ndarray, size: np.ndarray, *, min_align: float) -> np.ndarray:
    """Patches whose normals point one way, (c,) bool.

    A patch is flat when the largest eigenvalue of its normals' mean outer product is at
    least ``min_align`` (1: all parallel). A box's face is; the bark of a trunk (normals
    turning around its axis) and the envelope of a dense crown (turning every way) are not.

    Parameters
    ----------
    normals : (m, 3) float64 — unit normal of each node (sign arbitrary)
    patch, size : from :func:`planar_patches`
    min_align : float — in [1/3, 1]

    Returns
    -------
    (c,) bool
    """
    c = size.shape[0]
    on = np.flatnonzero(patch >= 0)
    if c == 0 or on.size == 0:
        return np.zeros(c, bool)
    n, p = normals[on], patch[on]
    outer = np.stack([np.bincount(p, weights=n[:, i] * n[:, j], minlength=c) for i in range(3) for j in range(3)], axis=1)
    outer = outer.reshape(c, 3, 3) / np.maximum(size, 1)[:, None, None]
    return np.linalg.eigvalsh(outer)[:, -1] >= min_align


def faces(patch: np.ndarray, size: np.ndarray, min_nodes: int) -> np.ndarray:
    """Nodes in patches of at least ``min_nodes`` nodes, (m,) bool.

    ``patch``, ``size`` from :func:`planar_patches`. A box's face is one large patch; the
    bark of a sparsely scanned trunk looks planar only in small patches.
    """
    if size.size == 0:
        return np.zeros(patch.shape[0], bool)
    return (patch >= 0) & (size[np.maximum(patch, 0)] >= min_nodes)


def standing(patch: np.ndarray, size: np.ndarray, node_height: np.ndarray, *, min_top: float) -> np.ndarray:
    """Nodes in patches whose highest node stands above ``min_top`` [m], (m,) bool.

    ``patch``, ``size`` from :func:`planar_patches`; ``node_height`` above the ground [m].
    A box's or a vehicle's faces stand up from the ground; flat grass tops lie below.
    """
    out = np.zeros(patch.shape[0], bool)
    idx = np.flatnonzero(patch >= 0)
    if idx.size == 0:
        return out
    top = np.full(size.shape[0], -np.inf)
    np.maximum.at(top, patch[idx], node_height[idx])
    out[idx] = top[patch[idx]] > min_top
    return out


def hard_surfaces(
    nodes: np.ndarray,
    patch: np.ndarray,
    size: np.ndarray,
    node_height: np.ndarray,
    *,
    min_nodes: int,
    margin: float,
    min_top: float,
) -> np.ndarray:
    """Nodes of large planar surfaces standing above the grass, and those next to them.

    A vehicle parked under a crown, a bin or a wall touches the foliage, so shortest
    paths from the trunk run over it. Trees have no large flat parts (a thick trunk's
    bark does, but it is curved: leave it out of ``patch``, see :func:`curved_patches`).
    Grass patches are planar too but stay below ``min_top``.

    Parameters
    ----------
    nodes : (m, 3) float64 [m]
    patch : (m,) int64 — planar patch of each node, -1 = none (:func:`planar_patches`)
    size : (c,) int64 — nodes per patch
    node_height : (m,) float64 — height above ground [m]
    min_nodes : int — least size of a surface [nodes]; 0 = no surfaces
    margin : float — nodes this close to a surface are part of the object [m]
    min_top : float — a surface's highest node must stand above this [m]

    Returns
    -------
    (m,) bool
    """
    m = nodes.shape[0]
    out = np.zeros(m, bool)
    idx = np.flatnonzero(patch >= 0)
    if min_nodes <= 0 or idx.size < min_nodes:
        return out
    comp = patch[idx]
    top = np.full(size.shape[0], -np.inf)
    np.maximum.at(top, comp, node_height[idx])
    surface = idx[faces(patch, size, min_nodes)[idx] & (top[comp] > min_top)]
    if surface.size == 0:
        return out
    d, _ = cKDTree(nodes[surface]).query(nodes, distance_upper_bound=margin + 1e-9)
    return np.isfinite(d)


def trunk_feet(
    xyz: np.ndarray,
    tree_id: np.ndarray,
    is_ground: np.ndarray,
    height: np.ndarray,
    trunk_xy: np.ndarray,
    *,
    ground_top: float,
    margin: float,
    max_radius: float,
    slice_height: float = FOOT_SLICE,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground points that are the foot of a trunk.

    Ground removal takes everything within ``ground_top`` of the ground surface,
    including the bottom of every trunk. Nothing but the trunk stands inside the trunk's
    cross-section, so the ground points within its circle (fitted to the tree's points
    in a slice just above ``ground_top``) plus ``margin`` belong to the tree.

    Parameters
    ----------
    xyz : (n, 3) float64 [m]
    tree_id : (n,) int64 — 0 = no tree, k = trunk k-1
    is_ground : (n,) bool
    height : (n,) float — height above ground [m]
    trunk_xy : (k, 2) float64 [m]
    ground_top : float — ground points lie below this height [m]
    margin : float — widening of the fitted circle (noise, the flare at the base) [m]
    max_radius : float — a fitted circle larger than this, or centred farther than this
        from the trunk, is not a trunk's and is ignored [m]
    slice_height : float — thickness of the slice the circle is fitted to [m]

    Returns
    -------
    idx : (f,) int64 — the foot points (ground points to relabel)
    src : (f,) int64 — for each, the nearest slice point of its tree, whose labels it takes
    """
    k = trunk_xy.shape[0]
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
    gidx = np.flatnonzero(is_ground)
    if k == 0 or gidx.size == 0:
        return empty
    top = ground_top + slice_height
    cand = indices_where(tree_id.shape[0], lambda s: (tree_id[s] > 0) & (height[s] >= ground_top) & (height[s] < top))
    own = trunk_xy[tree_id[cand] - 1]
    cand = cand[((xyz[cand, :2] - own) ** 2).sum(1) <= max_radius**2]
    if cand.size == 0:
        return empty
    centres, radii = tree_circles(xyz[cand, :2], tree_id[cand], k)
    off = np.hypot(*(centres - trunk_xy).T)
    trunk_like = np.flatnonzero(np.isfinite(radii) & (radii <= max_radius) & (off <= max_radius))
    if trunk_like.size == 0:
        return empty
    # the ground points in the cells around some trunk's circle can be a foot (one pass
    # over them); each trunk then looks at its own disc of those through one k-d tree
    reaches = radii[trunk_like] + margin
    query = reaches * (1 + 1e-9) + 1e-12
    gidx = gidx[near_centres(xyz[gidx, :2], centres[trunk_like], float(query.max()))]
    if gidx.size == 0:
        return empty
    order, uniq, start, counts = group_runs(tree_id[cand])  # each tree's slice points, in input order
    first = dict(zip(uniq.tolist(), zip(start.tolist(), counts.tolist())))
    # the cells' ball at the widest reach holds every point of each trunk's own (the
    # exact test below keeps the same points a k-d tree's ball at its reach gave, in the
    # same order), for a sort of cell keys instead of a k-d tree and lists of hits
    cells = CellIndex(xyz[gidx, :2], float(query.max()))
    idx, src = [], []
    for t, reach in zip(trunk_like, reaches):
        c = centres[t]
        win = gidx[cells.ball(c)]
        foot = win[((xyz[win, :2] - c) ** 2).sum(1) <= reach**2]  # the exact test
        if foot.size == 0:
            continue
        s0, n0 = first[t + 1]
        pts = cand[order[s0 : s0 + n0]]
        _, j = cKDTree(xyz[pts]).query(xyz[foot])
        idx.append(foot)
        src.append(pts[j])
    if not idx:
        return empty
    return np.concatenate(idx).astype(np.int64), np.concatenate(src).astype(np.int64)
