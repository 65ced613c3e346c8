"""Rows end to end on a generated hedgerow: trunks, addresses, empty slots and replants,
the same tiled and untiled."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from simulator.scoring.result import evaluate_result
from pipeline.jobparams import JobParams, TilingParams
from simulator.simparams import SimulationParams
from simulator.truth import write_simulation
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

    untiled = pq.read_table(out / "trees.parquet").to_pydict()
    # ids in address order: row by row, position by position
    addr = list(zip(untiled["row"], untiled["position"]))
    assert untiled["tree_id"] == list(range(1, len(addr) + 1)) and addr == sorted(addr)
    # and the points follow the renumbering: each tree's points lie around its own trunk
    labels = pq.read_table(out / "points.parquet", columns=["tree_id"]).column(0).to_numpy()
    import laspy
    pts = laspy.read(str(las))
    xy = np.c_[np.asarray(pts.x), np.asarray(pts.y)]
    for k in (1, len(addr) // 2, len(addr)):
        centre = np.median(xy[labels == k], axis=0)
        trunk = np.array([untiled["trunk_x"][k - 1], untiled["trunk_y"][k - 1]])
        assert np.hypot(*(centre - trunk)) < 0.5, k

    tiled = run_job(JobSpec(str(las), str(tmp_path / "tiled"), job=JobParams(tiling=TilingParams(tile_size=8.0))))
    assert tiled.trees["tree_id"].tolist() == untiled["tree_id"]
    assert tiled.trees["row"].tolist() == untiled["row"] and tiled.trees["position"].tolist() == untiled["position"]
    assert tiled.trees["young"].tolist() == untiled["young"]


@pytest.mark.slow
def test_a_row_whose_trunks_are_all_hidden_is_found_from_its_canopy(tmp_path):
    """The lowest 1.2 m of every tree of row 2 cut out of a generated hedge: no trunk
    there, but the canopy shows the row, and row 3 keeps its number."""
    import laspy

    from simulator.truth import read_truth, read_truth_layout

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


@pytest.mark.slow
def test_trees_on_open_slots_are_decided_on_the_block_and_tiled_equals_untiled(tmp_path, monkeypatch):
    """High density with foliage to the ground: some trees are turned down as a
    neighbour's satellite and let in on their empty slot, a replant on the slot before
    a row's first tree. A tile's own rows decided these otherwise near its edges (tiled
    21 trees, untiled 22, on this block); the block's decision runs those tiles again."""
    import workers.dispatch

    las, truth = tmp_path / "hd.laz", tmp_path / "hd.truth.parquet"
    sim = SimulationParams(spacing=2.5, row_spacing=4.5, low_foliage=True, rows=3, trees_per_row=8, missing=0.1,
                           replants=0.05, density=0.5, seed=100)
    write_simulation(sim, str(las), str(truth))
    single = run_job(JobSpec(str(las), str(tmp_path / "single")))
    again = []
    first = workers.dispatch.process_tiles

    def counting(store, tiles, *args, **kwargs):
        again.append([t["id"] for t in tiles])
        return first(store, tiles, *args, **kwargs)

    monkeypatch.setattr(workers.dispatch, "process_tiles", counting)  # the block's second round only
    tiled = run_job(JobSpec(str(las), str(tmp_path / "tiled"), job=JobParams(tiling=TilingParams(tile_size=14.0))))
    assert tiled.n_tiles == 6 and again and 0 < len(again[0]) < 6
    assert tiled.n_trees == single.n_trees
    for col in ("trunk_x", "trunk_y", "row", "position", "young"):
        np.testing.assert_allclose(np.asarray(tiled.trees[col], float), np.asarray(single.trees[col], float), err_msg=col)
    a = pq.read_table(tmp_path / "single" / "points.parquet", columns=["tree_id"]).column(0).to_numpy()
    b = pq.read_table(tmp_path / "tiled" / "points.parquet", columns=["tree_id"]).column(0).to_numpy()
    assert np.array_equal(a, b)
    s = evaluate_result(str(truth), str(tmp_path / "single"), match_distance=1.0)
    assert s["trunk_recall"] >= 21 / 22
