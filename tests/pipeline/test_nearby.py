"""pipeline.nearby: a cell index's ball is what a k-d tree's ball query gives; the cells
around centres hold every point within reach of one."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from pipeline.nearby import CellIndex, near_centres


def _kdtree_ball(xy, c, reach):
    return np.sort(np.asarray(cKDTree(xy).query_ball_point(c, reach), dtype=np.int64))


def test_points_on_the_circle_and_an_ulp_either_side():
    c, reach = np.array([10.0, 20.0]), 0.49
    pts = [c + d * np.array([np.cos(a), np.sin(a)])
           for a in np.linspace(0, 2 * np.pi, 500) for d in (np.nextafter(reach, 0), reach, np.nextafter(reach, 1))]
    pts = np.array(pts + [[10.49, 20.0], [10.0, 19.51], [9.51, 20.0]])
    got = CellIndex(pts, reach).ball(c)
    np.testing.assert_array_equal(got, _kdtree_ball(pts, c, reach))
    assert 0 < len(got) < len(pts)


def test_a_position_off_the_points_finds_none():
    xy = np.array([[0.0, 0.0], [1.0, 1.0]])
    index = CellIndex(xy, 0.3)
    assert index.ball(np.array([-5.0, 0.0])).size == 0
    assert index.ball(np.array([0.5, 9.0])).size == 0
    np.testing.assert_array_equal(index.ball(np.array([0.9, 1.1])), [1])


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 2000),
    extent=st.sampled_from([0.3, 3.0, 40.0, 300.0]),  # 300 m: cell keys beyond 16 bits
    reach=st.sampled_from([0.25, 0.41, 0.49]),
    quantum=st.sampled_from([0.0, 0.001, 0.01]),
    seed=st.integers(0, 2**32 - 1),
)
def test_equals_the_kdtree_ball_query(n, extent, reach, quantum, seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, extent, (n, 2)) + rng.uniform(-1e5, 1e5, 2)
    if quantum:  # LAS coordinates: many points at equal distances
        xy = np.round(xy / quantum) * quantum
    index = CellIndex(xy, reach)
    centres = np.r_[xy[rng.integers(0, n, 4)], xy[rng.integers(0, n, 4)] + rng.normal(0, reach, (4, 2))]
    for c in centres:
        np.testing.assert_array_equal(index.ball(c), _kdtree_ball(xy, c, reach))


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 2000),
    c=st.integers(1, 30),
    extent=st.sampled_from([0.3, 3.0, 40.0]),
    reach=st.sampled_from([0.13, 0.41, 1.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_near_centres_holds_every_point_within_reach(n, c, extent, reach, seed):
    rng = np.random.default_rng(seed)
    offset = rng.uniform(-1e5, 1e5, 2)
    xy = rng.uniform(0, extent, (n, 2)) + offset
    centres = rng.uniform(0, extent, (c, 2)) + offset
    # and points exactly at reach from a centre, along the axes and diagonals
    ring = centres[rng.integers(0, c, 8)] + reach * np.c_[[1, -1, 0, 0, 0.6, -0.6, 0.8, -0.8],
                                                          [0, 0, 1, -1, 0.8, 0.8, -0.6, -0.6]]
    xy = np.r_[xy, ring]
    got = near_centres(xy, centres, reach)
    within = np.flatnonzero((cKDTree(centres).query(xy)[0] <= reach))
    assert np.all(np.diff(got) > 0)
    assert np.isin(within, got).all()


def test_near_centres_by_hand():
    xy = np.array([[0.0, 0.0], [0.5, 0.0], [1.9, 0.0], [3.5, 0.0], [10.0, 10.0]])
    got = near_centres(xy, np.array([[0.0, 0.0]]), 1.0)
    assert {0, 1}.issubset(got) and not {3, 4} & set(got.tolist())


def test_many_points_in_several_cache_sized_passes():
    # more points than one pass of CACHE_POINTS: the passes' indices join in order
    from pipeline.passes import CACHE_POINTS

    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 30, (2 * CACHE_POINTS + 123, 2)) + 5e4
    centres = rng.uniform(0, 30, (6, 2)) + 5e4
    got = near_centres(xy, centres, 0.8)
    within = np.flatnonzero(cKDTree(centres).query(xy)[0] <= 0.8)
    assert np.all(np.diff(got) > 0) and np.isin(within, got).all()
    # every point it leaves out is outside the cells around each centre
    cell = np.floor((xy - (centres.min(axis=0) - 0.8 * (1 + 1e-6))) / (0.8 * (1 + 1e-6)))
    around = np.zeros(len(xy), bool)
    for c in np.floor((centres - (centres.min(axis=0) - 0.8 * (1 + 1e-6))) / (0.8 * (1 + 1e-6))):
        around |= (np.abs(cell - c) <= 1).all(axis=1)
    assert not np.isin(np.flatnonzero(~around), got).any()
    index = CellIndex(xy, 0.8)
    for c in centres:
        np.testing.assert_array_equal(index.ball(c), _kdtree_ball(xy, c, 0.8))


def test_centres_spread_over_a_huge_extent_take_the_box_alone():
    from pipeline.nearby import MAX_NEAR_CELLS
    from pipeline.passes import CACHE_POINTS

    rng = np.random.default_rng(1)
    xy = rng.uniform(-5e4, 5e4, (3 * CACHE_POINTS + 7, 2))
    centres = np.array([[-4e4, -4e4], [4e4, 4e4]])  # (8e4 / 1 m)² cells > MAX_NEAR_CELLS
    assert (8e4 / 1.0) ** 2 > MAX_NEAR_CELLS
    lo, hi = centres.min(axis=0) - 1.0 * (1 + 1e-6), centres.max(axis=0) + 1.0 * (1 + 1e-6)
    box = np.flatnonzero((xy[:, 0] >= lo[0]) & (xy[:, 0] <= hi[0]) & (xy[:, 1] >= lo[1]) & (xy[:, 1] <= hi[1]))
    assert np.array_equal(near_centres(xy, centres, 1.0), box)
