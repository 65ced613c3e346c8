"""bench.rayextract's file exchange with raycloudtools: the ray cloud and ground mesh it
writes, and how it reads the tool's outputs back. The real binary is not installable here,
so the run is checked against a stand-in that keeps the same command-line contract."""

import stat
import sys
import textwrap

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from bench.rayextract import (
    MESH_CELL,
    RAY_LENGTH,
    SCENES,
    compare_adtree,
    main,
    read_segmented,
    read_tree_bases,
    run_rayextract,
    table,
    write_ground_mesh,
    write_ray_cloud,
)
from bench.real_data import REAL
from pipeline.blockinfo import read_info
from simulator.simparams import SimulationParams
from simulator.terrain import ground_height

XYZ = np.array([[0.0, 0.0, 0.1], [1.0, 2.0, 3.0], [-4.5, 2.25, 1.5], [7.0, -1.0, 0.0]])


def test_ray_cloud_has_the_fields_raycloudtools_reads(tmp_path):
    write_ray_cloud(tmp_path / "c.ply", XYZ)
    ply = PlyData.read(str(tmp_path / "c.ply"))
    assert ply.text is False and ply.byte_order == "<"  # raycloudtools reads binary little-endian only
    v = ply["vertex"].data
    assert v.dtype.names == ("x", "y", "z", "time", "nx", "ny", "nz", "red", "green", "blue", "alpha")
    assert [v.dtype[k].str for k in ("x", "time", "nx", "red")] == ["<f4", "<f8", "<f4", "|u1"]
    np.testing.assert_allclose(np.c_[v["x"], v["y"], v["z"]], XYZ, atol=1e-6)
    # the ray start, end + normal, lies RAY_LENGTH straight above each point
    np.testing.assert_array_equal(np.c_[v["nx"], v["ny"], v["nz"]], np.tile([0.0, 0.0, RAY_LENGTH], (4, 1)))
    assert np.all(np.diff(v["time"]) > 0)
    assert np.all(v["alpha"] == 255)  # bounded rays: real returns


def test_ground_mesh_is_the_true_ground_over_the_box(tmp_path):
    params = SimulationParams(seed=3, slope=0.2)
    origin = np.array([params.easting, params.northing, params.elevation]) + np.array([1.0, -2.0, 0.5])
    lo, hi = np.array([-1.0, -1.0]), np.array([3.0, 2.0])
    local_ground = lambda x, y: ground_height(params, x + origin[0], y + origin[1]) - origin[2]  # noqa: E731
    n_tri = write_ground_mesh(tmp_path / "m.ply", local_ground, lo, hi)
    ply = PlyData.read(str(tmp_path / "m.ply"))
    v, f = ply["vertex"].data, np.stack(ply["face"].data["vertex_indices"])
    assert f.shape == (n_tri, 3) and f.min() == 0 and f.max() == len(v) - 1
    x, y, z = (v[k].astype(np.float64) for k in ("x", "y", "z"))
    np.testing.assert_allclose(z, ground_height(params, x + origin[0], y + origin[1]) - origin[2], atol=1e-4)
    assert x.min() <= lo[0] and x.max() >= hi[0] and y.min() <= lo[1] and y.max() >= hi[1]
    nx, ny = len(np.unique(x.round(4))), len(np.unique(y.round(4)))
    assert n_tri == 2 * (nx - 1) * (ny - 1)
    np.testing.assert_allclose(np.diff(np.unique(x.round(4))), MESH_CELL, atol=1e-4)


def _segmented(path, xyz, rgb):
    v = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = xyz.T
    v["red"], v["green"], v["blue"] = np.asarray(rgb, np.uint8).T
    PlyData([PlyElement.describe(v, "vertex")], byte_order="<").write(str(path))


def test_one_label_per_colour_and_black_is_no_tree(tmp_path):
    _segmented(tmp_path / "s.ply", XYZ, [(10, 20, 30), (0, 0, 0), (10, 20, 30), (0, 0, 1)])
    labels = read_segmented(tmp_path / "s.ply", XYZ)
    assert labels[1] == 0
    assert labels[0] == labels[2] > 0 and labels[3] > 0 and labels[3] != labels[0]


def test_segmented_cloud_must_match_the_input_point_by_point(tmp_path):
    _segmented(tmp_path / "short.ply", XYZ[:3], [(1, 1, 1)] * 3)
    with pytest.raises(ValueError, match="3 points, the input 4"):
        read_segmented(tmp_path / "short.ply", XYZ)
    _segmented(tmp_path / "shuffled.ply", XYZ[::-1], [(1, 1, 1)] * 4)
    with pytest.raises(ValueError, match="not in the input's order"):
        read_segmented(tmp_path / "shuffled.ply", XYZ)


def test_tree_bases_are_the_first_segment_of_each_tree_line(tmp_path):
    (tmp_path / "t.txt").write_text(
        "# Tree file. Optional per-tree attributes (e.g. 'height,crown_radius, ') followed by 'x,y,z,radius':\n"
        "x,y,z,radius,parent_id,section_id\n"
        "-3.0662,-5.4811,0.1500,0.1772,-1,0, -3.0677,-5.4769,0.4878,0.1772,0,13\n"
        "4.5,0.25,.5,0.1,-1,1, 4.5,0.3,0.9,0.1,0,14\n"
    )
    np.testing.assert_allclose(read_tree_bases(tmp_path / "t.txt"), [[-3.0662, -5.4811, 0.15], [4.5, 0.25, 0.5]])


STAND_IN = """\
    #!{python}
    # Stand-in with rayextract's contract: "rayextract trees cloud.ply mesh.ply" writes
    # cloud_segmented.ply (input points, one colour per tree, black = none) and
    # cloud_trees.txt. Trees: x < 0 and x >= 0; points below z = 0.5 are no tree.
    import sys
    import numpy as np
    from plyfile import PlyData, PlyElement
    assert sys.argv[1] == "trees", sys.argv
    v = PlyData.read(sys.argv[2])["vertex"].data
    PlyData.read(sys.argv[3])  # the mesh must be readable
    out = np.zeros(len(v), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k in ("x", "y", "z"):
        out[k] = v[k]
    left = v["x"] < 0
    out["red"] = np.where(left, 200, 0)
    out["blue"] = np.where(left, 0, 90)
    low = v["z"] < 0.5
    out["red"][low] = out["blue"][low] = 0
    PlyData([PlyElement.describe(out, "vertex")], byte_order="<").write("cloud_segmented.ply")
    with open("cloud_trees.txt", "w") as f:
        f.write("# Tree file\\nx,y,z,radius,parent_id,section_id\\n")
        f.write("-4.5,2.25,0,0.1,-1,0, -4.5,2.25,1,0.1,0,1\\n1,2,0,0.1,-1,1\\n")
"""


def test_run_feeds_the_tool_and_reads_back_its_answer(tmp_path):
    tool = tmp_path / "rayextract"
    tool.write_text(textwrap.dedent(STAND_IN).format(python=sys.executable))
    tool.chmod(tool.stat().st_mode | stat.S_IXUSR)
    labels, bases, seconds, peak = run_rayextract(str(tool), tmp_path / "run", XYZ, lambda x, y: np.zeros(len(x)))
    assert labels[0] == 0 and labels[3] == 0  # below 0.5 m
    assert labels[1] > 0 and labels[2] > 0 and labels[1] != labels[2]
    np.testing.assert_allclose(bases, [[-4.5, 2.25, 0.0], [1.0, 2.0, 0.0]])
    assert seconds > 0
    # the stand-in's own peak, a Python process with numpy and plyfile loaded: well above
    # 10 MB, well below this test process's
    assert 10 * 2**20 < peak < 2**30
    assert (tmp_path / "run" / "mesh.ply").exists()


def test_a_failing_tool_is_reported_with_its_output(tmp_path):
    tool = tmp_path / "rayextract"
    tool.write_text(f"#!{sys.executable}\nimport sys\nprint('cannot read mesh', file=sys.stderr)\nsys.exit(3)\n")
    tool.chmod(tool.stat().st_mode | stat.S_IXUSR)
    with pytest.raises(RuntimeError, match="exited 3: cannot read mesh"):
        run_rayextract(str(tool), tmp_path / "run", XYZ, lambda x, y: np.zeros(len(x)))


def test_main_refuses_a_missing_binary(tmp_path, capsys):
    assert main(["--rayextract", str(tmp_path / "nope")]) == 2
    assert "is not an executable file" in capsys.readouterr().err


def test_main_refuses_an_unknown_scene_group(tmp_path, capsys):
    tool = tmp_path / "rayextract"
    tool.write_text("#!/bin/sh\n")
    tool.chmod(tool.stat().st_mode | stat.S_IXUSR)
    assert main(["--rayextract", str(tool), "--scenes", "default,orchard"]) == 2
    assert "unknown scene group orchard" in capsys.readouterr().err


def test_hedgerow_scenes_are_the_issue_layouts():
    hedge = SCENES["hedgerows"]
    assert {(s["form"], s["spacing"], s["row_spacing"]) for s in hedge.values()} == {
        ("spindle", 1.0, 3.5), ("spindle", 1.5, 3.5), ("hedge", 1.35, 4.0)}
    for sim in hedge.values():
        SimulationParams(seed=0, **sim)  # valid simulator fields


def test_mobile_scenes_are_the_density_benchmark_blocks():
    from bench.density import FORMS

    for sim in SCENES["mobile"].values():
        assert {k: v for k, v in sim.items() if k != "density"} in FORMS.values()
        assert sim["density"] > 1  # denser than the simulator's default


def test_table_gives_memory_per_point_and_the_ratios():
    m = dict(found=3, trunk_f1=1.0, v_measure=0.9)
    rows = [{"setting": "s", "seed": 0, "n_points": 2**20, "n_trees": 3,
             "methods": {"ours": dict(m, seconds=2.0, peak_rss=200 * 2**20),
                         "rayextract trees": dict(m, seconds=5.0, peak_rss=100 * 2**20)}}]
    text = table(rows)
    assert "| s | 0 | 1,048,576 | ours | 3 (3) | 1.00 | 0.900 | 2.0 | 200 | 200 |" in text
    assert "| s | 0 | 2.50 | 0.50 |" in text


@pytest.mark.slow  # our pipeline twice on 200 k points in a fresh process
@pytest.mark.skipif(not (REAL / "AdTree").is_dir(), reason="../shared/data/real/AdTree not present")
def test_real_tree_row_scores_both_tools_on_the_exact_tree_ids(tmp_path):
    tool = tmp_path / "rayextract"
    tool.write_text(textwrap.dedent(STAND_IN).format(python=sys.executable))
    tool.chmod(tool.stat().st_mode | stat.S_IXUSR)
    row = compare_adtree(str(tool), tmp_path, 0.8)
    assert row["n_trees"] == 4 and row["n_points"] > 100_000
    ours, other = row["methods"]["ours"], row["methods"]["rayextract trees"]
    assert ours["found"] == 4 and ours["trunk_f1"] == 1.0 and ours["v_measure"] > 0.8
    # the stand-in puts every point above 0.5 m (local) into one tree, with the two bases it
    # always reports: a single cluster has no homogeneity, so its v-measure is 0
    assert other["found"] == 2 and other["v_measure"] == pytest.approx(0.0, abs=1e-9)
    # the row's flat ground plane, z = 0, in the block's local frame
    origin = read_info(str(tmp_path / "blocks" / "adtree-row-0.8.laz")).origin
    mesh = PlyData.read(str(tmp_path / "rayextract-runs" / "adtree-row-0.8" / "mesh.ply"))
    np.testing.assert_allclose(mesh["vertex"].data["z"], -origin[2], atol=1e-6)
