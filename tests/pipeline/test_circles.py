"""pipeline.circles: the circle fits, and circle_support counting exactly what the hypot definition counts."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.circles import circle_support, fit_circle, trunk_circle


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


def test_circle_fit_recovers_radius_from_a_half_arc_with_outliers():
    rng = np.random.default_rng(0)
    th = rng.uniform(0, np.pi, 200)
    xy = np.column_stack([3 + 0.15 * np.cos(th), -2 + 0.15 * np.sin(th)]) + rng.normal(0, 0.003, (200, 2))
    xy = np.concatenate([xy, rng.uniform(2.5, 3.5, (10, 2))])
    c, r = fit_circle(xy)
    assert r == pytest.approx(0.15, abs=0.01)
    assert np.allclose(c, [3, -2], atol=0.01)


@pytest.mark.parametrize("sigma", [0.02, 0.05])
def test_trunk_circle_corrects_for_noise(sigma):
    # a 0.2 m trunk seen from two alleys (two 120-degree arcs), each point off by Gaussian
    # noise sigma per axis: a plain fit comes out too large (mean squared radius
    # r^2 + 2 sigma^2), the corrected one not; averaged over 20 draws
    plain, corrected = [], []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        a = np.concatenate([rng.uniform(np.pi / 6, 5 * np.pi / 6, 150), rng.uniform(-5 * np.pi / 6, -np.pi / 6, 150)])
        xy = np.c_[0.1 * np.cos(a), 0.1 * np.sin(a)] + rng.normal(0, sigma, (300, 2)) + [3.0, -2.0]
        plain.append(fit_circle(xy)[1] - 0.1)
        centre, r = trunk_circle(xy)
        corrected.append(r - 0.1)
        assert np.allclose(centre, [3.0, -2.0], atol=0.03)
    plain, corrected = np.array(plain), np.array(corrected)
    assert plain.mean() > 0.002  # plain: radius 2.3 and 11.6 mm too large on average (sigma 0.02, 0.05)
    assert abs(corrected.mean()) < 0.003 and np.abs(corrected).mean() < 0.5 * np.abs(plain).mean()


def test_a_thin_stem_among_leaves_and_grass_keeps_its_own_circle():
    # a 4 cm stem seen from two alleys, 30 points of clutter scattered within 0.5 m: any
    # circle through the stem holds all of it in its 2 cm band, and the plain fit takes
    # whichever also gathers most clutter (docs/method.md); points deep inside a circle
    # count against it, and the refit stays with the circle found
    plain_wrong = solid_wrong = 0
    for seed in range(30):
        rng = np.random.default_rng(seed)
        a = np.concatenate([rng.uniform(np.pi / 6, 5 * np.pi / 6, 30), rng.uniform(-5 * np.pi / 6, -np.pi / 6, 30)])
        stem = np.c_[0.02 * np.cos(a), 0.02 * np.sin(a)] + rng.normal(0, 0.005, (60, 2))
        rr, th = 0.5 * np.sqrt(rng.uniform(0, 1, 30)), rng.uniform(0, 2 * np.pi, 30)
        xy = np.concatenate([stem, np.c_[rr * np.cos(th), rr * np.sin(th)]]) + [3.0, -2.0]
        plain_wrong += abs(trunk_circle(xy, solid=False)[1] - 0.02) > 0.01
        centre, r = trunk_circle(xy)
        solid_wrong += abs(r - 0.02) > 0.01 or np.hypot(*(centre - [3.0, -2.0])) > 0.01
    assert plain_wrong >= 15 and solid_wrong <= 4, (plain_wrong, solid_wrong)


def test_points_deep_inside_a_solid_circle_count_against_it():
    # circle r 0.1 at 0, band 0.02: three points on it, one 0.015 inside (in the band),
    # one 0.025 inside (not in the band, not deep), one 0.05 inside and one at the centre
    # (deep), one far outside
    xy = np.array([[0.1, 0], [0, 0.1], [-0.1, 0], [0.085, 0], [0, 0.075], [0.05, 0], [0, 0], [0.5, 0]])
    one = (np.zeros(1), np.zeros(1), np.array([0.1]))
    assert circle_support(xy, *one, 0.02)[0] == 4
    assert circle_support(xy, *one, 0.02, inside_depth=0.03)[0] == 4 - 2


def test_trunk_circle_leaves_a_clean_circle_alone():
    a = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    xy = np.c_[0.15 * np.cos(a), 0.15 * np.sin(a)]
    assert trunk_circle(xy)[1] == pytest.approx(0.15, abs=1e-6)
    assert np.isnan(trunk_circle(xy[:4])[1])


def _inside_by_definition(xy, ux, uy, r, depth):
    d = np.sqrt((xy[None, :, 0] - ux[:, None]) ** 2 + (xy[None, :, 1] - uy[:, None]) ** 2) - r[:, None]
    return (d < -depth).sum(1)


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(1, 400),
    t=st.integers(1, 200),
    scale=st.sampled_from([0.01, 0.3, 5.0]),
    inlier=st.sampled_from([0.003, 0.02, 0.1]),
    depth_bands=st.sampled_from([0.5, 1.5, 3.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_solid_support_equals_the_definition(n, t, scale, inlier, depth_bands, seed):
    """With ``inside_depth``: the band's points less those deeper inside than the depth,
    by ``sqrt(dx² + dy²)``; radii around the depth (some exactly it), and points on the
    circle through the depth's edge."""
    rng = np.random.default_rng(seed)
    depth = depth_bands * inlier
    angle = rng.uniform(0, 2 * np.pi, n)
    rad = rng.choice([scale, depth, scale - depth], n) + rng.normal(0, inlier, n) * rng.integers(0, 2, n)
    xy = np.c_[np.cos(angle), np.sin(angle)] * rad[:, None] + rng.uniform(-500, 500, 2)
    ux = xy[0, 0] + rng.normal(0, scale, t) * rng.integers(0, 2, t)
    uy = xy[0, 1] + rng.normal(0, scale, t) * rng.integers(0, 2, t)
    r = np.where(rng.uniform(size=t) < 0.3, depth, np.abs(rng.normal(scale, scale, t)))
    want = _by_definition(xy, ux, uy, r, inlier) - _inside_by_definition(xy, ux, uy, r, depth)
    np.testing.assert_array_equal(circle_support(xy, ux, uy, r, inlier, inside_depth=depth), want)


def test_many_points_and_far_off_circles_are_counted_exactly():
    """More points than a 16-bit row sum holds, and circles from nearly collinear triples
    (centres kilometres away), which are counted point by point."""
    rng = np.random.default_rng(7)
    angle = rng.uniform(0, 2 * np.pi, 70_000)
    xy = np.c_[np.cos(angle), np.sin(angle)] * 0.1 + rng.normal(0, 0.01, (70_000, 2))
    ux, uy = np.array([0.0, 0.001, 3e3, -1e7]), np.array([0.0, 0.0, 0.0, 5e6])
    r = np.array([0.1, 0.12, 3e3, np.hypot(1e7, 5e6)])
    np.testing.assert_array_equal(circle_support(xy, ux, uy, r, 0.02), _by_definition(xy, ux, uy, r, 0.02))


def test_points_within_rounding_of_the_edges_are_counted_as_hypot_says():
    """Many points within a few ulps of a band's edge, around circles far from the
    origin: some land on the wrong side in the matrix product's rounding, and only its
    narrowed and widened counts send those circles to be counted point by point (with
    the two counts at the band's edge itself, this test fails)."""
    rng = np.random.default_rng(1)
    inlier = 0.02
    for _ in range(25):
        c = rng.uniform(-500, 500, 2)
        ux, uy, r = c[0] + rng.normal(0, 0.05, 3), c[1] + rng.normal(0, 0.05, 3), rng.uniform(0.03, 0.3, 3)
        xy = []
        for cx, cy, rad in zip(ux, uy, r):
            for dist in (rad + inlier, rad - inlier):
                d = dist * (1 + np.arange(-6, 7) * np.finfo(np.float64).eps)
                a = rng.uniform(0, 2 * np.pi, (13, 40))
                xy.append(np.c_[(cx + d[:, None] * np.cos(a)).ravel(), (cy + d[:, None] * np.sin(a)).ravel()])
        xy = np.concatenate(xy)
        np.testing.assert_array_equal(circle_support(xy, ux, uy, r, inlier), _by_definition(xy, ux, uy, r, inlier))


@settings(max_examples=200, deadline=None)
@given(values=st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=1, max_size=40))
def test_median_is_numpys(values):
    from pipeline.circles import _median

    a = np.asarray(values)
    assert _median(a) == float(np.median(a))


def _trunk_circle_by_steps(xy, trials):
    """trunk_circle(solid=False) step by step: the search, the noise from numpy's medians,
    the search again in the noise band."""
    centre, r = fit_circle(xy, trials=trials)
    if not np.isfinite(r):
        return centre, r
    res = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1]) - r
    res = res[np.abs(res) < 0.15]
    sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))
    c2, r2 = fit_circle(xy, inlier=max(0.02, 2.5 * sigma), trials=trials)
    if not np.isfinite(r2):
        return centre, r
    return c2, float(np.sqrt(max(r2 * r2 - 2.0 * sigma * sigma, 0.25 * r2 * r2)))


@settings(max_examples=60, deadline=None)
@given(n=st.integers(5, 200), sigma=st.sampled_from([0.0, 0.002, 0.01, 0.03]), clutter=st.integers(0, 30),
       seed=st.integers(0, 2**32 - 1))
def test_a_post_section_fit_is_the_search_again_in_the_noise_band(n, sigma, clutter, seed):
    # clean sections keep the 2 cm band: the second search is the first one's circle
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, n)
    xy = np.c_[np.cos(angle), np.sin(angle)] * rng.uniform(0.02, 0.1) + rng.normal(0, sigma, (n, 2))
    xy = np.r_[xy, rng.uniform(-0.2, 0.2, (clutter, 2))] + rng.uniform(-100, 100, 2)
    got, want = trunk_circle(xy, trials=1024, solid=False), _trunk_circle_by_steps(xy, 1024)
    np.testing.assert_array_equal(got[0], want[0])
    assert got[1] == want[1] or (np.isnan(got[1]) and np.isnan(want[1]))


@settings(max_examples=100, deadline=None)
@given(n=st.integers(1, 300), scale=st.sampled_from([0.01, 1.0, 1e5]), seed=st.integers(0, 2**32 - 1))
def test_mean_of_points_is_numpys(n, scale, seed):
    from pipeline.circles import _mean_rows

    p = np.random.default_rng(seed).normal(0, scale, (n, 2)) + scale
    np.testing.assert_array_equal(_mean_rows(p), p.mean(axis=0))
