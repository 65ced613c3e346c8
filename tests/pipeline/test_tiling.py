"""Tile geometry: every point in exactly one core; buffered sets are exactly the points in the buffered box."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.errors import ParameterError
from pipeline.params import PipelineParams, SegmentParams
from pipeline.tilelimits import MAX_COPIES, check_buffer, check_tiling, copies_per_point, min_tile_size
from pipeline.tiling import buffered_tiles, core_tile, in_buffered, plan_grid


def _brute_force(xy, grid):
    """(point, tile) pairs by testing every tile's bounds directly."""
    pairs = set()
    for t in grid.tiles():
        x0, y0, x1, y1 = t.core
        in_core = (x0 <= xy[:, 0]) & (xy[:, 0] < x1) & (y0 <= xy[:, 1]) & (xy[:, 1] < y1)
        bx0, by0, bx1, by1 = t.buffered
        in_buf = (bx0 < xy[:, 0]) & (xy[:, 0] < bx1) & (by0 < xy[:, 1]) & (xy[:, 1] < by1)
        in_buf &= grid.buffer > 0  # no buffer: the buffered set is the core (as PDAL)
        pairs |= {(int(i), t.id) for i in np.flatnonzero(in_core | in_buf)}
    return pairs


coord = st.floats(min_value=0.0, max_value=6.0, allow_nan=False, allow_infinity=False)  # in tile sizes


@settings(max_examples=200, deadline=None)
@given(
    pts=st.lists(st.tuples(coord, coord), min_size=1, max_size=60),
    size=st.sampled_from([0.1, 0.3, 1.0, 2.5, 7.0, 10.0, 33.3]),
    buffer_frac=st.floats(min_value=0.0, max_value=2.5),
    ox=st.floats(min_value=-3.0, max_value=0.0),
    oy=st.floats(min_value=-3.0, max_value=0.0),
    shift=st.sampled_from([0.0, 512_345.0, 6_950_000.0]),
    snap=st.booleans(),
)
def test_every_point_in_exactly_one_core_and_buffers_exact(pts, size, buffer_frac, ox, oy, shift, snap):
    xy = np.asarray(pts, dtype=np.float64) * size + shift
    ox, oy = ox * size + shift, oy * size + shift
    if snap:  # put points exactly on tile edges
        xy = ox + np.round((xy - ox) / size) * size
    grid = plan_grid(xy.min(0), xy.max(0), tile_size=size, buffer=buffer_frac * size, grid_origin=(ox, oy))
    core = core_tile(xy, grid)
    # exactly one core per point, and the point is inside that core's half-open bounds
    for i, t in enumerate(core):
        x0, y0, x1, y1 = grid.tile(int(t)).core
        assert x0 <= xy[i, 0] < x1 and y0 <= xy[i, 1] < y1
        cores_holding = [
            tt.id for tt in grid.tiles()
            if tt.core[0] <= xy[i, 0] < tt.core[2] and tt.core[1] <= xy[i, 1] < tt.core[3]
        ]
        assert cores_holding == [int(t)]
    p, tiles = buffered_tiles(xy, grid, core=core)
    got = set(zip(p.tolist(), tiles.tolist()))
    assert len(got) == len(p)  # no duplicate pairs
    assert got == _brute_force(xy, grid)
    assert np.all(np.diff(tiles) >= 0)
    for t in set(tiles.tolist()) | {0, grid.n_tiles - 1}:  # one tile's set alone is the same
        assert np.array_equal(np.flatnonzero(in_buffered(xy, grid, t, core=core)), p[tiles == t])


def test_hand_checked_grid():
    grid = plan_grid((0.0, 0.0), (19.9, 9.9), tile_size=10.0, buffer=1.0, grid_origin=(0.0, 0.0))
    assert (grid.ncols, grid.nrows) == (2, 1)
    assert grid.tile(1).core == (10.0, 0.0, 20.0, 10.0)
    assert grid.tile(1).buffered == (9.0, -1.0, 21.0, 11.0)
    xy = np.array([[10.0, 5.0], [9.5, 5.0], [5.0, 5.0], [9.0, 5.0], [10.9, 5.0]])
    assert core_tile(xy, grid).tolist() == [1, 0, 0, 0, 1]
    p, t = buffered_tiles(xy, grid)
    assert sorted(zip(p.tolist(), t.tolist())) == [(0, 0), (0, 1), (1, 0), (1, 1), (2, 0), (3, 0), (4, 0), (4, 1)]


def test_grid_origin_shifts_edges():
    grid = plan_grid((500_003.0, 6_000_001.0), (500_041.0, 6_000_019.0), tile_size=10.0, buffer=0.0, grid_origin=(500_000.0, 6_000_000.0))
    assert (grid.col0, grid.row0, grid.ncols, grid.nrows) == (0, 0, 5, 2)
    assert grid.tile(0).core[:2] == (500_000.0, 6_000_000.0)


def test_points_outside_the_plan_go_to_edge_tiles():
    grid = plan_grid((0.0, 0.0), (20.0, 20.0), tile_size=10.0, buffer=0.0)
    assert core_tile(np.array([[-5.0, -5.0], [100.0, 100.0]]), grid).tolist() == [0, grid.n_tiles - 1]


def test_buffer_must_cover_reach():
    params = PipelineParams(segment=SegmentParams(max_crown_radius=3.0))
    reach = params.reach()
    plan_grid((0, 0), (50, 50), tile_size=10.0, buffer=reach, reach=reach)
    with pytest.raises(ParameterError) as e:
        plan_grid((0, 0), (50, 50), tile_size=10.0, buffer=2.0, reach=reach)
    msg = str(e.value)
    assert "2 m" in msg and f"{reach:g} m" in msg and "{tiling.buffer}" in e.value.hint
    assert (e.value.param, e.value.value, e.value.limit) == ("tiling.buffer", 2.0, reach)
    with pytest.raises(ParameterError):
        check_buffer(1.0, 1.5)


@pytest.mark.parametrize("size", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_tile_size(size):
    with pytest.raises(ParameterError, match="tile size"):
        plan_grid((0, 0), (10, 10), tile_size=size, buffer=0.0)


def test_a_grid_origin_far_below_the_block_counts_only_the_blocks_tiles():
    # a national grid's origin (0, 0) under a UTM block: 9 tiles, not "more than 1e8 tiles"
    grid = plan_grid((500_003.0, 6_000_001.0), (500_023.0, 6_000_021.0), tile_size=10.0, buffer=2.0, grid_origin=(0.0, 0.0))
    assert (grid.col0, grid.row0, grid.ncols, grid.nrows) == (50_000, 600_000, 3, 3)
    with pytest.raises(ParameterError, match="tile size 0.001 m gives more than"):
        plan_grid((500_003.0, 6_000_001.0), (500_023.0, 6_000_021.0), tile_size=1e-3, buffer=0.0, grid_origin=(0.0, 0.0))
    with pytest.raises(ParameterError, match="lies 5e\\+16 tiles of 1e-09 m from the block"):
        plan_grid((5e7, 5e7), (5e7, 5e7), tile_size=1e-9, buffer=0.0, grid_origin=(0.0, 0.0))


def test_absurd_buffer_and_grid_origin_are_parameter_errors():
    # 2 x 1e308 overflowed to inf in the copy count (an internal error); an origin of
    # 1e21 overflowed the cell numbers (numpy warnings, then a run on garbage cells)
    with pytest.raises(ParameterError, match="tile buffer 1e\\+308 m is wider than any block"):
        check_tiling(20.0, 1e308)
    for origin in ((1e21, 1e21), (-1e16, 0.0), (float("nan"), 0.0)):
        with pytest.raises(ParameterError, match="grid origin must be finite and within 1e\\+08 m of 0"):
            plan_grid((0, 0), (10, 10), tile_size=5.0, buffer=1.0, grid_origin=origin)
    plan_grid((0, 0), (10, 10), tile_size=5.0, buffer=1.0, grid_origin=(-9.9e7, 9.9e7))


def test_too_many_tiles():
    with pytest.raises(ParameterError, match="larger tiling.tile_size") as e:
        plan_grid((0, 0), (10_000, 10_000), tile_size=0.5, buffer=0.0)
    assert e.value.param == "tiling.tile_size"


def test_grid_round_trips_through_dict():
    grid = plan_grid((3.0, 4.0), (45.0, 20.0), tile_size=7.5, buffer=2.0, grid_origin=(1.0, 2.0))
    assert type(grid).from_dict(grid.to_dict()) == grid


def test_copies_per_point_by_hand():
    # a 6.15 m buffer reaches ceil(2 x 6.15 / s) + 1 tiles along each axis, at most the grid's
    assert copies_per_point(10.0, 6.15) == 3 * 3
    assert copies_per_point(20.0, 6.15) == 2 * 2
    assert copies_per_point(1.0, 6.15) == 14 * 14
    assert copies_per_point(1.0, 6.15, ncols=2, nrows=1) == 2
    assert copies_per_point(12.0, 1e6, ncols=2, nrows=1) == 2
    assert copies_per_point(min_tile_size(6.15), 6.15) <= MAX_COPIES < copies_per_point(min_tile_size(6.15) - 0.01, 6.15)


@pytest.mark.parametrize("size", [0.05, 1.0, 1.75])
def test_tiles_much_smaller_than_their_buffer_are_refused(size):
    # every point would be copied into hundreds of buffered tiles: refused before any work
    with pytest.raises(ParameterError, match=r"copy each point .* at least 1\.76 m"):
        plan_grid((0, 0), (50, 50), tile_size=size, buffer=6.15)
    check_tiling(size, 6.15)  # the geometry's own conditions hold: the block's grid says how many copies
    plan_grid((0, 0), (50, 50), tile_size=min_tile_size(6.15), buffer=6.15)


@pytest.mark.parametrize("size", [1e-300, 1e-20])
def test_absurdly_small_tile_size_is_refused_without_overflow(size):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "invalid value encountered in cast"
        with pytest.raises(ParameterError, match="larger tiling.tile_size"):
            plan_grid((0, 0), (50, 50), tile_size=size, buffer=0.0)


def test_huge_buffer_over_a_small_grid_is_cheap():
    # a buffer far wider than the block: every point in every tile of the 2 x 1 grid, and
    # no loop over the 100 km reach (that used to exhaust memory)
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 1, (1000, 2)) * [20.0, 10.0]
    grid = plan_grid((0, 0), (20, 10), tile_size=12.0, buffer=1e5)  # the widest allowed
    assert (grid.ncols, grid.nrows) == (2, 1)
    p, t = buffered_tiles(xy, grid)
    assert len(p) == 2000 and set(zip(p.tolist(), t.tolist())) == _brute_force(xy, grid)
    # a block processed in one piece is one tile, however small next to the buffer
    one = plan_grid((0, 0), (0.5, 0.5), tile_size=1.5, buffer=6.15)
    assert one.ncols * one.nrows == 1


@settings(max_examples=100, deadline=None)
@given(
    pts=st.lists(st.tuples(coord, coord), min_size=1, max_size=80),
    size=st.sampled_from([0.3, 2.5, 10.0]),
    buffer_frac=st.floats(min_value=0.05, max_value=2.5),
    few=st.booleans(),
)
def test_pairs_come_sorted_by_tile_then_point_whether_masked_or_sorted(pts, size, buffer_frac, few):
    # a tile's records are written in this order and read back as its points' order
    import pipeline.tiling as tiling

    xy = np.asarray(pts, dtype=np.float64) * size + 512_345.0
    grid = plan_grid(xy.min(0), xy.max(0), tile_size=size, buffer=buffer_frac * size, grid_origin=(512_345.0 - size, 512_345.0))
    expected = sorted((t, i) for i, t in _brute_force(xy, grid))
    saved = tiling.MASK_SORT_TILES
    tiling.MASK_SORT_TILES = saved if few else 0  # 0: always the sort of the pairs
    try:
        p, t = buffered_tiles(xy, grid)
    finally:
        tiling.MASK_SORT_TILES = saved
    assert p.dtype == np.int64 and t.dtype == np.int64
    assert list(zip(t.tolist(), p.tolist())) == expected
