"""A generated block's files: LAS/LAZ and truth Parquet written and read back, nothing partial left."""

from __future__ import annotations

import numpy as np
import pytest

from simulator.simparams import SimulationParams
from simulator.truth import read_truth, write_simulation
from synthetic_blocks import SMALL


def test_las_and_truth_round_trip(tmp_path, small):
    from pipeline.blockinfo import read_info
    from pipeline.reading import read_points

    las, truth = tmp_path / "block.laz", tmp_path / "truth.parquet"
    summary = write_simulation(small, str(las), str(truth))
    assert summary == {"n_points": small.n_points, "n_trees": SMALL.n_trees, "crs_epsg": 28356}
    xyz, info = read_points(str(las))
    assert info.n_points == small.n_points
    assert info.crs_wkt and "28356" in info.crs_wkt
    assert np.abs(xyz + np.asarray(info.origin) - small.xyz).max() <= 0.0006  # 1 mm scale
    cols, trunks = read_truth(str(truth))
    assert np.array_equal(cols["point_index"], np.arange(small.n_points, dtype=np.uint64))
    assert np.array_equal(cols["tree_id"], small.tree_id)
    assert np.array_equal(cols["is_wood"], small.is_wood)
    assert np.array_equal(cols["kind"], small.kind)
    assert np.allclose(trunks, small.trunks, atol=1e-6)
    assert np.allclose(cols["trunk_radius"], small.trunk_radius, atol=1e-6)
    assert read_info(str(las)).n_points == small.n_points
    assert sorted(p.name for p in tmp_path.iterdir()) == ["block.laz", "truth.parquet"]


def test_streamed_write_equals_in_memory_write(tmp_path, small):
    from pipeline.reading import read_points

    write_simulation(SMALL, str(tmp_path / "s.laz"), str(tmp_path / "s.parquet"))
    write_simulation(small, str(tmp_path / "m.laz"), str(tmp_path / "m.parquet"))
    a, _ = read_points(str(tmp_path / "s.laz"))
    b, _ = read_points(str(tmp_path / "m.laz"))
    assert np.array_equal(a, b)
    ta, _ = read_truth(str(tmp_path / "s.parquet"))
    assert np.array_equal(ta["tree_id"], small.tree_id)


def test_failed_write_leaves_nothing(tmp_path, small):
    def chunks():
        yield small
        raise RuntimeError("generator broke")

    with pytest.raises(RuntimeError):
        write_simulation(chunks(), str(tmp_path / "x.laz"), str(tmp_path / "x.parquet"))
    assert list(tmp_path.iterdir()) == []


def test_a_simulation_without_points_writes_nothing(tmp_path):
    # --density 1e-300 used to write a 0-point block ("wrote 0 points", exit 0)
    from pipeline.errors import ParameterError

    with pytest.raises(ParameterError, match="made no points"):
        write_simulation(SimulationParams(rows=1, trees_per_row=2, density=1e-300), str(tmp_path / "x.laz"),
                         str(tmp_path / "x.parquet"))
    assert list(tmp_path.iterdir()) == []


def test_read_truth_rejects_other_files(tmp_path):
    from pipeline.errors import InputError

    bad = tmp_path / "bad.parquet"
    bad.write_bytes(b"not parquet")
    with pytest.raises(InputError):
        read_truth(str(bad))
    with pytest.raises(InputError):
        read_truth(str(tmp_path / "missing.parquet"))
    from simulator.truth import read_truth_layout

    for path in (bad, tmp_path / "missing.parquet"):
        with pytest.raises(InputError):
            read_truth_layout(str(path))
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(pa.table({"x": [1.0]}), tmp_path / "other.parquet")
    with pytest.raises(InputError, match="not an orchard truth file"):
        read_truth_layout(str(tmp_path / "other.parquet"))


def test_truth_layout_round_trip(tmp_path, gappy):
    from simulator.orchard import Orchard
    from simulator.truth import read_truth_layout

    las, truth = str(tmp_path / "b.las"), str(tmp_path / "t.parquet")
    write_simulation(gappy, las, truth)
    lay = read_truth_layout(truth)
    assert np.array_equal(lay["tree_row"], gappy.tree_row) and lay["tree_row"].dtype == np.int64
    assert np.array_equal(lay["tree_slot"], gappy.tree_slot)
    assert np.array_equal(lay["tree_young"], gappy.tree_young) and lay["tree_young"].dtype == bool
    assert np.allclose(lay["empty_slots"], gappy.empty_slots, atol=1e-6) and lay["empty_slots"].shape == (3, 4)
    assert lay["spacing"] == 1.0 and lay["row_spacing"] == 3.5
    cols, trunks = read_truth(truth)  # the point truth reads as before
    assert len(trunks) == len(gappy.trunks)
    # a truth file without a layout (an Orchard made by hand) answers None and no empty slots
    bare = Orchard(gappy.xyz[:100], gappy.tree_id[:100], gappy.is_wood[:100], gappy.kind[:100], gappy.trunks,
                   gappy.trunk_radius)
    write_simulation(bare, str(tmp_path / "c.las"), str(tmp_path / "u.parquet"))
    old = read_truth_layout(str(tmp_path / "u.parquet"))
    assert old["tree_row"] is None and old["tree_slot"] is None and old["tree_young"] is None
    assert old["spacing"] is None and old["empty_slots"].shape == (0, 4)
