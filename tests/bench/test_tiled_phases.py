"""bench.tiled_phases reports the phases, the tiles and the tiles run again of a tiled run."""

from __future__ import annotations

import json

from bench import tiled_phases
from simulator.simparams import SimulationParams
from simulator.truth import write_simulation


def test_a_tiled_run_reports_its_phases_and_tiles(tmp_path, capsys, dask_cluster):
    block = tmp_path / "small.laz"
    write_simulation(SimulationParams(rows=2, trees_per_row=4, density=0.2, seed=1), str(block),
                     str(tmp_path / "small.truth.parquet"))
    assert tiled_phases.main([str(block), "--out", str(tmp_path / "out"), "--tile-size", "10",
                                "--scheduler", dask_cluster.scheduler_address]) == 0
    stats = json.loads(capsys.readouterr().err.strip().splitlines()[-1])
    assert set(stats["timings"]) >= {"tile", "ground", "process", "merge_write", "total"}
    assert stats["tiles"] > 1 and stats["n_buffered"] > 0 and isinstance(stats["run_again"], list)
    assert stats["views"] > 0
