"""``orchard process`` and ``orchard convert`` on PLY, PCD, E57 and text inputs: the
same trees as the same points in LAZ; bad inputs and options: one line, exit 2."""

from __future__ import annotations

import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pipeline"))
from format_files import every_format  # noqa: E402

from pipeline.laswriting import LasBlockWriter  # noqa: E402
from simulator.simparams import SimulationParams  # noqa: E402
from simulator.truth import write_simulation  # noqa: E402
from service.cli import main  # noqa: E402


def _run(capsys, *argv):
    code = main([*map(str, argv)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    """6 generated trees in local metres at millimetres: as LAZ and in every other format."""
    folder = tmp_path_factory.mktemp("process-formats")
    sim = folder / "sim.laz"
    write_simulation(SimulationParams(rows=2, trees_per_row=3, density=0.12, seed=5), str(sim), str(folder / "t.parquet"))
    las = laspy.read(sim)
    xyz = np.column_stack([las.x, las.y, las.z])
    xyz = np.round((xyz - np.floor(xyz.min(axis=0))) * 1000) / 1000
    ref = folder / "ref.laz"
    with LasBlockWriter(ref, scales=(0.001, 0.001, 0.001), offsets=(0.0, 0.0, 0.0), crs_epsg=28356) as w:
        w.write(xyz)
    return ref, every_format(folder / "in", xyz)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A random cloud of 2,000 points, as LAZ and in every other format."""
    folder = tmp_path_factory.mktemp("process-formats-small")
    xyz = np.round(np.random.default_rng(2).uniform(0, 30, (2000, 3)), 3)
    ref = folder / "ref.laz"
    with LasBlockWriter(ref, scales=(0.001, 0.001, 0.001), offsets=(0.0, 0.0, 0.0)) as w:
        w.write(xyz)
    return ref, every_format(folder / "in", xyz)


@pytest.mark.slow
def test_each_format_gives_the_trees_of_the_laz(block, tmp_path, capsys):
    ref, files = block
    code, _, err = _run(capsys, "process", ref, "--out", tmp_path / "laz")
    assert code == 0, err
    expected = (tmp_path / "laz" / "trees.csv").read_bytes()
    assert expected.count(b"\n") > 4  # trees were found
    for kind in ("ply-binary", "pcd-binary_compressed", "e57", "text-header"):
        out = tmp_path / kind
        code, _, err = _run(capsys, "process", files[kind], "--out", out, "--crs", "EPSG:28356")
        assert code == 0, err
        assert f"{files[kind].name}: {kind.split('-')[0].upper()}, " in err and "converted to LAZ" in err
        assert (out / "trees.csv").read_bytes() == expected, kind
        assert f"Orchard report — {files[kind].name}" in (out / "report.html").read_text()
        assert not list(tmp_path.glob(".orchard-input-*"))  # the converted block went with the run


def test_orchard_convert(small, tmp_path, capsys):
    _, files = small
    out = tmp_path / "c.laz"
    code, _, err = _run(capsys, "convert", files["ply-ascii"], "--out", out, "--crs", "EPSG:28356")
    assert code == 0, err
    assert "points from PLY a.ply" in err
    assert laspy.read(out).header.parse_crs().to_epsg() == 28356
    code, _, err = _run(capsys, "convert", files["ply-ascii"], "--out", out)
    assert code == 2 and "exists" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("args,words", [
    (["--crs", "EPSG:28356"], "--crs is for PLY, PCD, E57 and text inputs"),
    (["--columns", "x,y,z"], "--columns names the columns of a text input"),
])
def test_input_options_on_a_las_block_are_refused(small, tmp_path, capsys, args, words):
    ref, _ = small
    code, _, err = _run(capsys, "process", ref, "--out", tmp_path / "o", *args)
    assert code == 2 and words in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name,data,args,words", [
    ("junk.ply", b"ply\nformat ascii 1.0\nelement vertex 99999999\nproperty float x\nproperty float y\n"
                 b"property float z\nend_header\n1 2 3\n", [], "junk.ply: the PLY header claims 99999999 vertex rows"),
    ("t.xyz", b"1 2 3\n4 5 6\n", ["--crs", "EPSG:4326"], "degrees"),
    ("t.xyz", b"1 2 3\n4 5 6\n", ["--columns", "a,b,c"], "t.xyz: --columns has no x, y, z"),
    ("s.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n",
     ["--columns", "x,y,z"], "this is a PCD file"),
])
def test_bad_inputs_are_one_line_and_exit_2(tmp_path, capsys, name, data, args, words):
    src = tmp_path / name
    src.write_bytes(data)
    code, _, err = _run(capsys, "process", src, "--out", tmp_path / "o", *args)
    assert code == 2 and words in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists() and not list(tmp_path.glob(".orchard-input-*"))


def test_a_converted_file_states_no_day_so_the_capture_takes_the_given_one(small, tmp_path, capsys):
    import os

    from pipeline.blockinfo import creation_date
    from workers.captures import resolve_capture

    _, files = small
    out = tmp_path / "c.laz"
    code, _, err = _run(capsys, "convert", files["ply-binary"], "--out", out)
    assert code == 0, err
    assert creation_date(out) is None  # not the conversion day: a PLY has no capture day
    assert laspy.read(out).header.point_count == 2000  # the file is whole after its header was touched
    assert resolve_capture(str(out), captured_at="2025-10-03").captured_at_source == "given"
    os.utime(files["ply-binary"], (1_700_000_000, 1_700_000_000))  # 2023-11-14
    from service.commands.process import _file_day

    assert _file_day(str(files["ply-binary"])) == "2023-11-14"


@pytest.mark.slow
def test_a_converted_capture_is_named_and_dated_after_its_original(block, tmp_path, capsys):
    import json
    import os

    import pyarrow.parquet as pq

    _, files = block
    ply = files["ply-binary"]
    os.utime(ply, (1_700_000_000, 1_700_000_000))
    code, _, err = _run(capsys, "process", ply, "--out", tmp_path / "a", "--crs", "EPSG:28356")
    assert code == 0, err
    record = json.loads(pq.read_schema(tmp_path / "a" / "trees.parquet").metadata[b"orchard:capture"])
    assert (record["capture_id"], record["captured_at"], record["captured_at_source"]) == (ply.stem, "2023-11-14", "upload")
    code, _, err = _run(capsys, "process", ply, "--out", tmp_path / "b", "--crs", "EPSG:28356", "--captured-on", "2024-02-01")
    assert code == 0, err
    record = json.loads(pq.read_schema(tmp_path / "b" / "trees.parquet").metadata[b"orchard:capture"])
    assert (record["captured_at"], record["captured_at_source"]) == ("2024-02-01", "given")
