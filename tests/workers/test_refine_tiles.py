"""The refined segmentation gives the same labels tiled and untiled."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.jobparams import JobParams, TilingParams
from pipeline.params import PipelineParams
from workers.job import run_job
from workers.jobspec import JobSpec


@pytest.mark.slow
@pytest.mark.parametrize("sim", [
    dict(rows=2, trees_per_row=3, density=0.2, seed=3),
    dict(form="hedge", rows=1, trees_per_row=8, spacing=1.2, row_spacing=4.0, density=0.3, seed=4),
], ids=["vase", "hedge"])
def test_refined_labels_do_not_depend_on_tiling(tmp_path, sim):
    """The random walk of the contested nodes reads only the tile's graph; the buffer
    holds every node a tree in the core can reach, so the walk sees the same graph."""
    from simulator.simparams import SimulationParams
    from simulator.truth import write_simulation

    block = tmp_path / "b.laz"
    write_simulation(SimulationParams(**sim), str(block), str(tmp_path / "t.parquet"))
    params = PipelineParams.model_validate({"segment": {"method": "refined"}})
    single = run_job(JobSpec(str(block), str(tmp_path / "single"), job=JobParams(pipeline=params)))
    tiled = run_job(JobSpec(str(block), str(tmp_path / "tiled"), job=JobParams(pipeline=params, tiling=TilingParams(tile_size=6.0))))
    assert tiled.n_tiles > 2 and tiled.n_trees == single.n_trees > 0
    pa = pq.read_table(tmp_path / "single" / "points.parquet").to_pydict()
    pb = pq.read_table(tmp_path / "tiled" / "points.parquet").to_pydict()
    for col in ("point_index", "tree_id", "is_ground"):
        assert pa[col] == pb[col], col
    assert np.mean(np.asarray(pa["is_wood"]) == np.asarray(pb["is_wood"])) >= 0.999


@pytest.mark.slow
def test_a_reach_from_each_trees_height_does_not_depend_on_tiling(tmp_path):
    """Each tree's reach comes from the nodes within a metre of its trunk, which a tile
    holds for every trunk whose material can reach its core: here crown_radius is small,
    so every tree's reach follows its height, tree by tree (all under max_crown_radius)."""
    from simulator.simparams import SimulationParams
    from simulator.truth import write_simulation

    block = tmp_path / "b.laz"
    write_simulation(SimulationParams(rows=2, trees_per_row=3, density=0.2, seed=5), str(block), str(tmp_path / "t.parquet"))
    params = PipelineParams.model_validate({"segment": {"crown_radius": 0.5, "crown_per_height": 0.45}})
    single = run_job(JobSpec(str(block), str(tmp_path / "single"), job=JobParams(pipeline=params)))
    tiled = run_job(JobSpec(str(block), str(tmp_path / "tiled"), job=JobParams(pipeline=params, tiling=TilingParams(tile_size=6.0))))
    assert tiled.n_tiles > 2 and tiled.n_trees == single.n_trees > 0
    pa = pq.read_table(tmp_path / "single" / "points.parquet").to_pydict()
    pb = pq.read_table(tmp_path / "tiled" / "points.parquet").to_pydict()
    run_job(JobSpec(str(block), str(tmp_path / "default"), job=JobParams()))
    pd_ = pq.read_table(tmp_path / "default" / "points.parquet").to_pydict()
    assert np.count_nonzero(pa["tree_id"]) < np.count_nonzero(pd_["tree_id"])  # the height's reach did cut material
    for col in ("point_index", "tree_id", "is_ground"):
        assert pa[col] == pb[col], col
