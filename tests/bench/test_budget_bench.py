"""bench.budget: each tile's points, voxels and worker peak; a run at a budget against its estimate."""

from __future__ import annotations

import json

import pytest

from bench import budget
from pipeline.budget import FIXED_BYTES, block_bytes
from pipeline.reading import sample_density
from simulator.simparams import SimulationParams
from simulator.truth import write_simulation


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bench-budget")
    path = folder / "sparse.laz"
    # the rows are counts and peaks of whatever tiles there are: half the points of
    # the workers' small block (same extent, so the same 10 m tiles) do
    write_simulation(SimulationParams(rows=2, trees_per_row=4, density=0.1, seed=1), str(path), str(folder / "t.parquet"))
    return str(path)


@pytest.mark.slow
def test_per_tile_rows_count_points_voxels_and_the_workers_peak(block, capsys):
    assert budget.main([block, "--tile-size", "10", "--per-tile"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    tiles, kinds = lines[:-1], lines[-1]["task_peaks"]
    assert len(tiles) > 1
    for t in tiles:
        assert 0 < t["voxels"] <= t["points"] and 0 < t["rss_before"] <= t["peak"]
    assert {"orchard-tile", "orchard-ground"} <= set(kinds)
    assert max(t["peak"] for t in tiles) == kinds["orchard-tile"]


@pytest.mark.slow
def test_a_budget_run_reports_its_tiles_and_every_workers_peak(block, capsys, tmp_path):
    from pipeline.blockinfo import read_info

    info = read_info(block)
    gb = (FIXED_BYTES + 0.85 * (block_bytes(sample_density(block, info=info, voxel_size=0.1)) - FIXED_BYTES)) / 1e9
    assert budget.main([block, "--worker-memory", str(gb)]) == 0
    (got,) = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert got["tile_size"] is not None and got["n_tiles"] > 1 and got["n_points"] == info.n_points
    assert FIXED_BYTES < got["estimate_largest_tile"] <= gb * 1e9
    assert len(got["worker_peaks"]) == 2 and got["main_peak"] > 0


def test_per_tile_needs_a_tile_size(capsys):
    with pytest.raises(SystemExit) as exit_:
        budget.main(["x.laz", "--per-tile"])
    assert exit_.value.code == 2 and "--per-tile needs --tile-size" in capsys.readouterr().err
