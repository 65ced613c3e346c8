"""Tiles chosen for a memory budget: a block that fits stays whole, a larger one is cut
into tiles whose estimated need keeps the budget, and the result is the untiled one."""

from __future__ import annotations

import math

import json
import subprocess
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.jobparams import TilingParams
from pipeline.params import PipelineParams
from pipeline.budget import (
    BYTES_PER_POINT,
    DENSITY_HEADROOM,
    FIXED_BYTES,
    MIN_CORE_PER_BUFFER,
    BudgetError,
    tile_points,
    tile_size_for_budget,
)
from pipeline.tiling import min_tile_size
from workers.job import run_job
from workers.jobspec import JobSpec, auto_tiled


def _need(points: float) -> float:
    return FIXED_BYTES + points * BYTES_PER_POINT


def test_tile_size_by_hand():
    # 1 M points over 100 x 100 m: 100 points/m^2, 200 with the headroom. At 400 bytes a
    # point, 400 MB leaves 200 MB = 500 k points for a buffered tile: sqrt(500 k / 200) =
    # 50 m, less 2 x 5 m
    assert DENSITY_HEADROOM == 2.0 and FIXED_BYTES == 200e6
    assert tile_size_for_budget(1_000_000, (0, 0), (100, 100), budget=400e6, buffer=5.0, bytes_per_point=400) == 40.0
    assert tile_points(40.0, 5.0, 1_000_000, (0, 0), (100, 100)) == 500_000
    # the whole block needs 200 MB + 400 MB: 600 MB keeps it in one piece, a byte less does not
    assert tile_size_for_budget(1_000_000, (0, 0), (100, 100), budget=600e6, buffer=5.0, bytes_per_point=400) is None
    assert tile_size_for_budget(1_000_000, (0, 0), (100, 100), budget=600e6 - 1, buffer=5.0, bytes_per_point=400) is not None


def test_a_small_dense_block_over_the_budget_stays_whole():
    # 11 M points on 20 m x 20 m: the smallest tile with its buffer holds all of it
    assert tile_size_for_budget(11_000_000, (0, 0), (20, 20), budget=2e9, buffer=6.25) is None


def test_the_budget_named_in_the_refusal_is_enough():
    with pytest.raises(BudgetError) as err:
        tile_size_for_budget(50_000_000, (0, 0), (100, 100), budget=2e9, buffer=6.25)
    enough = math.ceil(err.value.need / 1e8) / 10 * 1e9  # as the command line words it
    assert tile_size_for_budget(50_000_000, (0, 0), (100, 100), budget=enough, buffer=6.25) is not None


def test_a_budget_below_the_smallest_tile_is_refused_with_its_figures():
    with pytest.raises(BudgetError) as err:
        tile_size_for_budget(1_000_000, (0, 0), (100, 100), budget=210e6, buffer=5.0)
    e = err.value
    assert e.budget == 210e6 and e.density == 100.0 and e.tile_size == 10.0 and e.buffer == 5.0
    assert e.need == pytest.approx(_need(200 * 20.0**2)) and e.need > e.budget
    assert "GB" in str(e) and "--" not in str(e)  # no command-line wording in workers' errors


@settings(max_examples=300, deadline=None)
@given(
    st.integers(1, 10**9),
    st.floats(0.0, 5000.0),
    st.floats(0.0, 5000.0),
    st.floats(0.0, 20.0),
    st.floats(1e8, 1e11),
)
def test_the_chosen_tile_keeps_the_budget_and_is_the_largest_that_does(n, width, depth, buffer, budget):
    mins, maxs = (10.0, -3.0), (10.0 + width, -3.0 + depth)
    try:
        size = tile_size_for_budget(n, mins, maxs, budget=budget, buffer=buffer)
    except BudgetError as e:
        assert e.need > budget
        return
    smallest = math.ceil(max(MIN_CORE_PER_BUFFER * buffer, min_tile_size(buffer), 1.0))
    if size is None:  # the block fits, or is no larger than the smallest tile and its buffer
        assert _need(n) <= budget or smallest + 2 * buffer >= max(width, depth)
        return
    assert _need(n) > budget
    assert size == int(size) and size >= MIN_CORE_PER_BUFFER * buffer and size >= 1.0
    assert _need(tile_points(size, buffer, n, mins, maxs)) <= budget * (1 + 1e-12)
    assert _need(tile_points(size + 1.0, buffer, n, mins, maxs)) > budget


# ---------------------------------------------------------------- on a generated block

#: a smaller reach than the default (max crown radius 3 m, the simulator's crowns are
#: 2.75 m) so that a block of 18 trees holds several tiles
PARAMS = {"segment": {"max_crown_radius": 3.0}}


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    from pipeline.blockinfo import read_info
    from pipeline.synthetic.simparams import SimulationParams
    from pipeline.synthetic.truth import write_simulation

    folder = tmp_path_factory.mktemp("autotile")
    path = folder / "b.laz"
    write_simulation(SimulationParams(rows=3, trees_per_row=6, density=0.1, seed=4), str(path), str(folder / "t.parquet"))
    return path, read_info(str(path))


def _budget(info) -> float:
    """A budget the whole block does not fit, with room for a few tiles of 15 m or so:
    the header-only rule refuses it (its smallest tile at twice the mean density needs
    more), the densest tile the block really has does not."""
    return FIXED_BYTES + 0.575 * info.n_points * BYTES_PER_POINT


def _densest_tile(path, info, size: float, buffer: float) -> int:
    from pipeline.reading import read_points
    from pipeline.tiling import buffered_tiles, plan_grid

    xyz, _ = read_points(path, origin=(0.0, 0.0, 0.0))
    grid = plan_grid(info.mins, info.maxs, tile_size=size, buffer=buffer, grid_origin=info.origin[:2])
    _, tile = buffered_tiles(xyz, grid)
    return int(np.bincount(tile).max())


def test_a_block_within_the_budget_is_left_whole_and_one_above_it_is_tiled(block, tmp_path):
    path, info = block
    params = PipelineParams.model_validate(PARAMS)
    whole = JobSpec(str(path), str(tmp_path / "o"), params=params, tiling=TilingParams(worker_memory=_need(info.n_points) / 1e9))
    assert auto_tiled(whole, info) is whole
    assert auto_tiled(JobSpec(str(path), str(tmp_path / "o"), params=params), info).tiling.tile_size is None  # no budget
    assert auto_tiled(JobSpec(str(path), str(tmp_path / "o"), params=params, tiling=TilingParams(tile_size=7.0, worker_memory=1.0 / 1e9)), info).tiling.tile_size == 7.0
    spec = auto_tiled(JobSpec(str(path), str(tmp_path / "o"), params=params, tiling=TilingParams(worker_memory=_budget(info) / 1e9)), info)
    size = spec.tiling.tile_size
    assert size is not None and size >= MIN_CORE_PER_BUFFER * params.reach()
    # every buffered tile of the job's grid holds no more points than the budget allows
    assert _need(_densest_tile(str(path), info, size, params.reach())) <= _budget(info)
    # the header alone (a file that cannot be sampled) refuses this budget for this block
    with pytest.raises(BudgetError):
        tile_size_for_budget(info.n_points, info.mins, info.maxs, budget=_budget(info), buffer=params.reach())


def test_a_block_that_cannot_be_sampled_is_tiled_from_its_header(block, tmp_path):
    import dataclasses

    path, info = block
    params = PipelineParams.model_validate(PARAMS)
    budget = FIXED_BYTES + 0.7 * info.n_points * BYTES_PER_POINT
    spec = JobSpec(str(path), str(tmp_path / "o"), params=params, tiling=TilingParams(worker_memory=budget / 1e9))
    unsampled = dataclasses.replace(info, seekable=False)  # as a LAZ file of variable-size chunks
    expected = tile_size_for_budget(info.n_points, info.mins, info.maxs, budget=budget, buffer=params.reach())
    assert auto_tiled(spec, unsampled).tiling.tile_size == expected
    assert auto_tiled(spec, info).tiling.tile_size > expected  # sampled: the block's real tiles are less dense


@pytest.mark.slow
def test_the_tiles_chosen_for_a_budget_give_the_untiled_result(block, tmp_path):
    path, info = block
    params = PipelineParams.model_validate(PARAMS)
    single = run_job(JobSpec(str(path), str(tmp_path / "single"), params=params))
    tiled = run_job(JobSpec(str(path), str(tmp_path / "tiled"), params=params, tiling=TilingParams(worker_memory=_budget(info) / 1e9)))
    assert single.n_tiles == 1 and tiled.n_tiles >= 6
    assert tiled.n_trees == single.n_trees >= 15
    for col in ("tree_id", "trunk_x", "trunk_y", "height_m", "n_points"):
        assert np.array_equal(single.trees[col], tiled.trees[col]), col
    pa = pq.read_table(tmp_path / "single" / "points.parquet", columns=["point_index", "tree_id", "is_ground"]).to_pydict()
    pb = pq.read_table(tmp_path / "tiled" / "points.parquet", columns=["point_index", "tree_id", "is_ground"]).to_pydict()
    assert pa["point_index"] == pb["point_index"] and pa["tree_id"] == pb["tree_id"]
    # one point of 159 k lies on the ground model's edge differently in its tile
    assert np.mean(np.asarray(pa["is_ground"]) == np.asarray(pb["is_ground"])) >= 0.9999


# VmHWM, not getrusage: ru_maxrss survives exec, and would count the forking pytest's memory
_RUN = """
import json, re, sys
from pipeline.jobparams import TilingParams
from pipeline.params import PipelineParams
from workers.job import run_job
from workers.jobspec import JobSpec
spec = JobSpec(sys.argv[1], sys.argv[2], params=PipelineParams.model_validate_json(sys.argv[3]),
               tiling=TilingParams(worker_memory=float(sys.argv[4]) / 1e9))
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


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--worker-memory", "0.21"], "too small for this block"),
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
        assert "(--worker-memory 0.3 or more)" in err  # the smallest tile's need, rounded up


@pytest.mark.slow
def test_orchard_process_tiles_a_block_above_its_budget(block, tmp_path, capsys):
    path, info = block
    gb = _budget(info) / 1e9
    code, err = _process(capsys, path, "--out", tmp_path / "o", "--segment-max-crown-radius", 3, "--worker-memory", gb)
    assert code == 0, err
    assert "tiles of 15 m" in err and "1 tile(s)" not in err
