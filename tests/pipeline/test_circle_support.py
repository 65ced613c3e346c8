"""pipeline.metrics.circle_support counts exactly what the hypot definition counts."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.metrics import circle_support


def _by_definition(xy, ux, uy, r, inlier):
    resid = np.abs(np.hypot(xy[None, :, 0] - ux[:, None], xy[None, :, 1] - uy[:, None]) - r[:, None])
    return (resid < inlier).sum(1)


def test_by_hand():
    xy = np.array([[1.0, 0.0], [0.0, 1.05], [0.0, 0.0], [2.0, 2.0]])
    got = circle_support(xy, np.array([0.0, 2.0]), np.array([0.0, 2.0]), np.array([1.0, 0.5]), 0.1)
    np.testing.assert_array_equal(got, [2, 0])


def test_points_on_the_edges_of_the_band_count_as_hypot_says():
    """Points at distance r ± inlier from the centre, and one ulp either side: the sum of
    squares cannot tell these apart, np.hypot decides them."""
    inlier = 0.02
    ux, uy, r = np.array([3.25, -7.5]), np.array([1.125, 40.0]), np.array([0.1, 0.35])
    xy = []
    for cx, cy, rad in zip(ux, uy, r):
        for dist in (rad + inlier, rad - inlier):
            for d in (np.nextafter(dist, 0), dist, np.nextafter(dist, 1)):
                for angle in np.linspace(0, 2 * np.pi, 37):
                    xy.append([cx + d * np.cos(angle), cy + d * np.sin(angle)])
    xy = np.array(xy)
    np.testing.assert_array_equal(circle_support(xy, ux, uy, r, inlier), _by_definition(xy, ux, uy, r, inlier))


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 600),
    t=st.integers(1, 300),
    scale=st.sampled_from([0.01, 0.3, 5.0]),
    inlier=st.sampled_from([0.003, 0.02, 0.1]),
    quantum=st.sampled_from([0.0, 0.001]),
    seed=st.integers(0, 2**32 - 1),
)
def test_equals_the_hypot_definition(n, t, scale, inlier, quantum, seed):
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, n)
    xy = np.c_[np.cos(angle), np.sin(angle)] * scale + rng.normal(0, inlier, (n, 2)) + rng.uniform(-500, 500, 2)
    if quantum:  # coordinates on the LAS grid: many equal distances
        xy = np.round(xy / quantum) * quantum
    ux = xy[0, 0] + rng.normal(0, scale, t)
    uy = xy[0, 1] + rng.normal(0, scale, t)
    r = np.abs(rng.normal(scale, scale, t))
    np.testing.assert_array_equal(circle_support(xy, ux, uy, r, inlier), _by_definition(xy, ux, uy, r, inlier))
