"""The memory-budget rules: by hand on counted cells, against the header-only rule on a
turned block, and the sampled counts against the true points and voxels of every
buffered tile of a generated block."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.blockinfo import read_info
from pipeline.budget import (
    BYTES_PER_NODE,
    BYTES_PER_POINT,
    FIXED_BYTES,
    SAMPLE_MARGIN,
    BudgetError,
    DensitySample,
    balanced_tile_size,
    bytes_needed,
    count_cells,
    fits_whole,
    makespan,
    sampled_tile_bytes,
    sampled_tile_nodes,
    sampled_tile_points,
    surely_tiled,
    tile_size_for_sample,
)
from pipeline.reading import count_range, read_counted, read_points, sample_density, sample_from_ranges
from pipeline.tiling import buffered_tiles, plan_grid


def _exact(xy: np.ndarray, side: float) -> DensitySample:
    """Every point of ``xy`` (in a ``side`` x ``side`` m block at 0) counted per metre."""
    n = int(side) + 1
    counts = count_cells(xy[:, 0], xy[:, 1], origin=(0.0, 0.0), cell=1.0, shape=(n, n))
    return DensitySample(counts=counts, origin=(0.0, 0.0), cell=1.0, sampled=len(xy), n_points=len(xy))


def test_the_sampled_rule_by_hand():
    # 100 points in every 1 m cell of 300 x 300 m: a buffered tile of core s and buffer 5
    # aligned to the metre covers (s + 10)^2 cells inside the block; 500 k points allow
    # s + 10 <= 70.7 (larger tiles up to 147 m have a tile wholly inside the block, and
    # from 148 m the first tile's buffer alone is too much)
    sample = DensitySample(counts=np.full((300, 300), 100), origin=(0.0, 0.0), cell=1.0,
                           sampled=9_000_000, n_points=9_000_000)
    budget = bytes_needed(500_000)
    assert tile_size_for_sample(sample, (0, 0), (300, 300), budget=budget, buffer=5.0, grid_origin=(0, 0)) == 60.0
    assert sampled_tile_points(sample, 60.0, 5.0, (0, 0), (300, 300), (0, 0)).max() == 100 * 70**2
    assert sampled_tile_points(sample, 61.0, 5.0, (0, 0), (300, 300), (0, 0)).max() == 100 * 71**2  # > 500 k
    # the header-only rule used before doubled the mean density for rows it could not see
    assert _header_rule(9_000_000, (300, 300), 500_000, 5.0) == 40.0
    # a box edge between cell edges counts the whole cell (never fewer points than held)
    assert sampled_tile_points(sample, 60.0, 4.5, (0, 0), (300, 300), (0, 0)).max() == 100 * 70**2
    # half of the points counted: each stands for two, with the margin for sampling error
    half = dataclasses.replace(sample, counts=sample.counts // 2, sampled=4_500_000)
    assert sampled_tile_points(half, 60.0, 5.0, (0, 0), (300, 300), (0, 0)).max() == 100 * 70**2 * SAMPLE_MARGIN
    # whole when the block fits; refused with the densest tile's figures when none does
    assert tile_size_for_sample(sample, (0, 0), (300, 300), budget=bytes_needed(9_000_000), buffer=5.0, grid_origin=(0, 0)) is None
    # (the smallest core is one buffer, 5 m: 15 x 15 cells with its buffer)
    with pytest.raises(BudgetError) as err:
        tile_size_for_sample(sample, (0, 0), (300, 300), budget=bytes_needed(22_499), buffer=5.0, grid_origin=(0, 0))
    assert err.value.tile_size == 5.0 and err.value.need == bytes_needed(100 * 15**2) and err.value.density == 100.0


def test_nodes_per_point_set_the_tile_by_hand():
    # 100 points a metre everywhere; as a sparse scan every point is its own voxel-graph
    # node, as a dense one 10 points share a node. A budget of 100 * 70^2 points' worth at
    # one node a point allows 70 m buffered tiles (a 60 m core) on the sparse block, and on
    # the dense one (95 + 850) / (95 + 85) times the area: sqrt(25,725) = 160.4 m, so a 155 m
    # core (its first tile's buffer begins outside the block: 160 cells)
    assert (BYTES_PER_POINT, BYTES_PER_NODE) == (95, 850)  # the figures below
    points = np.full((300, 300), 100)
    sparse = DensitySample(counts=points, origin=(0.0, 0.0), cell=1.0, sampled=9_000_000, n_points=9_000_000,
                           nodes=points.copy())
    dense = dataclasses.replace(sparse, nodes=points // 10)
    budget = bytes_needed(100 * 70**2)
    assert budget == FIXED_BYTES + 945 * 100 * 70**2
    assert tile_size_for_sample(sparse, (0, 0), (300, 300), budget=budget, buffer=5.0, grid_origin=(0, 0)) == 60.0
    assert tile_size_for_sample(dense, (0, 0), (300, 300), budget=budget, buffer=5.0, grid_origin=(0, 0)) == 155.0
    assert sampled_tile_bytes(dense, 155.0, 5.0, (0, 0), (300, 300), (0, 0)).max() == FIXED_BYTES + 180 * 100 * 160**2
    # no node counts: every point its own node, as the sparse block
    unknown = dataclasses.replace(sparse, nodes=None)
    assert tile_size_for_sample(unknown, (0, 0), (300, 300), budget=budget, buffer=5.0, grid_origin=(0, 0)) == 60.0
    # more nodes than points counted (runs meeting the same voxels) count as one a point
    doubled = dataclasses.replace(sparse, nodes=2 * points)
    assert np.array_equal(sampled_tile_bytes(doubled, 60.0, 5.0, (0, 0), (300, 300), (0, 0)),
                          sampled_tile_bytes(sparse, 60.0, 5.0, (0, 0), (300, 300), (0, 0)))
    # the whole dense block fits what its nodes need, though not what its points alone would
    whole = bytes_needed(9_000_000, 900_000)
    assert tile_size_for_sample(dense, (0, 0), (300, 300), budget=whole, buffer=5.0, grid_origin=(0, 0)) is None
    assert tile_size_for_sample(unknown, (0, 0), (300, 300), budget=whole, buffer=5.0, grid_origin=(0, 0)) is not None


def test_the_makespan_of_tiles_handed_out_largest_first_by_hand():
    assert makespan([5.0, 3.0, 2.0], 1) == 10.0  # one worker: the total
    assert makespan([[2.0, 5.0], [3.0, 0.0]], 5) == 5.0  # a worker a tile: the largest
    # 7 | 5 | 4 -> 7 | 5+3 | 4+3 -> 7+2 | 8 | 7
    assert makespan([3.0, 7.0, 2.0, 4.0, 5.0, 3.0], 3) == 9.0
    assert makespan([4.0, 4.0, 3.0, 3.0, 2.0], 2) == 9.0  # LPT's, not the best split (8: 4+4 | 3+3+2)
    assert makespan([], 2) == 0.0


def _strip_and_line() -> DensitySample:
    """A 45 m x 10 m block of 100 points per m^2 and 1000 more in its column of 1 m cells
    at x in [24, 25)."""
    counts = np.full((10, 45), 100, dtype=np.int64)
    counts[:, 24] += 100
    n = int(counts.sum())
    return DensitySample(counts=counts, origin=(0.0, 0.0), cell=1.0, sampled=n, n_points=n)


def test_one_worker_takes_the_least_total_two_the_balanced_tiles():
    # 5 m buffers, two tiles along x (cores 23-30 m), one row: a core s holds x in
    # [-5, s+5) and [s-5, 50) of the block, 45 + 10 m of columns (1000 points each)
    # whatever s, and the line in both (23-29 m) or in the first only (30 m).
    # 1 worker, the total: 30 m's 36,000 + 20,000 against 57,000 at 23-29 m.
    # 2 workers, the fuller tile: 23 m's 29,000 (+ 28,000); 24 m and up hold more
    sample, where = _strip_and_line(), dict(budget=1e12, buffer=5.0, grid_origin=(0.0, 0.0))
    mins, maxs = (0.0, 0.0), (45.0, 10.0)
    for size, tiles in ((30.0, [36_000.0, 20_000.0]), (29.0, [35_000.0, 22_000.0]), (23.0, [29_000.0, 28_000.0])):
        assert sorted(sampled_tile_points(sample, size, 5.0, mins, maxs, (0.0, 0.0)).ravel(), reverse=True) == tiles
    assert balanced_tile_size(sample, 30.0, mins, maxs, **where, n_workers=1) == 30.0
    assert balanced_tile_size(sample, 30.0, mins, maxs, **where, n_workers=2) == 23.0
    assert balanced_tile_size(sample, 30.0, mins, maxs, **where, n_workers=8) == 23.0


def test_a_grid_origin_between_cell_edges_counts_every_cell_a_tile_touches():
    sample = DensitySample(counts=np.full((300, 300), 100), origin=(0.0, 0.0), cell=1.0,
                           sampled=9_000_000, n_points=9_000_000)
    # cores from 0.5 m: a 60 m core and 5 m buffer spans 71 cells per axis
    assert sampled_tile_points(sample, 60.0, 5.0, (0, 0), (300, 300), (0.5, 0.5)).max() == 100 * 71**2


def _header_rule(n: int, maxs, most: int, buffer: float) -> float:
    """The tile core the rule used before chose [m] for buffered tiles of at most ``most``
    points: from the header alone, twice the mean density over the bounding box (from 0
    to ``maxs``) everywhere."""
    density = 2.0 * n / (float(maxs[0]) * float(maxs[1]))
    return float(np.floor(np.sqrt(most / density) - 2.0 * buffer))


def _rows(n: int, length: float, width: float, angle_deg: float, seed: int = 0) -> np.ndarray:
    """``n`` points of a ``length`` x ``width`` m block of tree rows 5 m apart along its
    length (80 % of the points in 1.5 m wide rows, the rest anywhere), turned by
    ``angle_deg`` and moved to start at 0."""
    rng = np.random.default_rng(seed)
    k = int(0.8 * n)
    u = rng.uniform(0.0, length, n)
    v = np.r_[rng.integers(0, int(width / 5), k) * 5 + 2.5 + rng.uniform(-0.75, 0.75, k), rng.uniform(0, width, n - k)]
    a = np.radians(angle_deg)
    xy = np.c_[u, v] @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    return xy - xy.min(axis=0)


def _densest_tile(xy: np.ndarray, size: float, buffer: float) -> int:
    grid = plan_grid((0, 0), xy.max(axis=0), tile_size=size, buffer=buffer, grid_origin=(0, 0))
    _, tile = buffered_tiles(xy, grid)
    return int(np.bincount(tile).max())


def test_a_turned_block_is_tiled_by_its_local_density_not_its_bounding_box():
    # 400 k points on 200 m x 40 m; turned 45 degrees its bounding box is 3.1 times its
    # area, more than the doubled density of the header-only rule used before covers
    n, most = 400_000, 60_000
    budget = bytes_needed(most)
    for angle in (0.0, 45.0):
        xy = _rows(n, 200.0, 40.0, angle)
        header = _header_rule(n, xy.max(axis=0), most, 5.0)
        side = int(np.ceil(xy.max())) + 1
        sample = DensitySample(count_cells(xy[:, 0], xy[:, 1], origin=(0, 0), cell=1.0, shape=(side, side)),
                               origin=(0.0, 0.0), cell=1.0, sampled=n, n_points=n)
        sampled = tile_size_for_sample(sample, (0, 0), xy.max(axis=0), budget=budget, buffer=5.0, grid_origin=(0, 0))
        assert _densest_tile(xy, sampled, 5.0) <= most  # every tile of the chosen grid keeps the budget
        if angle == 45.0:
            assert _densest_tile(xy, header, 5.0) > 1.3 * most  # the header's tiles break it
            assert sampled < header
        else:
            assert sampled >= 1.5 * header  # the header's tiles waste it


# ---------------------------------------------------------------- on a generated block


@pytest.fixture(scope="module")
def blocks(tmp_path_factory):
    from simulator.simparams import SimulationParams
    from simulator.truth import write_simulation

    folder = tmp_path_factory.mktemp("budget")
    out = {}
    for rotation in (0.0, 45.0):
        path = folder / f"b{rotation:g}.las"  # LAS: runs of any length can be sampled
        write_simulation(SimulationParams(rows=3, trees_per_row=6, density=0.1, seed=4, rotation=rotation),
                         str(path), str(folder / "t.parquet"))
        info = read_info(str(path))
        xyz, _ = read_points(str(path), origin=(0.0, 0.0, 0.0))
        out[rotation] = (info, xyz)
    return out


def test_sampling_every_run_counts_every_point(blocks):
    info, xyz = blocks[0.0]
    sample = sample_density(info.path, info=info, las_run=5_000)
    assert sample.exact and sample.sampled == info.n_points == sample.counts.sum()
    local = xyz[:, :2] - np.asarray(info.origin[:2])
    assert sample.cell == 0.25 and np.array_equal(
        sample.counts, count_cells(local[:, 0], local[:, 1], origin=(0, 0), cell=0.25, shape=sample.counts.shape))


def test_a_file_whose_chunks_cannot_be_reached_out_of_order_is_counted_whole(blocks):
    info, _ = blocks[0.0]
    every = sample_density(info.path, info=info)
    unseekable = sample_density(info.path, info=dataclasses.replace(info, seekable=False), runs=1, fraction=0.25,
                                las_run=2_000)
    assert unseekable.exact and np.array_equal(unseekable.counts, every.counts)


def test_a_truncated_file_is_refused_while_counting(blocks, tmp_path):
    from pipeline.errors import InputError

    info, _ = blocks[0.0]
    short = tmp_path / "short.las"
    data = Path(info.path).read_bytes()
    short.write_bytes(data[: len(data) - 30 * 1000])  # the last thousand or so points gone
    with pytest.raises(InputError):
        sample_density(str(short), info=dataclasses.replace(info, path=str(short)))


@settings(max_examples=25, deadline=None)
@given(
    rotation=st.sampled_from([0.0, 45.0]),
    size=st.integers(9, 30),
    shift=st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0)),
    fraction=st.sampled_from([1.0, 0.45, 0.25]),
)
def test_the_sampled_counts_bound_the_true_tiles(blocks, rotation, size, shift, fraction):
    # the points of every buffered tile of the actual grid, counted from the points, against
    # the estimate from runs of 2,000 points: with every point counted no tile is
    # underestimated; from a quarter of the runs or more the densest tile's estimate is at
    # least the densest tile's points (so the budget holds) and at most 2.5 times them
    info, xyz = blocks[rotation]
    origin = (info.origin[0] + shift[0], info.origin[1] + shift[1])
    sample = sample_density(info.path, info=info, runs=1, fraction=fraction, las_run=2_000)
    assert sample.exact == (fraction == 1.0)
    grid = plan_grid(info.mins, info.maxs, tile_size=float(size), buffer=4.15, grid_origin=origin)
    _, tile = buffered_tiles(xyz, grid)
    true = np.bincount(tile, minlength=grid.n_tiles).reshape(grid.nrows, grid.ncols)
    est = sampled_tile_points(sample, float(size), 4.15, info.mins, info.maxs, origin)
    assert est.shape == true.shape
    if sample.exact:
        assert (est >= true).all()
    assert true.max() <= est.max() <= 2.5 * true.max()


def _voxel_centres(xyz: np.ndarray, voxel_size: float) -> np.ndarray:
    """Centres (x, y) of the distinct voxels of ``voxel_size`` (grid at 0) that ``xyz`` occupies."""
    keys = np.unique(np.floor(xyz / voxel_size).astype(np.int64), axis=0)
    return (keys[:, :2] + 0.5) * voxel_size


def _stored_local(info) -> np.ndarray:
    """The block's points in its local frame, by the stored integers' arithmetic (a point
    on a voxel face falls on the same side as in the count)."""
    import laspy

    las = laspy.read(info.path)
    ints = np.column_stack([las.X, las.Y, las.Z])
    return ints * np.asarray(info.scales) + (np.asarray(info.offsets) - np.asarray(info.origin))


_CENTRES: dict = {}


def _stored_voxel_centres(info, voxel_size: float) -> np.ndarray:
    """`_voxel_centres` of the block's stored points (`_stored_local`), worked out once per
    block and voxel size: the examples below only read them."""
    key = (info.path, voxel_size)
    if key not in _CENTRES:
        _CENTRES[key] = _voxel_centres(_stored_local(info), voxel_size)
        _CENTRES[key].setflags(write=False)
    return _CENTRES[key]


def test_one_run_counts_every_cells_distinct_voxels(blocks):
    info, _ = blocks[0.0]
    sample = sample_density(info.path, info=info, voxel_size=0.1, chunk_points=info.n_points)
    centres = _stored_voxel_centres(info, 0.1)
    assert np.array_equal(sample.counts, sample_density(info.path, info=info).counts)
    assert np.array_equal(sample.nodes, count_cells(centres[:, 0], centres[:, 1], origin=(0, 0), cell=0.25,
                                                    shape=sample.counts.shape))
    assert 0.3 * info.n_points < sample.nodes.sum() < info.n_points  # a sparse block: most points their own voxel


@settings(max_examples=15, deadline=None)
@given(rotation=st.sampled_from([0.0, 45.0]), size=st.integers(9, 30), run=st.sampled_from([3_000, 20_000]),
       voxel=st.sampled_from([0.05, 0.1, 0.2]))
def test_counted_nodes_bound_every_tiles_voxels(blocks, rotation, size, run, voxel):
    # runs of a few thousand points each count their own voxels: a voxel two runs reach
    # counts twice, so no buffered tile's voxels (by centre) are undercounted, and on a
    # block written tree by tree the overcount stays small
    info, _ = blocks[rotation]
    sample = sample_density(info.path, info=info, voxel_size=voxel, chunk_points=run)
    centres = _stored_voxel_centres(info, voxel) + np.asarray(info.origin[:2])
    grid = plan_grid(info.mins, info.maxs, tile_size=float(size), buffer=4.15, grid_origin=info.origin[:2])
    inside = np.zeros(grid.n_tiles, dtype=np.int64)
    for t in grid.tiles():
        x0, y0, x1, y1 = t.buffered
        inside[t.id] = np.count_nonzero((centres[:, 0] > x0) & (centres[:, 0] < x1) & (centres[:, 1] > y0) & (centres[:, 1] < y1))
    true = inside.reshape(grid.nrows, grid.ncols)
    est = sampled_tile_nodes(sample, float(size), 4.15, info.mins, info.maxs, info.origin[:2])
    assert (est >= true).all()
    assert sample.nodes.sum() <= 1.5 * len(centres)


@pytest.mark.parametrize("rotation", [0.0, 45.0])
@pytest.mark.parametrize("run", [3_000, 20_000])
def test_ranges_counted_apart_sum_to_the_sequential_count(blocks, rotation, run):
    # workers count their own ranges; summed, the sample is the one a single pass over
    # runs of the same length gives, voxel for voxel (a voxel's centre may lie in a cell
    # none of its run's points do: those cells must come back too)
    info, _ = blocks[rotation]
    whole = sample_density(info.path, info=info, voxel_size=0.1, chunk_points=run)
    parts = [count_range(info.path, start, run, info=info, voxel_size=0.1) for start in range(0, info.n_points, run)]
    summed = sample_from_ranges(info, reversed(parts))  # tasks finish in any order
    assert summed.exact and summed.sampled == whole.sampled == info.n_points
    assert np.array_equal(summed.counts, whole.counts) and np.array_equal(summed.nodes, whole.nodes)
    assert (summed.cell, summed.origin) == (whole.cell, whole.origin)
    points_only = sample_from_ranges(info, [count_range(info.path, s, run, info=info) for s in range(0, info.n_points, run)])
    assert points_only.nodes is None and np.array_equal(points_only.counts, whole.counts)


@pytest.mark.parametrize("run", [3_000, 20_000])
def test_reading_and_counting_in_one_pass_gives_the_read_and_the_count(blocks, run):
    # a job that counts a block and keeps it whole reads it once: the points must be
    # read_points' to the bit, and the count sample_density's, cell for cell
    info, _ = blocks[45.0]
    xyz, counted = read_counted(info.path, info=info, voxel_size=0.1, chunk_points=run)
    assert np.array_equal(xyz, read_points(info.path)[0])
    whole = sample_density(info.path, info=info, voxel_size=0.1, chunk_points=run)
    assert counted.exact and counted.sampled == whole.sampled == info.n_points
    assert np.array_equal(counted.counts, whole.counts) and np.array_equal(counted.nodes, whole.nodes)
    assert (counted.cell, counted.origin) == (whole.cell, whole.origin)
    _, points_only = read_counted(info.path, info=info, chunk_points=run)
    assert points_only.nodes is None and np.array_equal(points_only.counts, whole.counts)


@pytest.mark.parametrize("voxel", [0.1, 0.4])
def test_voxels_counted_on_a_grid_or_by_a_sort_are_the_same(blocks, voxel, monkeypatch):
    # a run whose voxel grid has at most a few cells a point marks them on the grid; the
    # sort it replaces must give the same voxels (forced here by allowing no cell a point)
    import pipeline.reading
    from pipeline.voxels import packed_keys

    info, xyz = blocks[45.0]
    local = xyz - np.asarray(info.origin)
    _, _, span = packed_keys(local, voxel, (0.0, 0.0, 0.0))
    dense = int(np.prod(span)) <= pipeline.reading.DENSE_CELLS_PER_POINT * len(xyz)
    assert dense == (voxel == 0.4)  # both paths are taken here
    grid = sample_density(info.path, info=info, voxel_size=voxel)
    monkeypatch.setattr(pipeline.reading, "DENSE_CELLS_PER_POINT", 0)
    sorted_ = sample_density(info.path, info=info, voxel_size=voxel)
    assert np.array_equal(grid.nodes, sorted_.nodes) and np.array_equal(grid.counts, sorted_.counts)
    assert grid.nodes.sum() > 0


def test_a_truncated_file_is_refused_while_reading_and_counting(blocks, tmp_path):
    from pipeline.errors import InputError

    info, _ = blocks[0.0]
    short = tmp_path / "short.las"
    data = Path(info.path).read_bytes()
    short.write_bytes(data[: len(data) - 30 * 1000])
    with pytest.raises(InputError):
        read_counted(str(short), info=dataclasses.replace(info, path=str(short)), voxel_size=0.1)


def test_a_range_beyond_the_file_is_refused(blocks):
    from pipeline.errors import InputError

    info, _ = blocks[0.0]
    with pytest.raises(InputError):
        count_range(info.path, info.n_points - 10, 20, info=dataclasses.replace(info, n_points=info.n_points + 10))


def test_surely_tiled_needs_more_than_the_budget_with_no_node_at_all():
    n = 1_000_000
    at = FIXED_BYTES + BYTES_PER_POINT * n  # what n points need with no graph
    assert surely_tiled(n, at - 1) and not surely_tiled(n, at) and not surely_tiled(n, None)
    assert not fits_whole(n, at)  # between the two rules: the block is counted


def test_a_workers_range_of_the_file_follows_its_budget():
    from pipeline.budget import FIXED_BYTES, MIN_RANGE_POINTS, RANGE_BYTES_PER_POINT, range_points

    assert range_points(None, 2_000_000) == 2_000_000  # no budget
    assert range_points(2e9, 2_000_000) == 2_000_000  # the default budget keeps the default range
    at = FIXED_BYTES + 1_000_000 * RANGE_BYTES_PER_POINT
    assert range_points(at, 2_000_000) == 1_000_000 and range_points(at - RANGE_BYTES_PER_POINT, 2_000_000) == 999_999
    assert range_points(0.31e9, 2_000_000) == MIN_RANGE_POINTS  # never below the floor ...
    assert range_points(0.31e9, 20_000) == 20_000  # ... nor above the range asked for

