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


def test_the_fit_recovers_known_constants_from_the_tiles_that_raised_the_peak(tmp_path, capsys):
    from bench import budget_fit

    # peaks of exactly 200 MB + 80 B a point + 700 B a voxel, but the third tile starts on
    # the heap the first left: its peak is that heap's, above the line, and not fitted
    line = lambda p, v: 200e6 + 80 * p + 700 * v  # noqa: E731
    rows = [(0, 4_000_000, 400_000), (1, 2_000_000, 900_000), (2, 100_000, 10_000), (3, 8_000_000, 500_000)]
    peaks = [line(p, v) for _, p, v in rows]
    peaks[2] = peaks[0] - 1
    path = tmp_path / "block.jsonl"
    path.write_text("\n".join(json.dumps({"tile": t, "points": p, "voxels": v, "rss_before": 1, "peak": y})
                              for (t, p, v), y in zip(rows, peaks)) + '\n{"task_peaks": {}}\n')
    tiles = budget_fit.read_tiles([str(path)])
    assert [t["raised"] for t in tiles] == [True, True, False, True]
    coef, res = budget_fit.fit([t for t in tiles if t["raised"]])
    assert coef == pytest.approx([200e6, 80, 700], rel=1e-6) and abs(res).max() < 1.0
    assert budget_fit.main([str(path), "--constants", "200e6,80,700"]) == 0
    assert "estimate ÷ peak at least 1.00 (tiles that raised the peak)" in capsys.readouterr().out
