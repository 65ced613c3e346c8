"""Which points of a trunk's slice are its stem: the pieces a stem circle is fitted to.

A slice 0.3 m above a young tree's base also holds an irrigation riser or a stake
0.15-0.4 m from the stem when the segmentation gave it to the tree; a circle through
both spans them (0.35-0.52 m for stems of 0.06-0.09 m) and pulls the trunk's position
toward the riser. A stem's surface is one piece, or arcs about a diameter apart where
the scan saw it from two sides; a pipe beside it lies farther from the stem than the
stem is wide. A young tree's stake stands closer (6-12 cm) and, blurred by the scan's
noise, in the stem's piece: on a block of young trees the piece is split once more where
it is two sections side by side.
"""

from __future__ import annotations

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from pipeline.circles import fit_circle
from pipeline.floors import group_percentile

#: points of one surface lie closer than this [m], or than LINK_SPACINGS times the
#: slice's median point spacing where the scan is sparser
MIN_LINK = 0.03
LINK_SPACINGS = 3.0
#: a piece of fewer points gives no circle to tell the stem by
MIN_PIECE = 6
#: a slice of more pieces, the largest holding a smaller share of its points, is a
#: sparse scan's ring in fragments (a stem, a riser, a stake and twigs are a few)
MIN_SHARE = 0.5
MAX_PIECES = 6
#: two parts of one piece are two things side by side where their centres lie this many
#: times the parts' spread (RMS along the line through them, summed) apart: one blob
#: split at its mean gives 1.33 (a normal), a stem and a stake 6-12 cm apart 1.6-3
SPLIT_SEPARATION = 1.6


def stem_points(xy: np.ndarray, tree: np.ndarray, *, stakes: bool = False) -> np.ndarray:
    """(n,) bool: the points of each tree's slice that are its stem.

    Each tree's slice is split into pieces (points linked closer than its link length);
    the stem is the piece with the most points and every piece with a point on or inside
    that piece's circle (:func:`pipeline.circles.fit_circle`, widened by the larger of the
    link length and half its radius) or within the piece's extent (bounding-box diagonal):
    the other side of a stem seen from two alleys lies on that circle, a riser or stake
    beside the stem outside it. A slice of one piece, or whose largest piece holds fewer
    than :data:`MIN_PIECE` points, or which is in more than :data:`MAX_PIECES` pieces
    none holding :data:`MIN_SHARE` of its points, is kept whole.

    With ``stakes`` (a block of young trees, each tied to a stake) the stem's points are
    split once more where they are two things side by side (:func:`_beside_stake`): a
    stake 6-12 cm from a young stem, as thick as it, touches the stem's piece under the
    scan's noise. One of the two sections is kept, for its diameter: both are about the
    stem's size, but which one is the stem is not known. Not on grown blocks: a grown
    stem of 4-6 cm radius under 2 cm of noise looks the same as two such sections.

    Parameters
    ----------
    xy : (n, 2) float64 — the slices' points [m]
    tree : (n,) int64 — the tree (trunk) of each point
    stakes : bool — the trees may have a stake touching their stem
    """
    n = xy.shape[0]
    keep = np.ones(n, bool)
    if n < 3:
        return keep
    kd = cKDTree(xy, balanced_tree=False, compact_nodes=False)
    nearest = kd.query(xy, k=2)[0][:, 1]
    trees, inv = np.unique(tree, return_inverse=True)
    spacing = group_percentile(nearest, inv, trees.size, 50.0)
    link = np.maximum(MIN_LINK, LINK_SPACINGS * spacing)
    pairs = kd.query_pairs(float(link.max()), output_type="ndarray")
    if pairs.size:
        same = inv[pairs[:, 0]] == inv[pairs[:, 1]]
        pairs = pairs[same]
        d = np.hypot(*(xy[pairs[:, 0]] - xy[pairs[:, 1]]).T)
        pairs = pairs[d <= link[inv[pairs[:, 0]]]]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, piece = connected_components(graph, directed=False)
    # pieces are numbered within trees' points in any order: one tree may own several
    pieces_of_tree = np.bincount(inv[np.unique(piece, return_index=True)[1]], minlength=trees.size)
    for t in np.flatnonzero(pieces_of_tree > 1):
        own = np.flatnonzero(inv == t)
        keep[own] = _grown_stem(xy[own], piece[own], link[t])
    for t in range(trees.size if stakes else 0):
        own = np.flatnonzero((inv == t) & keep)
        if own.size >= 2 * MIN_PIECE:
            keep[own] = _beside_stake(xy[own])
    return keep


def _grown_stem(xy: np.ndarray, piece: np.ndarray, link: float) -> np.ndarray:
    """(m,) bool: one tree's stem among its slice's pieces (see :func:`stem_points`)."""
    labels, sizes = np.unique(piece, return_counts=True)
    fragments = sizes.max() < MIN_SHARE * piece.shape[0] and labels.size > MAX_PIECES
    if sizes.max() < MIN_PIECE or fragments:
        return np.ones(piece.shape[0], bool)  # too few points to say what the stem is
    inner = xy[piece == labels[np.argmax(sizes)]]
    centre, radius = fit_circle(inner, solid=True)
    if not np.isfinite(radius):
        return np.ones(piece.shape[0], bool)
    # a piece with a point on or inside the main piece's circle is more of that stem, and
    # so is one within the main piece's own extent (a short arc's circle is uncertain)
    reach = max(float(np.hypot(*(inner.max(axis=0) - inner.min(axis=0)))), link)
    near = cKDTree(inner).query(xy, distance_upper_bound=reach)[0] <= reach
    inside = near | (np.hypot(*(xy - centre).T) <= radius + max(link, 0.5 * radius))
    return np.isin(piece, np.unique(piece[inside]))


def _beside_stake(xy: np.ndarray) -> np.ndarray:
    """(m,) bool: the stem of a young tree's slice that may hold its stake (see :func:`stem_points`).

    The points are split in two (k-means); the parts are two sections side by side where
    their centres lie SPLIT_SEPARATION times their spread apart and the circles fitted to
    each (:func:`pipeline.circles.fit_circle`) do not overlap: one blob split at its
    middle, or one stem's two arcs (whose circles share a centre), stays whole. The part
    kept is the one with fewer points, the stem in 60 of 77 split slices of generated
    young blocks (their stakes as thick as the stems or thicker); which part is the stem
    the slice cannot tell in general (the real young row's stems are scanned denser than
    their stakes), so it gives a diameter, not a position.
    """
    keep = np.ones(xy.shape[0], bool)
    _, part = kmeans2(xy - xy.mean(axis=0), 2, seed=0, minit="++")
    sizes = np.bincount(part, minlength=2)
    if sizes.min() < MIN_PIECE:
        return keep
    a, b = xy[part == 0], xy[part == 1]
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    gap = float(np.hypot(*(cb - ca)))
    if gap == 0.0:
        return keep
    axis = (cb - ca) / gap
    spread = np.sqrt(np.mean(((a - ca) @ axis) ** 2)) + np.sqrt(np.mean(((b - cb) @ axis) ** 2))
    if gap < SPLIT_SEPARATION * spread:
        return keep
    (oa, ra), (ob, rb) = fit_circle(a, solid=True), fit_circle(b, solid=True)
    if not (np.isfinite(ra) and np.isfinite(rb)) or np.hypot(*(ob - oa)) <= ra + rb:
        return keep  # one circle's arcs, or parts of one blob
    return part == int(np.argmin(sizes))
