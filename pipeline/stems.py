"""Trunk evidence just above the ground layer: a trunk's foot and its standing stem.

A trunk rises out of the ground as a compact column of bark: its points crowd a small
disc in the ground layer (its foot) and in every thin slice above it (its stem), while
shoots or foliage hanging into the grass leave those slices thin or evenly spread.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: the foot test (:func:`foot_ratio`): ground-layer points within this radius [m] of a
#: trunk's centre (a trunk's foot) ...
FOOT_RADIUS = 0.2
#: ... against those out to this radius [m] around it (the grass)
FOOT_ANNULUS = 0.8


def foot_ratio(xy: np.ndarray, foot_xy: np.ndarray | None) -> np.ndarray:
    """Density of ``foot_xy`` points within FOOT_RADIUS of each ``xy`` over the density
    FOOT_RADIUS-FOOT_ANNULUS around it, (k,) float64 (1 where there are no points)."""
    if foot_xy is None or foot_xy.shape[0] == 0 or xy.shape[0] == 0:
        return np.ones(xy.shape[0])
    tree = cKDTree(foot_xy)
    inner = tree.query_ball_point(xy, FOOT_RADIUS, return_length=True).astype(np.float64)
    outer = tree.query_ball_point(xy, FOOT_ANNULUS, return_length=True) - inner
    d_in = inner / (np.pi * FOOT_RADIUS**2)
    d_out = outer / (np.pi * (FOOT_ANNULUS**2 - FOOT_RADIUS**2))
    return (d_in + 1.0) / (d_out + 1.0)


#: the stem test (:func:`stem_contrast`): a disc of this radius [m] around a probe ...
STEM_RADIUS = 0.15
#: ... against the ring between these radii [m] (a trunk of radius up to about 0.2 m
#: fills the disc and leaves the ring to the grass and clutter around it)
STEM_RING = (0.25, 0.4)
#: probes on a STEM_STEP lattice [m] within STEM_SEARCH [m] of a group's centre
STEM_SEARCH = 0.4
STEM_STEP = 0.05
#: STEM_SLICES slices of STEM_SLICE_HEIGHT [m] stacked from the top of the ground layer:
#: below a trunk's first branches, where drooping shoots are thinning out
STEM_SLICES = 3
STEM_SLICE_HEIGHT = 0.1


def stem_contrast(xy: np.ndarray, stem_xy: np.ndarray | None, stem_slice: np.ndarray | None, *, n_slices: int) -> np.ndarray:
    """How much a standing stem stands out just above the ground layer, near each ``xy``.

    A trunk is a column of bark rising out of the ground: in every thin horizontal
    slice above the ground layer its points crowd a small disc, much denser than the
    ring around it. Shoots or foliage hanging to a few decimetres above the grass leave
    the lowest slices thin or evenly spread. For a position p and a slice, the contrast
    is (density within STEM_RADIUS of p + 1) / (density in the ring STEM_RING around p
    + 1) [points/m²]; a position's score is its lowest contrast over the slices, and a
    candidate's score the best position within STEM_SEARCH of ``xy`` (on a STEM_STEP
    lattice, since the flow-weighted centre of a group may sit off its stem).

    Parameters
    ----------
    xy : (k, 2) float64 — candidate centres [m]
    stem_xy : (p, 2) float64 or None — non-ground points just above the ground layer [m]
    stem_slice : (p,) int64 or None — slice of each point, 0 .. n_slices-1
    n_slices : int

    Returns
    -------
    (k,) float64, the score (NaN where no points were given: the test is then off).
    """
    k = xy.shape[0]
    if stem_xy is None or stem_slice is None or k == 0:
        return np.full(k, np.nan)
    g = np.arange(-STEM_SEARCH, STEM_SEARCH + 1e-9, STEM_STEP)
    off = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    off = off[np.hypot(off[:, 0], off[:, 1]) <= STEM_SEARCH + 1e-9]
    m = off.shape[0]
    probes = (xy[:, None, :] + off[None, :, :]).reshape(-1, 2)
    owner = np.repeat(np.arange(k), m)  # candidate of each probe
    a_in = np.pi * STEM_RADIUS**2
    a_ring = np.pi * (STEM_RING[1] ** 2 - STEM_RING[0] ** 2)
    # a tree built without median splits nor shrunk boxes builds in about half the time and
    # counts alike: a ball's count is the points within it whatever the tree's shape
    trees = [cKDTree(stem_xy[stem_slice == s].reshape(-1, 2), balanced_tree=False, compact_nodes=False)
             for s in range(n_slices)]  # empty: contrast 1

    def disc(s: int, at: np.ndarray) -> np.ndarray:
        return trees[s].query_ball_point(probes[at], STEM_RADIUS, return_length=True) / a_in + 1.0

    def contrast(s: int, at: np.ndarray) -> np.ndarray:
        tree, p = trees[s], probes[at]
        ring = tree.query_ball_point(p, STEM_RING[1], return_length=True) - tree.query_ball_point(
            p, STEM_RING[0], return_length=True)
        return disc(s, at) / (ring / a_ring + 1.0)

    # Strategy: branch and bound, exact. The disc alone (an empty ring) bounds a probe's
    # contrast in a slice from above, at a fraction of the cost of counting the ring;
    # the probe with the best bound of each candidate, scored in full, bounds the
    # candidate's score from below, and the rings are counted only where a probe can
    # still beat that, slice by slice (a small share of the probes).
    every = np.arange(probes.shape[0])
    bound = disc(0, every)
    for s in range(1, n_slices):
        bound = np.minimum(bound, disc(s, every))
    lead = np.argmax(bound.reshape(k, m), axis=1) + np.arange(k) * m
    floor = contrast(0, lead)
    for s in range(1, n_slices):
        floor = np.minimum(floor, contrast(s, lead))
    bound[lead] = floor
    live = np.flatnonzero(bound > floor[owner])  # not the leads: theirs equals the floor
    for s in range(n_slices):
        bound[live] = np.minimum(bound[live], contrast(s, live))
        live = live[bound[live] > floor[owner[live]]]
    return bound.reshape(k, m).max(axis=1)
