"""The file-based evaluation of a result folder against a truth file, and ``orchard evaluate``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.errors import InputError
from simulator.scoring.result import evaluate_result
from simulator.scoring.scores import v_measure, wood_f1


def _write_result(folder, trunks_xy, point_index, tree_id, is_wood, diameters=None):
    from pipeline.parquet import PointsParquetWriter, write_trees_parquet
    from pipeline.metrics import TREE_COLUMNS

    folder.mkdir()
    k = len(trunks_xy)
    cols = {c: np.zeros(k) for c in TREE_COLUMNS}
    cols["tree_id"] = np.arange(1, k + 1, dtype=np.int64)
    cols["n_points"] = np.zeros(k, dtype=np.int64)
    cols["trunk_x"], cols["trunk_y"] = trunks_xy[:, 0].astype(float), trunks_xy[:, 1].astype(float)
    if diameters is not None:
        cols["trunk_diameter_m"] = np.asarray(diameters, dtype=float)
    write_trees_parquet(str(folder / "trees.parquet"), cols, crs_wkt=None)
    with PointsParquetWriter(str(folder / "points.parquet")) as w:
        w.write(point_index, tree_id, np.zeros(len(point_index), bool), is_wood, np.zeros(len(point_index), np.float32))


@pytest.fixture(scope="module")
def truth_file(tmp_path_factory):
    """A hand-made 'block' of 8 points, 2 trees, written with the simulator's writer."""
    from simulator.orchard import Orchard
    from simulator.truth import write_simulation

    folder = tmp_path_factory.mktemp("truth")
    xyz = np.array([[500000.0 + i, 6950000.0, 100.0] for i in range(8)])
    orchard = Orchard(
        xyz=xyz,
        tree_id=np.array([0, 1, 1, 1, 2, 2, 2, 0], dtype=np.int64),
        is_wood=np.array([0, 1, 0, 0, 1, 1, 0, 0], dtype=bool),
        kind=np.array([0, 2, 3, 3, 2, 2, 3, 6], dtype=np.uint8),
        trunks=np.array([[500001.0, 6950000.0, 100.0], [500005.0, 6950000.0, 100.0]]),
        trunk_radius=np.array([0.1, 0.1]),
    )
    write_simulation(orchard, str(folder / "block.las"), str(folder / "truth.parquet"))
    return folder / "truth.parquet"


def test_evaluate_result_reads_a_result_folder(tmp_path, truth_file):
    # trees found at both trunks plus a false one; point 6 mislabelled as tree 1; point 7 missing;
    # rows in shuffled order (alignment is by point_index)
    idx = np.array([6, 0, 1, 2, 3, 4, 5], dtype=np.uint64)
    tree = np.array([1, 0, 1, 1, 1, 2, 2])
    wood = np.array([0, 0, 1, 0, 1, 1, 1], bool)
    _write_result(tmp_path / "res", np.array([[500001.2, 6950000.0], [500004.9, 6950000.1], [500020.0, 6950000.0]]), idx, tree, wood,
                  diameters=[0.25, np.nan, 0.5])
    m = evaluate_result(str(truth_file), str(tmp_path / "res"))
    # true trunks are 0.2 m thick: tree 1 measured 0.25, tree 2 not measurable, the false one not compared
    assert (m["trunk_diameter_n"], m["trunk_diameter_unmeasured"]) == (1, 1)
    assert (m["trunk_diameter_bias"], m["trunk_diameter_mae"]) == pytest.approx((0.05, 0.05))
    assert (m["trunk_tp"], m["trunk_fp"], m["trunk_fn"]) == (2, 1, 0)
    assert m["trunk_mean_distance"] == pytest.approx((0.2 + math.hypot(0.1, 0.1)) / 2)
    assert m["v_measure"] == pytest.approx(v_measure([1, 1, 1, 2, 2, 2], [1, 1, 1, 2, 2, 1]))
    assert m["wood_f1"] == pytest.approx(wood_f1([1, 0, 0, 1, 1, 0], [1, 0, 1, 1, 1, 0]))
    assert m["n_missing_points"] == 1
    assert m["n_tree_points"] == 6


def test_evaluate_result_rejects_foreign_results(tmp_path, truth_file):
    _write_result(tmp_path / "res", np.array([[0.0, 0.0]]), np.array([0, 99], dtype=np.uint64), np.array([1, 1]), np.array([0, 0], bool))
    with pytest.raises(InputError, match="point_index"):
        evaluate_result(str(truth_file), str(tmp_path / "res"))
    with pytest.raises(InputError, match="does not exist"):
        evaluate_result(str(truth_file), str(tmp_path / "nowhere"))
    # a device or a folder as the truth file: said so, not "does not exist"
    for odd in ("/dev/null", str(tmp_path)):
        with pytest.raises(InputError, match="is not a regular file"):
            evaluate_result(odd, str(tmp_path / "res"))


def test_cli_simulate_then_evaluate_a_perfect_result(tmp_path, capsys):
    """`orchard simulate` and `orchard evaluate` through the console script's main()."""
    from simulator.truth import read_truth
    from service.cli import main

    block, truth = tmp_path / "b.laz", tmp_path / "t.parquet"
    rc = main(["simulate", "--out", str(block), "--truth", str(truth), "--rows", "1", "--trees-per-row", "2",
               "--density", "0.05", "--seed", "3", "--no-vehicle"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "2 vase trees" in out and out.count("\n") == 1
    cols, trunks = read_truth(str(truth))
    _write_result(tmp_path / "res", trunks[:, :2], cols["point_index"], cols["tree_id"], cols["is_wood"])
    assert main(["evaluate", "--truth", str(truth), "--result", str(tmp_path / "res"), "--json"]) == 0
    import json

    m = json.loads(capsys.readouterr().out)
    assert m["trunk_f1"] == 1.0 and m["v_measure"] == pytest.approx(1.0) and m["wood_f1"] == 1.0
    # the written result measured every trunk as 0 m thick: the error is the true diameter
    assert m["trunk_diameter_n"] == 2 and m["trunk_diameter_bias"] == pytest.approx(-2 * cols["trunk_radius"].mean())
    assert main(["evaluate", "--truth", str(truth), "--result", str(tmp_path / "res")]) == 0
    out = capsys.readouterr().out
    assert "trunk F1" in out and "trunk diameter error [m]" in out


def test_cli_rejects_nonsense_with_one_line(tmp_path, capsys):
    from service.cli import main

    rc = main(["simulate", "--out", str(tmp_path / "b.laz"), "--truth", str(tmp_path / "t.parquet"), "--noise", "0.5"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "noise" in err
    rc = main(["evaluate", "--truth", str(tmp_path / "none.parquet"), "--result", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_evaluate_refuses_the_truth_of_a_larger_block(tmp_path, capsys):
    """A complete `orchard process` result with fewer points than the truth is the result
    of another block (it used to be scored: v-measure 0.6 and "78,793 points missing")."""
    from service.cli import main

    small, big = tmp_path / "small.laz", tmp_path / "big.laz"
    args = ["--rows", "1", "--trees-per-row", "2", "--density", "0.05", "--seed", "3", "--no-vehicle"]
    assert main(["simulate", "--out", str(small), "--truth", str(tmp_path / "small.parquet"), *args]) == 0
    assert main(["simulate", "--out", str(big), "--truth", str(tmp_path / "big.parquet"), *args, "--trees-per-row", "3"]) == 0
    assert main(["process", str(small), "--out", str(tmp_path / "res")]) == 0
    capsys.readouterr()
    assert main(["evaluate", "--truth", str(tmp_path / "small.parquet"), "--result", str(tmp_path / "res")]) == 0
    capsys.readouterr()
    assert main(["evaluate", "--truth", str(tmp_path / "big.parquet"), "--result", str(tmp_path / "res")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "another block" in err


@pytest.mark.parametrize(
    "extra, words",
    [(["--epsg", "999999"], "not a known EPSG code"), (["--epsg", "4326"], "projected CRS in metres")],
)
def test_cli_simulate_refuses_a_crs_that_is_not_metres(tmp_path, capsys, extra, words):
    from service.cli import main

    rc = main(["simulate", "--out", str(tmp_path / "b.laz"), "--truth", str(tmp_path / "t.parquet"), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and words in err
    assert list(tmp_path.iterdir()) == []


def test_cli_simulate_refuses_a_folder_as_output(tmp_path, capsys):
    from service.cli import main

    (tmp_path / "d.laz").mkdir()
    rc = main(["simulate", "--out", str(tmp_path / "d.laz"), "--truth", str(tmp_path / "t.parquet")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "is a folder" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.laz"]  # no truth without its block
