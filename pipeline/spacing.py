"""The in-row spacing of the trees of a block, measured from its trunk candidates.

Hedgerows stand 0.8-1.5 m apart in the row, vase trees 4-8 m: the radii that group
ground contacts into trunks and tell a tree's own foliage touching the ground from its
neighbour (:class:`pipeline.params.TrunkParams`) follow the spacing the block shows.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: a candidate's neighbour counts for the spacing when it drains at least this share of
#: the candidate's catchment
COMPARABLE_SHARE = 0.5
#: fewest candidates that measure a spacing: two or three may be the bark of a single
#: thick trunk split into groups
MIN_CANDIDATES = 4
#: neighbours searched for the nearest comparable candidate
_NEIGHBOURS = 16


def comparable_distance(xy: np.ndarray, support: np.ndarray, *, share: float = COMPARABLE_SHARE) -> np.ndarray:
    """Distance from each candidate to the nearest other one draining at least ``share``
    times as much, (k,) float64 [m]; inf where none is among its _NEIGHBOURS nearest."""
    k = xy.shape[0]
    out = np.full(k, np.inf)
    if k < 2:
        return out
    d, j = cKDTree(xy).query(xy, k=min(_NEIGHBOURS + 1, k))
    d, j = d[:, 1:], j[:, 1:]  # without the candidate itself
    ok = support[j] >= share * support[:, None]
    first = np.argmax(ok, axis=1)
    has = ok[np.arange(k), first]
    out[has] = d[np.arange(k), first][has]
    return out


def estimate_spacing(xy: np.ndarray, support: np.ndarray) -> float | None:
    """The in-row spacing of a block's trees [m] from trunk candidates.

    A trunk's nearest candidate of a comparable catchment (at least COMPARABLE_SHARE of
    its own) is a neighbouring trunk, usually the next one in its row; a false candidate
    (shoots or foliage touching down, a trunk's bark split into two groups) drains much
    less than the trunk beside it, and its nearest comparable candidate is that trunk.
    The spacing is the median of these distances, each weighted by the square of the
    candidate's catchment, so that the weak false ones count little.

    Parameters
    ----------
    xy : (k, 2) float64 — candidate centres [m]
    support : (k,) float64 — catchment of each candidate [nodes]

    Returns
    -------
    float, or None with fewer than MIN_CANDIDATES candidates or none with a comparable one.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    support = np.asarray(support, dtype=np.float64)
    if xy.shape[0] < MIN_CANDIDATES:
        return None
    d = comparable_distance(xy, support)
    ok = np.isfinite(d)
    if not ok.any():
        return None
    d, w = d[ok], support[ok] ** 2
    order = np.argsort(d, kind="stable")
    cum = np.cumsum(w[order])
    return float(d[order][np.searchsorted(cum, 0.5 * cum[-1])])
