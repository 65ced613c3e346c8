"""Rows end to end on a generated hedgerow: trunks, addresses, empty slots and replants,
the same tiled and untiled."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.evaluation.result import evaluate_result
from pipeline.jobparams import TilingParams
from pipeline.synthetic.simparams import SimulationParams
from pipeline.synthetic.truth import write_simulation
from workers.job import run_job
from workers.jobspec import JobSpec


@pytest.fixture(scope="module")
def hedgerow(tmp_path_factory):
    """Tall spindle at 1.0 m x 3.5 m, 3 rows of 14 slots, two empty and two replanted."""
    d = tmp_path_factory.mktemp("hedgerow")
    las, truth = d / "spindle.laz", d / "spindle.truth.parquet"
    sim = SimulationParams(form="spindle", rows=3, trees_per_row=14, spacing=1.0, row_spacing=3.5, missing=0.05,
                           replants=0.05, density=0.4, seed=4, rotation=25.0)
    write_simulation(sim, str(las), str(truth))
    return las, truth


@pytest.mark.slow
def test_a_hedgerow_gets_its_trunks_and_addresses(hedgerow, tmp_path):
    las, truth = hedgerow
    out = tmp_path / "out"
    run_job(JobSpec(str(las), str(out)))
    s = evaluate_result(str(truth), str(out), match_distance=0.4)
    assert s["trunk_f1"] >= 0.95
    assert s["address_accuracy"] >= 0.97
    assert s["gap_recall"] >= 0.9 and s["gap_precision"] >= 0.9
    assert s["young_correct"] >= s["young_true"] - 1
    rows = pq.read_table(out / "rows.parquet").to_pydict()
    assert len(rows["row"]) == 3
    az = np.asarray(rows["azimuth_deg"])
    np.testing.assert_allclose(az, 90.0 - 25.0, atol=3.0)  # rotated 25° from east: positions run east-north-east

    tiled = run_job(JobSpec(str(las), str(tmp_path / "tiled"), tiling=TilingParams(tile_size=8.0)))
    untiled = pq.read_table(out / "trees.parquet").to_pydict()
    assert tiled.trees["row"].tolist() == untiled["row"] and tiled.trees["position"].tolist() == untiled["position"]
    assert tiled.trees["young"].tolist() == untiled["young"]


@pytest.mark.slow
def test_a_row_whose_trunks_are_all_hidden_is_found_from_its_canopy(tmp_path):
    """The lowest 1.2 m of every tree of row 2 cut out of a generated hedge: no trunk
    there, but the canopy shows the row, and row 3 keeps its number."""
    import laspy

    from pipeline.synthetic.truth import read_truth, read_truth_layout

    las, truth = tmp_path / "hedge.laz", tmp_path / "hedge.truth.parquet"
    sim = SimulationParams(form="hedge", rows=3, trees_per_row=10, spacing=1.35, row_spacing=4.0, density=0.4, seed=12,
                           vehicle=False, bin=False)
    write_simulation(sim, str(las), str(truth))
    cols, trunks = read_truth(str(truth))
    row_of_tree = np.r_[0, read_truth_layout(str(truth))["tree_row"]]
    data = laspy.read(str(las))
    in_row2 = row_of_tree[cols["tree_id"]] == 2
    low = np.asarray(data.z) < trunks[:, 2].max() + 1.2
    cut = tmp_path / "hidden.laz"
    data.points = data.points[~(in_row2 & low)]
    data.write(str(cut))
    out = tmp_path / "out"
    run_job(JobSpec(str(cut), str(out)))
    rows = pq.read_table(out / "rows.parquet").to_pydict()
    trees = pq.read_table(out / "trees.parquet").to_pydict()
    assert rows["row"] == [1, 2, 3] and rows["n_trees"][1] == 0
    assert rows["n_trees"][0] >= 9 and rows["n_trees"][2] >= 9
    ys = np.asarray(trees["trunk_y"])
    assert set(np.asarray(trees["row"])[ys > np.median(trunks[:, 1]) + 1.0].tolist()) == {3}
