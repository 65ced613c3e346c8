"""The part of a block a capture saw."""

import numpy as np

from pipeline.coverage import STEM_BAND, STEM_CELL, Coverage, occupied_cells, stem_cells


def test_cells_are_on_the_input_crs_whole_metre_grid():
    cells = occupied_cells(np.array([[0.2, 0.3], [0.9, 0.1], [2.5, 1.0]]), (500000.0, 20.0))
    assert sorted(map(tuple, cells.tolist())) == [(500000, 20), (500002, 21)]


def test_narrow_holes_are_closed_and_the_edge_is_eroded():
    xy = np.mgrid[0:20:0.5, 0:20:0.5].reshape(2, -1).T
    xy = xy[np.abs(xy[:, 1] - 10.0) > 0.7]  # the strip the scanner's vehicle hides
    cov = Coverage.from_cells(occupied_cells(xy, (0.0, 0.0)))
    assert cov.covered(np.array([[10.0, 10.0]]))[0]  # in the closed strip
    assert not cov.covered(np.array([[0.5, 10.0], [30.0, 10.0]])).any()  # at the edge, and beyond


def test_a_stem_needs_a_few_points_and_tiles_add_up():
    from pipeline.coverage import stem_cells, stems_of

    stem = np.array([[2.03, 3.04], [2.05, 3.06], [2.06, 3.02], [2.04, 3.05]])
    stray = np.array([[7.5, 1.5]])
    xy = np.r_[stem, stray]
    height = np.array([0.4, 0.5, 0.6, 1.5, 0.5])  # one stem point above the band
    among = np.ones(len(xy), bool)
    whole = stems_of([stem_cells(xy, height, among, (100.0, 0.0))])
    assert np.allclose(whole, [[102.05, 3.05]])  # the stray point is no stem
    split = stems_of([stem_cells(xy[:2], height[:2], among[:2], (100.0, 0.0)),
                      stem_cells(xy[2:], height[2:], among[2:], (100.0, 0.0))])
    assert np.allclose(split, whole)  # two tiles' points of one cell count together


def test_stem_cells_are_the_band_points_cells_and_counts_dense_or_sparse():
    from pipeline.coverage import STEM_BAND, STEM_CELL, stem_cells

    rng = np.random.default_rng(3)
    for spread in (0.3, 40.0):  # cells dense enough to be counted in place, and scattered ones
        xy = rng.uniform(-spread, spread, (3000, 2))
        height = rng.uniform(0.0, 1.2, 3000)
        among = rng.random(3000) < 0.8
        origin = (500000.0, 20.0)
        pick = among & (height >= STEM_BAND[0]) & (height < STEM_BAND[1])
        ij = np.floor((xy[pick] + np.asarray(origin)) / STEM_CELL).astype(np.int64)
        rows, counts = np.unique(ij, axis=0, return_counts=True)
        assert np.array_equal(stem_cells(xy, height, among, origin), np.c_[rows, counts])
    assert stem_cells(xy, height, np.zeros(3000, bool), origin).shape == (0, 3)
def test_stem_cells_of_many_points_in_several_passes():
    from pipeline.passes import CACHE_POINTS

    rng = np.random.default_rng(9)
    n = 3 * CACHE_POINTS + 5
    xy, height, among = rng.uniform(-20, 20, (n, 2)), rng.uniform(0, 1.2, n), rng.random(n) < 0.9
    origin = np.array([431000.0, 5123000.0])
    pick = among & (height >= STEM_BAND[0]) & (height < STEM_BAND[1])
    cells, counts = np.unique(np.floor((xy[pick] + origin) / STEM_CELL).astype(np.int64), axis=0, return_counts=True)
    np.testing.assert_array_equal(stem_cells(xy, height, among, origin), np.c_[cells, counts])
