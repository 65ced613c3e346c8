"""pipeline.stemslice: a trunk slice's stem, without a riser or stake beside it."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.circles import trunk_circle
from pipeline.stemslice import stem_points


def _ring(centre, radius, n, rng, arc=(0.0, 2 * np.pi)):
    a = rng.uniform(*arc, n)
    return np.c_[centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)] + rng.normal(0, 0.002, (n, 2))


def test_a_riser_beside_a_young_stem_is_left_out():
    rng = np.random.default_rng(1)
    stem = _ring((0.0, 0.0), 0.03, 40, rng, arc=(0.0, np.pi))
    riser = _ring((0.25, 0.05), 0.02, 15, rng, arc=(0.0, np.pi))
    xy = np.vstack([stem, riser])
    keep = stem_points(xy, np.zeros(len(xy), np.int64))
    assert keep[:40].all() and not keep[40:].any()


def test_a_stem_seen_from_both_sides_is_kept_whole():
    """Two arcs a diameter apart (the scan's two alleys), neither touching the other."""
    rng = np.random.default_rng(2)
    near = _ring((0.0, 0.0), 0.15, 60, rng, arc=(0.25 * np.pi, 0.75 * np.pi))
    far = _ring((0.0, 0.0), 0.15, 45, rng, arc=(1.25 * np.pi, 1.75 * np.pi))
    xy = np.vstack([near, far])
    assert stem_points(xy, np.zeros(len(xy), np.int64)).all()


def test_each_tree_keeps_its_own_stem():
    rng = np.random.default_rng(3)
    a = _ring((0.0, 0.0), 0.03, 40, rng)
    a_riser = _ring((0.3, 0.0), 0.02, 12, rng)
    b = _ring((1.0, 0.0), 0.03, 30, rng)  # tree 2: nothing beside it
    xy = np.vstack([a, a_riser, b])
    tree = np.r_[np.full(52, 1), np.full(30, 2)]
    keep = stem_points(xy, tree)
    assert keep[:40].all() and not keep[40:52].any() and keep[52:].all()


def _scanned_ring(centre, radius, n, rng):
    """A stem's section as scan lines cross it: about evenly spaced points."""
    step = 2 * np.pi / n
    a = np.arange(n) * step + rng.uniform(0, 2 * np.pi) + rng.uniform(-0.3, 0.3, n) * step
    return np.c_[centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)] + rng.normal(0, 0.002, (n, 2))


@settings(max_examples=80, deadline=None)
@given(n=st.integers(8, 120), radius=st.floats(0.01, 0.4), seed=st.integers(0, 2**32 - 1))
def test_a_ring_is_never_cut(n, radius, seed):
    """Sparse (8 points) or dense, thin or thick: one stem's section stays whole."""
    xy = _scanned_ring((5.0, -3.0), radius, n, np.random.default_rng(seed))
    assert stem_points(xy, np.full(n, 7, np.int64)).all()


def _blurred_section(centre, radius, n, rng, noise):
    """A thin section under range noise: points on the circle, scattered by ``noise``."""
    a = rng.uniform(0, 2 * np.pi, n)
    return np.c_[centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)] + rng.normal(0, noise, (n, 2))


@pytest.mark.parametrize("offset", [0.06, 0.08, 0.1, 0.12])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_stake_touching_a_young_stem_is_left_out(offset, seed):
    """A stake of the stem's radius 6-12 cm beside it, both blurred into one piece by the
    scan's noise: the circle fitted to the points kept is the stem's, not one through both.
    The stake gives more points (it is seen whole: nothing on it grows into the slice)."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi)
    at = offset * np.array([np.cos(angle), np.sin(angle)])
    stem = _blurred_section((0.0, 0.0), 0.015, 30, rng, 0.01)
    stake = _blurred_section(at, 0.015, 45, rng, 0.01)
    xy = np.vstack([stem, stake]) + np.array([3.0, 4.0])
    keep = stem_points(xy, np.full(len(xy), 2, np.int64), stakes=True)
    centre, radius = trunk_circle(xy[keep])
    assert np.hypot(*(centre - (3.0, 4.0))) < 0.02
    assert radius < 0.03
    whole_centre, whole_radius = trunk_circle(xy)
    assert whole_radius > 0.03 or np.hypot(*(whole_centre - (3.0, 4.0))) > 0.02  # the test can fail


def test_without_stakes_two_sections_side_by_side_stay_whole():
    """On a grown block (no stakes) a slice is split only into its pieces: a grown stem of
    4-6 cm radius under 2 cm of noise looks like two thin sections side by side."""
    rng = np.random.default_rng(4)
    stem = _blurred_section((0.0, 0.0), 0.015, 30, rng, 0.01)
    stake = _blurred_section((0.08, 0.0), 0.015, 45, rng, 0.01)
    xy = np.vstack([stem, stake])
    assert stem_points(xy, np.zeros(len(xy), np.int64)).all()
    assert not stem_points(xy, np.zeros(len(xy), np.int64), stakes=True).all()
