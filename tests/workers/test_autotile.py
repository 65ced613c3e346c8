"""Tiles chosen for a memory budget: a block that fits stays whole, a larger one is cut
into tiles whose counted points keep the budget, and the result is the untiled one."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.budget import (
    BYTES_PER_NODE,
    BYTES_PER_POINT,
    FIXED_BYTES,
    MIN_CORE_PER_BUFFER,
    BudgetError,
    DensitySample,
    balanced_tile_size,
    block_bytes,
    bytes_needed,
    fits_whole,
    makespan,
    sampled_tile_bytes,
    sampled_tile_nodes,
    sampled_tile_points,
    smallest_tile,
    tile_size_for_sample,
)
from pipeline.jobparams import JobParams, TilingParams
from pipeline.params import PipelineParams
from workers.job import run_job
from workers.jobspec import JobSpec, auto_tiled, budgeted
from workers.runoptions import RunOptions


def _uniform(n_points: int, width: int, depth: int) -> DensitySample:
    """``n_points`` spread evenly over 1 m cells of a ``width`` x ``depth`` m block at 0."""
    counts = np.full((depth, width), n_points // (width * depth), dtype=np.int64)
    return DensitySample(counts=counts, origin=(0.0, 0.0), cell=1.0, sampled=int(counts.sum()), n_points=int(counts.sum()))


#: hypothesis strategies of :func:`_random`'s block and a budget: width, depth [m], seed,
#: buffer [m], budget [B], grid origin [m]
RANDOM_BLOCK = (
    st.integers(5, 120),
    st.integers(5, 120),
    st.integers(0, 2**32 - 1),
    st.floats(0.0, 10.0),
    st.floats(3.1e8, 3e9),
    st.tuples(st.floats(-3.0, 0.0), st.floats(-3.0, 0.0)),
)


def _random(width: int, depth: int, seed: int, nodes_per_point: float | None = None) -> tuple[DensitySample, tuple, tuple]:
    """A block of 1 m cells with random counts (three in ten empty), and its bounds;
    with ``nodes_per_point``, nodes per cell around that share of its points (cells
    differ: rows against alleys)."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 20_000, size=(depth, width)) * (rng.random((depth, width)) < 0.7)
    n = int(counts.sum())
    nodes = None if nodes_per_point is None else np.round(counts * nodes_per_point * rng.uniform(0.2, 1.8, counts.shape)).astype(np.int64)
    sample = DensitySample(counts=counts, origin=(0.0, 0.0), cell=1.0, sampled=n, n_points=n, nodes=nodes)
    return sample, (0.0, 0.0), (float(width), float(depth))


def test_a_small_dense_block_over_the_budget_stays_whole():
    # 11 M points on 15 m x 15 m: the smallest tile with its buffer (7 + 2 x 6.25 m) holds all of it
    sample = _uniform(11_000_000, 15, 15)
    assert tile_size_for_sample(sample, (0, 0), (15, 15), budget=2e9, buffer=6.25, grid_origin=(0, 0)) is None


def test_the_budget_named_in_the_refusal_is_enough():
    sample = _uniform(50_000_000, 100, 100)
    with pytest.raises(BudgetError) as err:
        tile_size_for_sample(sample, (0, 0), (100, 100), budget=0.5e9, buffer=6.25, grid_origin=(0, 0))
    enough = math.ceil(err.value.need / 1e8) / 10 * 1e9  # as the command line words it
    assert tile_size_for_sample(sample, (0, 0), (100, 100), budget=enough, buffer=6.25, grid_origin=(0, 0)) is not None


def test_a_budget_below_the_smallest_tile_is_refused_with_its_figures():
    # 100 points a metre; the smallest core is one buffer, 5 m, so a buffered tile inside
    # the block covers 15 x 15 cells: 22,500 points
    with pytest.raises(BudgetError) as err:
        tile_size_for_sample(_uniform(1_000_000, 100, 100), (0, 0), (100, 100), budget=205e6, buffer=5.0, grid_origin=(0, 0))
    e = err.value
    assert e.budget == 205e6 and e.density == 100.0 and e.tile_size == 5.0 and e.buffer == 5.0
    assert e.need == pytest.approx(bytes_needed(100 * 15.0**2)) and e.need > e.budget
    assert "GB" in str(e) and "--" not in str(e)  # no command-line wording in workers' errors


@settings(max_examples=150, deadline=None)
@given(*RANDOM_BLOCK, st.sampled_from([None, 0.05, 0.3, 1.0]))
def test_the_chosen_tile_keeps_the_budget_and_is_the_largest_that_does(width, depth, seed, buffer, budget, origin,
                                                                       nodes_per_point):
    sample, mins, maxs = _random(width, depth, seed, nodes_per_point)
    nodes = sample.nodes
    try:
        size = tile_size_for_sample(sample, mins, maxs, budget=budget, buffer=buffer, grid_origin=origin)
    except BudgetError as e:
        assert e.need > budget and e.tile_size == smallest_tile(buffer)
        assert sampled_tile_bytes(sample, e.tile_size, buffer, mins, maxs, origin).max() == e.need
        return
    if size is None:  # the block fits, or is no larger than the smallest tile and its buffer
        assert block_bytes(sample) <= budget or smallest_tile(buffer) + 2 * buffer >= max(width, depth)
        return
    assert block_bytes(sample) > budget
    assert size == int(size) and size >= MIN_CORE_PER_BUFFER * buffer and size >= smallest_tile(buffer)
    assert sampled_tile_bytes(sample, size, buffer, mins, maxs, origin).max() <= budget
    for larger in range(int(size) + 1, max(width, depth) + 2):
        assert sampled_tile_bytes(sample, float(larger), buffer, mins, maxs, origin).max() > budget
    # each tile's bytes by the model, from its points and nodes (at most one a point)
    points = sampled_tile_points(sample, size, buffer, mins, maxs, origin)
    held = points if nodes is None else np.minimum(sampled_tile_nodes(sample, size, buffer, mins, maxs, origin), points)
    assert np.allclose(sampled_tile_bytes(sample, size, buffer, mins, maxs, origin),
                       FIXED_BYTES + BYTES_PER_POINT * points + BYTES_PER_NODE * held)


def test_a_block_a_little_wider_than_one_tile_is_cut_in_halves_not_in_a_tile_and_its_rest():
    # 45 m: the largest core that keeps the budget is 30 m (a 30 m tile and a 15 m one
    # along each axis); two 23 m tiles share the points evenly
    sample = _uniform(45 * 45 * 1000, 45, 45)
    budget = float(sampled_tile_bytes(sample, 30.0, 5.0, (0, 0), (45, 45), (0, 0)).max())
    size = tile_size_for_sample(sample, (0, 0), (45, 45), budget=budget, buffer=5.0, grid_origin=(0, 0))
    assert size == 30.0
    where = dict(budget=budget, buffer=5.0, grid_origin=(0, 0))
    assert balanced_tile_size(sample, size, (0, 0), (45, 45), **where, n_workers=2) == 23.0
    # one worker: every 2 x 2 grid holds the same 55 x 55 m of buffered tiles (ties: the larger)
    assert balanced_tile_size(sample, size, (0, 0), (45, 45), **where, n_workers=1) == 30.0
    points = sampled_tile_points(sample, 23.0, 5.0, (0, 0), (45, 45), (0, 0))
    assert points.shape == (2, 2) and points.max() <= 1.1 * points.min()


@settings(max_examples=100, deadline=None)
@given(*RANDOM_BLOCK, st.integers(1, 6))
def test_the_balanced_tile_keeps_the_budget_and_the_tiles_and_its_workers_finish_soonest(width, depth, seed, buffer,
                                                                                           budget, origin, n_workers):
    sample, mins, maxs = _random(width, depth, seed)
    try:
        largest = tile_size_for_sample(sample, mins, maxs, budget=budget, buffer=buffer, grid_origin=origin)
    except BudgetError:
        return
    if largest is None:
        return
    size = balanced_tile_size(sample, largest, mins, maxs, budget=budget, buffer=buffer, grid_origin=origin,
                              n_workers=n_workers)
    assert size == int(size) and smallest_tile(buffer) <= size <= largest
    shape = sampled_tile_points(sample, largest, buffer, mins, maxs, origin).shape
    assert sampled_tile_points(sample, size, buffer, mins, maxs, origin).shape == shape
    assert sampled_tile_bytes(sample, size, buffer, mins, maxs, origin).max() <= budget

    def lpt(points):  # the tiles largest first, each to the worker free first
        loads = [0.0] * n_workers
        for p in sorted(points.ravel().tolist(), reverse=True):
            loads[loads.index(min(loads))] += p
        return max(loads)

    time = lpt(sampled_tile_points(sample, size, buffer, mins, maxs, origin))
    assert time == makespan(sampled_tile_points(sample, size, buffer, mins, maxs, origin), n_workers)
    for other in range(int(smallest_tile(buffer)), int(largest) + 1):  # none sooner, larger ones later
        points = sampled_tile_points(sample, float(other), buffer, mins, maxs, origin)
        if points.shape == shape and sampled_tile_bytes(sample, float(other), buffer, mins, maxs, origin).max() <= budget:
            assert lpt(points) >= time
            assert other <= size or lpt(points) > time


# ---------------------------------------------------------------- on a generated block

#: a smaller reach than the default (max crown radius 3 m, the simulator's crowns are
#: 2.75 m) so that a block of 18 trees holds several tiles
PARAMS = {"segment": {"max_crown_radius": 3.0}}


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    from pipeline.blockinfo import read_info
    from simulator.simparams import SimulationParams
    from simulator.truth import write_simulation

    folder = tmp_path_factory.mktemp("autotile")
    path = folder / "b.laz"
    write_simulation(SimulationParams(rows=3, trees_per_row=6, density=0.1, seed=4), str(path), str(folder / "t.parquet"))
    return path, read_info(str(path))


def _budget(info) -> float:
    """A budget the whole block does not fit, with room for a few tiles of 16 m or so (14 m balanced):
    a header-only rule refuses it (its smallest tile at twice the mean density needs
    more), the densest tiles the block really has do not."""
    from pipeline.reading import sample_density

    return FIXED_BYTES + 0.575 * (block_bytes(sample_density(info.path, info=info, voxel_size=0.1)) - FIXED_BYTES)


def _densest_tile(path, info, size: float, buffer: float) -> tuple[int, int]:
    """Points and occupied 10 cm voxels of the buffered tile of the grid that holds most points."""
    from pipeline.reading import read_points
    from pipeline.tiling import buffered_tiles, plan_grid

    xyz, _ = read_points(path, origin=(0.0, 0.0, 0.0))
    grid = plan_grid(info.mins, info.maxs, tile_size=size, buffer=buffer, grid_origin=info.origin[:2])
    point, tile = buffered_tiles(xyz, grid)
    densest = int(np.argmax(np.bincount(tile)))
    mine = xyz[point[tile == densest]]
    return len(mine), len(np.unique(np.floor(mine / 0.1).astype(np.int64), axis=0))


def test_a_block_within_the_budget_is_left_whole_and_one_above_it_is_tiled(block, tmp_path):
    path, info = block
    params = PipelineParams.model_validate(PARAMS)
    whole = JobSpec(str(path), str(tmp_path / "o"), job=JobParams(pipeline=params), run=RunOptions(worker_memory=bytes_needed(info.n_points) / 1e9))
    assert auto_tiled(whole, info) is whole
    assert auto_tiled(JobSpec(str(path), str(tmp_path / "o"), job=JobParams(pipeline=params)), info).tiling.tile_size is None  # no budget
    assert auto_tiled(JobSpec(str(path), str(tmp_path / "o"), job=JobParams(pipeline=params, tiling=TilingParams(tile_size=7.0)), run=RunOptions(worker_memory=1.0 / 1e9)), info).tiling.tile_size == 7.0
    spec = auto_tiled(JobSpec(str(path), str(tmp_path / "o"), job=JobParams(pipeline=params), run=RunOptions(worker_memory=_budget(info) / 1e9)), info)
    size = spec.tiling.tile_size
    assert size is not None and size >= MIN_CORE_PER_BUFFER * params.reach()
    # every buffered tile of the job's grid holds no more points and voxels than the budget allows
    points, voxels = _densest_tile(str(path), info, size, params.reach())
    assert bytes_needed(points, voxels) <= _budget(info)
    assert _header_rule_refuses(info, _budget(info), params.reach())


def test_a_block_counted_and_kept_whole_is_decoded_once(block, tmp_path, monkeypatch):
    # a block that may not fit is counted; kept whole, the job processes the points read
    # for the count instead of decoding the file a second time
    import workers.job
    import workers.jobspec
    from pipeline.reading import read_points, sample_density

    path, info = block
    params = PipelineParams.model_validate(PARAMS)
    budget = block_bytes(sample_density(info.path, info=info, voxel_size=0.1))  # what it needs whole, as counted
    assert not fits_whole(info.n_points, budget)  # so it is counted
    spec = JobSpec(str(path), str(tmp_path / "counted"), job=JobParams(pipeline=params), run=RunOptions(worker_memory=budget / 1e9))
    kept, points = budgeted(spec, info)
    assert kept.tiling.tile_size is None and np.array_equal(points, read_points(str(path))[0])
    tiled, none = budgeted(JobSpec(str(path), str(tmp_path / "t"), job=JobParams(pipeline=params), run=RunOptions(worker_memory=_budget(info) / 1e9)), info)
    assert tiled.tiling.tile_size is not None and none is None  # not held while tiles run

    reads = []  # every decode of the block, by the name it is called through
    for module, name in ((workers.job, "read_points"), (workers.jobspec, "read_points"), (workers.jobspec, "read_counted")):
        original = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, _f=original, _n=f"{module.__name__}.{name}", **k:
                            reads.append(_n) or _f(*a, **k))
    counted = run_job(spec)
    assert reads == ["workers.jobspec.read_counted"] and counted.n_tiles == 1
    plain = run_job(JobSpec(str(path), str(tmp_path / "plain"), job=JobParams(pipeline=params)))  # fits the default budget surely
    assert reads[1:] == ["workers.jobspec.read_points"]  # read before the job's work, once
    assert counted.n_trees == plain.n_trees >= 15
    for name in ("trees.parquet", "points.parquet"):
        a, b = pq.read_table(tmp_path / "counted" / name), pq.read_table(tmp_path / "plain" / name)
        assert a.column_names == b.column_names
        for col in a.column_names:  # NaN where a trunk has no circle: equal here
            np.testing.assert_array_equal(a[col].to_numpy(), b[col].to_numpy(), err_msg=f"{name}: {col}")


def _header_rule_refuses(info, budget: float, buffer: float) -> bool:
    """Whether a rule from the header alone refuses ``budget``: twice the mean density
    over the bounding box, every point its own node, for its smallest tile (a core of
    two buffers), as the rule before the counted one."""
    area = (info.maxs[0] - info.mins[0]) * (info.maxs[1] - info.mins[1])
    return bytes_needed(2.0 * info.n_points / area * (math.ceil(2 * buffer) + 2 * buffer) ** 2) > budget


@pytest.mark.slow
def test_the_tiles_chosen_for_a_budget_give_the_untiled_result(block, tmp_path, monkeypatch):
    import workers.job
    from pipeline.budget import range_points
    from pipeline.chunks import CHUNK_POINTS

    path, info = block
    params = PipelineParams.model_validate(PARAMS)
    single = run_job(JobSpec(str(path), str(tmp_path / "single"), job=JobParams(pipeline=params)))
    ranges = []  # the tiler's ranges of the file follow the budget too
    tile_block = workers.job.tile_block
    monkeypatch.setattr(workers.job, "tile_block", lambda *a, **k: ranges.append(k["chunk_points"]) or tile_block(*a, **k))
    spec = JobSpec(str(path), str(tmp_path / "tiled"), job=JobParams(pipeline=params), run=RunOptions(worker_memory=_budget(info) / 1e9))
    tiled = run_job(spec)
    assert ranges == [range_points(_budget(info), CHUNK_POINTS)] and ranges[0] < CHUNK_POINTS
    # balanced tiles: smaller than the largest that keeps the budget, as many, their fullest holding fewer points
    from pipeline.reading import sample_density
    from pipeline.tiling import plan_grid

    largest = tile_size_for_sample(sample_density(str(path), info=info, voxel_size=0.1), info.mins, info.maxs,
                                   budget=_budget(info), buffer=params.reach(), grid_origin=info.origin[:2])
    size = auto_tiled(spec, info).tiling.tile_size
    assert size < largest
    grids = [plan_grid(info.mins, info.maxs, tile_size=s, buffer=params.reach(), grid_origin=info.origin[:2])
             for s in (size, largest)]
    assert grids[0].ncols == grids[1].ncols and grids[0].nrows == grids[1].nrows
    assert _densest_tile(str(path), info, size, params.reach())[0] < _densest_tile(str(path), info, largest, params.reach())[0]
    assert single.n_tiles == 1 and tiled.n_tiles >= 6
    assert tiled.n_trees == single.n_trees >= 15
    for col in ("tree_id", "n_points"):
        assert np.array_equal(single.trees[col], tiled.trees[col]), col
    # on the balanced 14 m grid one trunk stands 1.1 m from a core border: its base comes
    # out 3 µm higher in its tile than untiled (the tile's ground), its fit 18 µm aside
    for col in ("trunk_x", "trunk_y", "height_m"):
        assert np.abs(single.trees[col] - tiled.trees[col]).max() <= 1e-4, col
    pa = pq.read_table(tmp_path / "single" / "points.parquet", columns=["point_index", "tree_id", "is_ground"]).to_pydict()
    pb = pq.read_table(tmp_path / "tiled" / "points.parquet", columns=["point_index", "tree_id", "is_ground"]).to_pydict()
    assert pa["point_index"] == pb["point_index"] and pa["tree_id"] == pb["tree_id"]
    # one point of 159 k lies on the ground model's edge differently in its tile
    assert np.mean(np.asarray(pa["is_ground"]) == np.asarray(pb["is_ground"])) >= 0.9999


# VmHWM, not getrusage: ru_maxrss survives exec, and would count the forking pytest's memory
_RUN = """
import json, re, sys
from pipeline.jobparams import JobParams
from pipeline.params import PipelineParams
from workers.job import run_job
from workers.jobspec import JobSpec
from workers.runoptions import RunOptions
spec = JobSpec(sys.argv[1], sys.argv[2], job=JobParams(pipeline=PipelineParams.model_validate_json(sys.argv[3])),
               run=RunOptions(worker_memory=float(sys.argv[4]) / 1e9))
outcome = run_job(spec)
peak = int(re.search(r"VmHWM:\\s+(\\d+) kB", open("/proc/self/status").read()).group(1)) * 1024
print(json.dumps({"tiles": outcome.n_tiles, "peak": peak}))
"""


@pytest.mark.slow
def test_a_process_running_the_budgets_tiles_stays_within_it(block, tmp_path):
    # a sanity bound on the estimate, not a measurement: the peak resident memory of a
    # process running the whole job (its tiles one after the other, then the merge), at a
    # budget the header-only rule refuses for this block
    path, info = block
    budget = _budget(info)
    params = PipelineParams.model_validate(PARAMS).model_dump_json()
    p = subprocess.run(
        [sys.executable, "-c", _RUN, str(path), str(tmp_path / "out"), params, str(budget)],
        capture_output=True, text=True, timeout=600,
    )
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got["tiles"] > 1
    assert got["peak"] <= budget, (got, budget / 1e6)


# ---------------------------------------------------------------- orchard process


def _process(capsys, *argv) -> tuple[int, str]:
    from service.cli import main

    code = main(["process", *map(str, argv)])
    return code, capsys.readouterr().err


def test_tile_size_0_keeps_a_block_whole_whatever_the_budget_says(block, tmp_path, capsys, monkeypatch):
    path, _ = block
    monkeypatch.setenv("ORCHARD_WORKER_MEMORY_GB", "0.21")  # tiles (or a refusal) without --tile-size 0
    code, err = _process(capsys, path, "--out", tmp_path / "o", "--tile-size", 0, "--segment-max-crown-radius", 3)
    assert code == 0, err
    assert "1 tile(s)" in err and "tiles of" not in err


def test_a_block_counted_and_kept_whole_is_counted_once(block, tmp_path, capsys, monkeypatch):
    # between what the header surely allows (every point a node) and what its counted
    # voxels need: the command counts it, keeps it whole, and the job must neither count
    # it again nor decode it again (it processes the points read for the count)
    import workers.job
    import workers.jobspec as jobspec
    from pipeline.reading import read_counted, sample_density

    path, info = block
    need = block_bytes(sample_density(str(path), info=info, voxel_size=0.1))
    assert need < 0.42e9 < bytes_needed(info.n_points)
    calls = []
    monkeypatch.setattr(jobspec, "sample_density", lambda *a, **k: calls.append("count") or sample_density(*a, **k))
    monkeypatch.setattr(jobspec, "read_counted", lambda *a, **k: calls.append("read and count") or read_counted(*a, **k))
    monkeypatch.setattr(workers.job, "read_points", lambda *a, **k: calls.append("read"))
    code, err = _process(capsys, path, "--out", tmp_path / "o", "--segment-max-crown-radius", 3, "--worker-memory", 0.42)
    assert code == 0, err
    assert "1 tile(s)" in err and calls == ["read and count"]


@pytest.mark.parametrize(
    "argv, words",
    [
        # (counted by a cluster of worker processes first)
        pytest.param(["--worker-memory", "0.21"], "too small for this block", marks=pytest.mark.slow),
        (["--worker-memory", "0"], "--worker-memory: Input should be greater than 0"),
        (["--worker-memory", "nan"], "--worker-memory: Input should be a finite number"),
        (["--worker-memory", "1", "--tile-size", "10"], "not both"),
        (["--tile-size", "0", "--scheduler", "tcp://127.0.0.1:1"], "--tile-size 0"),
    ],
)
def test_a_budget_that_cannot_work_is_one_line_exit_2_before_any_output(block, tmp_path, capsys, argv, words):
    path, _ = block
    code, err = _process(capsys, path, "--out", tmp_path / "o", "--segment-max-crown-radius", 3, *argv)
    assert code == 2 and len(err.strip().splitlines()) == 1 and words in err, err
    assert not (tmp_path / "o").exists()
    if "too small" in words:
        assert "(--worker-memory 0.4 or more)" in err  # the smallest tile's need, 0.330 GB, rounded up


@pytest.mark.slow
def test_a_block_that_surely_needs_tiles_is_counted_by_the_workers(block, tmp_path, capsys, monkeypatch):
    # the header alone says so (a budget below its points with no graph at all): the
    # command starts its cluster first and the workers count the block, not this process
    import pipeline.budget
    import pipeline.reading
    import workers.cellranges
    import workers.counting
    import workers.jobspec

    def not_here(*a, **k):
        raise AssertionError("counted in the submitting process")

    path, info = block
    gb = _budget(info) / 1e9
    monkeypatch.setattr(pipeline.budget, "surely_tiled", lambda n, budget: True)  # this small block is not
    monkeypatch.setattr(workers.counting, "CHUNK_POINTS", 40_000)  # several ranges, as a large block has
    monkeypatch.setattr(workers.cellranges, "CHUNK_POINTS", 40_000)  # (counted as they are split)
    for module in (workers.jobspec, pipeline.reading, workers.counting):
        monkeypatch.setattr(module, "sample_density", not_here)
    monkeypatch.setattr(workers.jobspec, "read_counted", not_here)
    code, err = _process(capsys, path, "--out", tmp_path / "o", "--segment-max-crown-radius", 3, "--worker-memory", gb,
                         "--workers", 2, "--no-dashboard")
    assert code == 0, err
    lines = err.splitlines()
    ranges = -(-info.n_points // 40_000)
    # a progress line as each range is counted, then the tiles the count chose and the cluster
    assert [line.split("]")[1].split()[0] for line in lines[: ranges + 1]] == [f"{k}/{ranges}" for k in range(ranges + 1)]
    assert all(line.startswith("counting [") for line in lines[: ranges + 1]), err
    # 16 m the largest that keeps the budget, 14 m the same 3 x 2 tiles balanced (balanced_tile_size)
    assert "tiles of 14 m" in lines[ranges + 1] and lines[ranges + 2] == "dask dashboard: none", err


@pytest.mark.slow
def test_orchard_process_tiles_a_block_above_its_budget(block, tmp_path, capsys):
    path, info = block
    gb = _budget(info) / 1e9
    code, err = _process(capsys, path, "--out", tmp_path / "o", "--segment-max-crown-radius", 3, "--worker-memory", gb,
                         "--workers", 1, "--no-dashboard")  # options of a tiled run, taken when the budget tiles
    assert code == 0, err
    assert "tiles of 14 m" in err and "1 tile(s)" not in err and "dask dashboard: none" in err  # 16 m balanced
