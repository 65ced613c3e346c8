"""The trunk tests between neighbouring contact groups: shoots, satellites, stems of their own.

A group that passed every test of its own can still be a neighbour's shoots touching
down, or a satellite drained by a much stronger trunk beside it; a group with a stem of
its own is neither (:func:`own_stems`). Used by :mod:`pipeline.trunks`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.params import TrunkParams

#: groups that are no trunks (too wide, or shoots beside a clearer stem) pass their
#: catchment to the accepted group they lie beside, up to this many cluster radii away
#: (stated in the help of TrunkParams.cluster_radius)
POOL_REACH = 1.25
#: a satellite lies at most this many satellite radii from its trunk (stated in the help
#: of TrunkParams.satellite_radius)
SATELLITE_REACH = 2.0
#: a clearer stem drops a group only if it drains at least this share of that group's
#: catchment (a grass tuft under a shoot tip makes a sharp little column that drains little)
SHOOT_MIN_SUPPORT = 0.5
#: a group with a stem of its own (:func:`own_stems`): its catchment reaches above
#: ``max_post_height`` (a bole, not a post or a shoot bundle), and graph nodes within COLUMN_RADIUS
#: [m] of its centre in every COLUMN_SLICE [m] slice from COLUMN_BOTTOM (above the grass
#: and the tips of drooping shoots) to COLUMN_TOP [m]: a bole standing in a closed stand.
#: Such a group is never dropped as a neighbour's shoots or satellite (a weaker catchment
#: in a closed canopy says who won the interlocking crowns, not that there is no tree)
COLUMN_RADIUS = 0.25
COLUMN_SLICE = 0.25
COLUMN_BOTTOM = 0.3
COLUMN_TOP = 2.5
#: ... and whose stem stands out at least this clearly above the ground layer (stem
#: score, :func:`pipeline.stems.stem_contrast`): drooping shoot bundles on high-density vase blocks fill
#: such a column too, but score 1.7-11 (one 252 of 11), true trunks there 46-1005, the
#: stems of TreeLS's pine plot 12-425
COLUMN_MIN_STEM = 12.0
#: ... or, in any block, whose column goes on unbroken to this far [m] above the tallest
#: post (``max_post_height``): a bole continuous from the ground into the crowns, whatever
#: its stem score and wherever its catchment ends. A dominated stem of a closed stand may
#: score under COLUMN_MIN_STEM (7.7-11 on generated conifer stands) and its catchment end
#: at 2.6-4.5 m (taller neighbours drain the interlocking crowns above it), but its column
#: reaches 5.05-7.3 m; a post ends at its top, and the shoot bundles of orchard crowns
#: stand lower (their columns end by 4.3 m on high-density vase blocks)
BOLE_ABOVE_POST = 0.5


def _suppressed(xy: np.ndarray, strength: np.ndarray, ok: np.ndarray, reach: float, beats) -> np.ndarray:
    """Greedy suppression among the accepted groups ``ok``: strongest first by
    ``strength`` (NaN last), each group not yet suppressed suppresses every group within
    ``reach`` [m] for which ``beats(i, other, d)`` holds (d: their distance [m]).

    Returns (g,) int64, the group that suppressed each group (-1: not suppressed).
    """
    by = np.full(xy.shape[0], -1, np.int64)
    idx = np.flatnonzero(ok)
    if idx.size < 2:
        return by
    tree = cKDTree(xy[idx])
    for j in np.argsort(-np.nan_to_num(strength[idx], nan=-np.inf), kind="stable"):
        i = idx[j]
        if by[i] >= 0:
            continue
        for q in tree.query_ball_point(xy[i], reach):
            other = idx[q]
            if other != i and by[other] < 0 and beats(i, other, float(np.hypot(*(xy[other] - xy[i])))):
                by[other] = i
    return by


def _nearest(xy: np.ndarray, ok: np.ndarray, which: np.ndarray, reach: float) -> np.ndarray:
    """For the groups ``which``, the nearest group in ``ok`` within ``reach`` [m] (-1: none)."""
    out = np.full(which.size, -1, np.int64)
    idx = np.flatnonzero(ok)
    if idx.size == 0 or which.size == 0:
        return out
    d, j = cKDTree(xy[idx]).query(xy[which])
    return np.where(d <= reach, idx[j], -1)


def _pool(support: np.ndarray, which: np.ndarray, into: np.ndarray) -> None:
    """Add ``support`` of the groups ``which`` to the groups ``into`` (-1: nowhere), in place."""
    has = into >= 0
    np.add.at(support, into[has], support[which[has]])


def satellites(xy: np.ndarray, support: np.ndarray, ok: np.ndarray, radius: float, ratio: float) -> np.ndarray:
    """Groups dominated by a stronger accepted group nearby.

    Strongest first: a group at distance d from an accepted group is its satellite when
    that group drains ``ratio * max(1, d / radius)**2`` times more material, up to
    ``SATELLITE_REACH * radius`` away (the farther, the weaker a satellite must be).
    """
    if radius <= 0:
        return np.zeros(xy.shape[0], bool)
    return _suppressed(xy, support, ok, SATELLITE_REACH * radius,
                       lambda i, other, d: support[i] >= ratio * max(1.0, d / radius) ** 2 * support[other]) >= 0


def shoots(xy: np.ndarray, stem: np.ndarray, support: np.ndarray, ok: np.ndarray, radius: float, ratio: float) -> np.ndarray:
    """Accepted groups beside a much clearer stem: greedy by stem score, a group within
    ``radius`` of a kept group whose stem score is at least ``ratio`` times its own, and
    which drains at least SHOOT_MIN_SUPPORT times as much, is a shoot or foliage touching
    down near that trunk, not a trunk (a grass tuft under a shoot tip can make a sharp
    little column that drains little: it must not drop a trunk). NaN scores compare
    false: a group without a score is never dropped and drops nothing.

    Returns (g,) int64, the trunk group each shoot group lies beside (-1: not a shoot)."""
    if ratio <= 0:
        return np.full(xy.shape[0], -1, np.int64)
    return _suppressed(xy, stem, ok, radius, lambda i, other, d: (
        stem[i] >= ratio * stem[other] and support[i] >= SHOOT_MIN_SUPPORT * support[other]))


def own_stems(centre: np.ndarray, nodes: np.ndarray, node_height: np.ndarray, top: float = COLUMN_TOP) -> np.ndarray:
    """Groups with a stem of their own: nodes within COLUMN_RADIUS of each ``centre``
    (g, 2) in every COLUMN_SLICE slice from COLUMN_BOTTOM to ``top`` [m] above the
    ground. Returns (g,) bool."""
    g = centre.shape[0]
    sel = np.flatnonzero((node_height >= COLUMN_BOTTOM) & (node_height < top))
    if g == 0 or sel.size == 0:
        return np.zeros(g, bool)
    n_slices = int(round((top - COLUMN_BOTTOM) / COLUMN_SLICE))
    slc = np.minimum(((node_height[sel] - COLUMN_BOTTOM) // COLUMN_SLICE).astype(np.int64), n_slices - 1)
    near = cKDTree(nodes[sel, :2]).query_ball_point(centre, COLUMN_RADIUS)
    return np.array([np.unique(slc[np.asarray(j, np.int64)]).size == n_slices if j else False for j in near])


def accept(
    xy: np.ndarray, support: np.ndarray, stem: np.ndarray, ok: np.ndarray, wide: np.ndarray, params: TrunkParams,
    own: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The last trunk tests, between neighbouring groups: shoots, then satellites.

    A tree's catchment also drains through groups beside its trunk that are no trunks
    themselves: a curtain too wide for a trunk (``wide``: groups that failed only the
    width test) and shoots beside a clearer stem. Each passes its catchment to the group
    it lies beside (the nearest accepted one, or the stem that made it a shoot), up to
    POOL_REACH cluster radii away, before the satellite test compares catchments (else
    a shoot bundle beside a trunk can take most of its catchment, and the trunk is
    dropped as a satellite of its neighbour in the row).

    Parameters
    ----------
    xy : (g, 2) float64 — group centres [m]
    support : (g,) float64 — each group's own catchment [nodes]
    stem : (g,) float64 — stem scores (:func:`pipeline.stems.stem_contrast`; NaN: none)
    ok : (g,) bool — groups that passed every test of their own
    wide : (g,) bool — groups that failed only the width test
    params : TrunkParams
    own : (g,) bool, optional — groups with a stem of their own (:func:`own_stems`):
        never dropped as shoots or satellites

    Returns
    -------
    ok : (g,) bool — the groups accepted as trunks
    pooled : (g,) float64 — each group's catchment with what it received
    """
    reach = POOL_REACH * params.cluster_radius
    pooled = support.astype(np.float64)
    wide = np.flatnonzero(wide)
    _pool(pooled, wide, _nearest(xy, ok, wide, reach))
    shoot_of = shoots(xy, stem, pooled, ok, params.satellite_radius, params.stem_ratio)
    shoot = np.flatnonzero(shoot_of >= 0)
    beside = np.hypot(*(xy[shoot] - xy[shoot_of[shoot]]).T) <= reach
    _pool(pooled, shoot, np.where(beside, shoot_of[shoot], -1))
    own = np.zeros(xy.shape[0], bool) if own is None else own
    ok = ok & ((shoot_of < 0) | own)
    # satellites: strongest first, a group near an accepted, much stronger one is not a tree
    ok &= ~(satellites(xy, pooled, ok, params.satellite_radius, params.satellite_ratio) & ~own)
    return ok, pooled
