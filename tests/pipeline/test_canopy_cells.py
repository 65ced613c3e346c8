"""pipeline.voxels.keyed_cells (canopy.unique_cells, the stem cells): np.unique(cells, axis=0) by one int64 key per cell."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.canopy import unique_cells


def test_unique_cells_by_hand():
    cells = np.array([[2, 1], [0, 5], [2, 1], [0, -3], [-1, 7]])
    got = unique_cells(cells)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, [[-1, 7], [0, -3], [0, 5], [2, 1]])


def test_no_cells():
    got = unique_cells(np.zeros((0, 2), np.int64))
    assert got.shape == (0, 2) and got.dtype == np.int64


def test_cells_too_far_apart_for_one_key_still_come_out_sorted():
    cells = np.array([[2**40, 0], [-(2**40), 2**40], [2**40, 0], [0, -(2**40)]])
    np.testing.assert_array_equal(unique_cells(cells), np.unique(cells, axis=0))


@settings(max_examples=200, deadline=None)
@given(
    n=st.integers(1, 400),
    span=st.sampled_from([1, 3, 50, 10**4, 10**9]),
    offset=st.integers(-(10**9), 10**9),
    seed=st.integers(0, 2**32 - 1),
)
def test_unique_cells_equals_numpy_unique_by_rows(n, span, offset, seed):
    """Dense grids (occupancy path) and sparse ones (sorted keys) alike."""
    cells = np.random.default_rng(seed).integers(-span, span + 1, (n, 2)) + offset
    np.testing.assert_array_equal(unique_cells(cells), np.unique(cells, axis=0))


def test_canopy_cells_of_many_points_in_several_passes():
    from pipeline.canopy import canopy_cells
    from pipeline.passes import CACHE_POINTS

    rng = np.random.default_rng(8)
    n = 3 * CACHE_POINTS + 11
    xy, height = rng.uniform(-30, 30, (n, 2)), rng.uniform(-1, 4, n)
    among = rng.random(n) < 0.8
    offset = np.array([512000.0, 6800000.0])
    keep = (height >= 1.0) & among
    want = np.unique(np.floor((xy[keep] + offset) / 0.25).astype(np.int64), axis=0)
    np.testing.assert_array_equal(canopy_cells(xy, height, offset=offset, among=among), want)


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 400),
    span=st.sampled_from([1, 3, 50, 10**4, 10**9, 2**40]),
    seed=st.integers(0, 2**32 - 1),
)
def test_keyed_cells_counts_equal_numpy_unique_by_rows(n, span, seed):
    """The counted cells (stem cells) on dense, sparse and overflowing keys alike."""
    from pipeline.voxels import keyed_cells

    cells = np.random.default_rng(seed).integers(-span, span + 1, (n, 2))
    want, want_counts = np.unique(cells, axis=0, return_counts=True)
    got, counts = keyed_cells(cells[:, 0], cells[:, 1], counts=True)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(counts, want_counts)
