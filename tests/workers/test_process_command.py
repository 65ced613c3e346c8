"""``orchard process``: outputs, and every bad input → one line, exit code 2, nothing left behind."""

from __future__ import annotations

import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest

from service.cli import main


def _run(capsys, *argv):
    code = main(["process", *map(str, argv)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _assert_clean_failure(code, err, out_dir, expect_code=2):
    assert code == expect_code, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("orchard process: ")
    assert "Traceback" not in err
    assert not out_dir.exists() or not any(out_dir.rglob("*"))


def test_process_prints_a_summary_and_its_rows(small_block, tmp_path, capsys):
    code, out, err = _run(capsys, small_block, "--out", tmp_path / "o")
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].startswith("8 trees, 2 rows, 0 empty slots, 0 young, mean height ")
    assert lines[1].split() == ["row", "trees", "empty", "young", "height_m"]
    assert [ln.split()[:4] for ln in lines[2:]] == [["1", "4", "0", "0"], ["2", "4", "0", "0"]]
    assert "8 trees" in err
    assert pq.read_table(tmp_path / "o" / "trees.parquet").num_rows == 8


def test_process_prints_the_tree_table_on_request(small_block, tmp_path, capsys):
    code, out, err = _run(capsys, small_block, "--out", tmp_path / "o", "--trees")
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].split()[:5] == ["row", "pos", "tree", "young", "trunk_x"]
    assert len(lines) == 1 + 8
    assert [ln.split()[:4] for ln in lines[1:3]] == [["1", "1", "1", "no"], ["1", "2", "2", "no"]]


@pytest.mark.slow
def test_process_tiled_with_embedded_cluster(small_block, tmp_path, capsys):
    code, out, err = _run(capsys, small_block, "--out", tmp_path / "o", "--tile-size", 10, "--workers", 2, "--labelled-laz")
    assert code == 0, err
    assert "dask dashboard: http" in err
    assert "tiles [" in err and "] 0/" in err
    names = {p.name for p in (tmp_path / "o").iterdir()} - {"rows.parquet", "gaps.parquet"}  # (rows where found)
    assert names == {"labelled.laz", "points.parquet", "trees.parquet", "trees.csv", "report.html", "map.png",
                     "history.parquet"}


@pytest.mark.slow
@pytest.mark.parametrize("tiled", [False, True])
def test_process_a_block_with_stray_points_kilometres_away(small_block, tmp_path, capsys, tiled, dask_cluster):
    # a GNSS glitch: three returns 30-40 km from the orchard. Before, one ground raster
    # spanning them needed hundreds of GiB (MemoryError), and 10 m tiles over the 40 km
    # box (12 M, a few dozen of them holding points) were refused as more than 1 M tiles
    from pipeline.laswriting import LasBlockWriter
    from pipeline.reading import read_points

    xyz, info = read_points(small_block)
    xyz = xyz + info.origin
    stray = xyz[:3] + [[30_000.0, 0.0, 0.0], [0.0, 40_000.0, 0.0], [30_000.0, 30_000.0, 5.0]]
    path = tmp_path / "stray.laz"
    with LasBlockWriter(path, offsets=tuple(np.floor(xyz.min(axis=0)))) as w:
        w.write(np.vstack([xyz, stray]))
    extra = ["--tile-size", 10, "--scheduler", dask_cluster.scheduler_address] if tiled else []
    code, out, err = _run(capsys, path, "--out", tmp_path / "o", *extra)
    assert code == 0, err
    assert "8 trees" in err
    tree_id = pq.read_table(tmp_path / "o" / "points.parquet").column("tree_id").to_numpy()
    assert len(tree_id) == len(xyz) + 3 and (tree_id[-3:] == 0).all()


def _las(path, n=1000, **kw):
    from pipeline.laswriting import LasBlockWriter

    rng = np.random.default_rng(0)
    with LasBlockWriter(path, offsets=(500_000.0, 6_950_000.0, 0.0), **kw) as w:
        w.write(rng.uniform(0, 10, (n, 3)) + [500_000.0, 6_950_000.0, 100.0])
    return path


def _patch(path, offset, fmt, *values):
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    path.write_bytes(bytes(data))
    return path


def _bad_inputs(tmp_path):
    text = tmp_path / "notes.laz"
    text.write_text("this is not a point cloud\n")
    trunc = _las(tmp_path / "trunc.las", n=5000)
    trunc.write_bytes(trunc.read_bytes()[:2000])
    trunc_laz = _las(tmp_path / "trunc.laz", n=50_000)
    trunc_laz.write_bytes(trunc_laz.read_bytes()[: trunc_laz.stat().st_size // 2])
    empty = tmp_path / "empty.las"
    with laspy.open(empty, mode="w", header=laspy.LasHeader(version="1.4", point_format=6)):
        pass
    nan = _patch(_las(tmp_path / "nan.las"), 131, "<d", float("nan"))
    absurd = _patch(_las(tmp_path / "absurd.las"), 155, "<d", 1e13)
    return {
        "not-las": (text, "not a LAS/LAZ file"),
        "truncated": (trunc, "truncated"),
        "truncated-laz": (trunc_laz, "truncated"),
        "empty": (empty, "empty"),
        "nan-scale": (nan, "scale"),
        "absurd-offset": (absurd, "absurd"),
        "missing": (tmp_path / "nope.laz", "no such file"),
        "folder": (tmp_path, "is a folder; give a .las or .laz file"),  # was "no such file"
        "device": (Path("/dev/null"), "not a regular file"),
        "empty-path": ("", "no input file given"),  # was the current folder's name
    }


@pytest.mark.parametrize("case", ["not-las", "truncated", "truncated-laz", "empty", "nan-scale", "absurd-offset", "missing",
                                  "folder", "device", "empty-path"])
@pytest.mark.parametrize("tiled", [False, True])
def test_bad_input(tmp_path, capsys, case, tiled):
    path, words = _bad_inputs(tmp_path)[case]
    out_dir = tmp_path / "out"
    extra = ["--tile-size", 10] if tiled else []
    code, _, err = _run(capsys, path, "--out", out_dir, *extra)
    _assert_clean_failure(code, err, out_dir)
    assert words in err


@pytest.mark.slow
def test_a_block_too_wide_for_one_ground_raster(tmp_path, capsys):
    # a 1.5 km diagonal line of points with no gap: one raster would need 36 M cells
    # (in one 5 km tile: test_a_failing_tile_prints_one_message_not_worker_tracebacks)
    from pipeline.laswriting import LasBlockWriter

    t = np.arange(0.0, 1500.0, 2.0)
    path = tmp_path / "line.laz"
    with LasBlockWriter(path, offsets=(500_000.0, 6_950_000.0, 0.0)) as w:
        w.write(np.column_stack([t + 500_000.0, t + 6_950_000.0, np.full_like(t, 100.0)]))
    out_dir = tmp_path / "out"
    code, _, err = _run(capsys, path, "--out", out_dir)
    _assert_clean_failure(code, err, out_dir)
    assert "too wide" in err and "--tile-size" in err
    assert "tile 0: " not in err


@pytest.mark.parametrize(
    "argv,words",
    [
        (["--graph-voxel-size", "-1"], "--graph-voxel-size"),
        (["--graph-voxel-size", "nan"], "--graph-voxel-size: Input should be a finite number"),
        (["--work", "w"], "--work needs tiles: the block fits the memory budget"),
        (["--tile-size", "20", "--buffer", "1e308"], "--buffer: Input should be less than or equal to 1000"),  # was an internal OverflowError
        (["--tile-size", "20", "--grid-origin=1e21,1e21"], "grid origin must be finite and within"),
        (["--graph-edge-radius", "5", "--graph-voxel-size", "0.1"], "--graph-edge-radius: Input should be less than or equal to 2"),
        (["--tile-size", "10", "--buffer", "1"], "reach"),
        (["--tile-size", "-5"], "--tile-size: Input should be greater than or equal to 1"),
        (["--tile-size", "20", "--workers", "0"], "--workers must be from 1 to"),
        (["--tile-size", "20", "--workers", "100000"], "--workers must be from 1 to"),
        # options that went unused without a word (and --engine pdal "worked" with no PDAL)
        (["--workers", "2"], "--workers needs tiles: the block fits the memory budget"),
        (["--tile-size", "0", "--workers", "2"], "--workers needs tiles: --tile-size 0 processes the block in one piece"),
        (["--tile-size", "20", "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "brings its own workers"),
        (["--grid-origin=0,0"], "--grid-origin needs tiles"),
        (["--engine", "pdal"], "--engine needs tiles"),
        (["--engine", "laspy"], "--engine needs tiles"),
        (["--rerun-tile", "3"], "--work"),
        (["--tile-size", "20", "--work", "memory://w1"], "lives in this process only"),
        # every job failed on it with "ImportError: Install s3fs" after the block was read
        (["--tile-size", "20", "--work", "nosuch://bucket/w"], "Protocol not known"),
    ],
)
def test_nonsense_parameters(small_block, tmp_path, capsys, argv, words):
    out_dir = tmp_path / "out"
    code, _, err = _run(capsys, small_block, "--out", out_dir, *argv)
    _assert_clean_failure(code, err, out_dir)
    assert words in err


def test_the_pdal_engine_without_pdal(small_block, tmp_path, capsys):
    """Only makes sense where PDAL's Python bindings are absent (with them, the run works)."""
    from workers.tiler import pdal_available

    if pdal_available():
        pytest.skip("PDAL's Python bindings are installed: --engine pdal runs")
    out_dir = tmp_path / "out"
    code, _, err = _run(capsys, small_block, "--out", out_dir, "--tile-size", "20", "--engine", "pdal")
    _assert_clean_failure(code, err, out_dir)
    assert "import pdal failed" in err and "--engine laspy" in err


def test_no_trees_exit_code(ground_block, tmp_path, capsys, dask_cluster):
    out_dir = tmp_path / "out"
    code, _, err = _run(capsys, ground_block, "--out", out_dir)
    _assert_clean_failure(code, err, out_dir, expect_code=3)
    assert "no trees" in err
    # tiled, into folders that did not exist: none is left behind (a/b stayed)
    code, _, err = _run(capsys, ground_block, "--out", tmp_path / "a" / "b" / "c", "--tile-size", 10,
                        "--scheduler", dask_cluster.scheduler_address)
    assert code == 3 and "no trees" in err, err
    assert not (tmp_path / "a").exists()


def test_console_script_bad_input(tmp_path):
    bad = tmp_path / "x.las"
    bad.write_bytes(b"LASF" + bytes(50))
    run = subprocess.run(
        [sys.executable, "-m", "service.cli", "process", str(bad), "--out", str(tmp_path / "out")],
        capture_output=True,
        timeout=120,
    )
    assert run.returncode == 2
    assert len(run.stderr.decode().strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_unusable_output_folder_fails_before_any_work(small_block, tmp_path, capsys):
    a_file = tmp_path / "afile"
    a_file.write_text("x")
    for out, words in ((a_file, "is a file"), (a_file / "sub", "is a file")):
        code, _, err = _run(capsys, small_block, "--out", out, "--tile-size", 10)
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert words in err and "dask dashboard" not in err  # refused before a cluster starts
    assert a_file.read_text() == "x"


def test_outputs_that_would_destroy_the_input_or_be_deleted_are_refused(small_block, tmp_path, capsys):
    # --out inside --work: printed "4 trees -> wr/results", exit 0, then the work store
    # deleted its results folder with the outputs; an input named labelled.laz in --out
    # was deleted as an earlier run's output (or overwritten with --labelled-laz)
    work = tmp_path / "wr"
    for out in (work / "results", work / "tiles" / "x", work / "attempts"):
        code, _, err = _run(capsys, small_block, "--out", out, "--tile-size", 12, "--work", work)
        _assert_clean_failure(code, err, out)
        assert f"lies inside the folder {out.relative_to(work).parts[0]} of --work" in err and "dask dashboard" not in err
    folder = tmp_path / "again"
    folder.mkdir()
    for name in ("labelled.laz", "points.parquet"):
        source = folder / name
        shutil.copy(small_block, source)
        for extra in ([], ["--labelled-laz"], ["--tile-size", "12"]):
            code, _, err = _run(capsys, source, "--out", folder, *extra)
            assert code == 2 and "under the name of an output" in err and "Traceback" not in err, err
            assert source.read_bytes() == small_block.read_bytes()
        source.unlink()
    assert sorted(p.name for p in folder.iterdir()) == []
    # an input in the output folder under a name of its own is fine
    shutil.copy(small_block, folder / "block.laz")
    code, _, err = _run(capsys, folder / "block.laz", "--out", folder, "--labelled-laz")
    assert code == 0, err
    names = {p.name for p in folder.iterdir()} - {"rows.parquet", "gaps.parquet"}
    assert names == {"block.laz", "labelled.laz", "points.parquet", "trees.parquet", "trees.csv", "report.html", "map.png",
                     "history.parquet"}


def test_resume_and_rerun_take_only_the_block_the_job_was_started_on(small_block, ground_block, tmp_path, capsys):
    # INPUT was ignored: another block given with --resume merged the first block's tiles
    from workers.workstore import JOB_KEY, WorkStore

    work = WorkStore(str(tmp_path / "work"))
    work.claim()
    work.put_json(JOB_KEY, {"input_path": str(small_block), "params": {"segment": {"max_crown_radius": 3.0}},
                            "labelled_laz": False})
    for extra in (["--resume"], ["--rerun-tile", "3"]):
        code, _, err = _run(capsys, ground_block, "--out", tmp_path / "out", "--work", tmp_path / "work", *extra)
        _assert_clean_failure(code, err, tmp_path / "out")
        assert f"is not the block the job in --work {tmp_path / 'work'} was started on ({small_block})" in err
    # nor other options, which went ignored: the job goes on as it was planned
    for extra, words in ((["--tile-size", "50", "--workers", "2"], "--tile-size, --workers: --resume and --rerun-tile go on"),
                         (["--grid-origin=0,0"], "--grid-origin: --resume"), (["--engine", "laspy"], "--engine: --resume"),
                         (["--segment-max-crown-radius", "2"], "the pipeline options differ"),
                         (["--labelled-laz"], "started without --labelled-laz")):
        code, _, err = _run(capsys, small_block, "--out", tmp_path / "out", "--work", tmp_path / "work", "--resume", *extra)
        _assert_clean_failure(code, err, tmp_path / "out")
        assert words in err, err
    # the job's own value of an option is no change
    code, _, err = _run(capsys, small_block, "--out", tmp_path / "out", "--work", tmp_path / "work", "--resume",
                        "--segment-max-crown-radius", "3")
    assert "differ" not in err and "--resume and --rerun-tile go on" not in err


@pytest.mark.parametrize("argv, words", [(["--buffer", "nan"], "--buffer: Input should be a finite number"),
                                         (["--buffer", "-1"], "--buffer: Input should be greater than or equal to 0"),
                                         (["--buffer", "20"], "--buffer needs --tile-size")])
def test_buffer_without_tiles_is_refused(small_block, tmp_path, capsys, argv, words):
    out_dir = tmp_path / "out"
    code, _, err = _run(capsys, small_block, "--out", out_dir, *argv)
    _assert_clean_failure(code, err, out_dir)
    assert words in err


@pytest.mark.slow
def test_a_failing_tile_prints_one_message_not_worker_tracebacks(tmp_path):
    # the dask workers are other processes writing to the same terminal: each attempt of
    # a failing tile used to print a "Compute Failed ... Traceback" block there
    from pipeline.laswriting import LasBlockWriter

    t = np.arange(0.0, 1500.0, 2.0)
    path = tmp_path / "line.laz"
    with LasBlockWriter(path, offsets=(500_000.0, 6_950_000.0, 0.0)) as w:
        w.write(np.column_stack([t + 500_000.0, t + 6_950_000.0, np.full_like(t, 100.0)]))
    run = subprocess.run(
        [sys.executable, "-m", "service.cli", "process", str(path), "--out", str(tmp_path / "out"),
         "--tile-size", "5000", "--workers", "1"],
        capture_output=True, text=True, timeout=180, check=False,
    )
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert "Traceback" not in run.stderr and "Compute Failed" not in run.stderr, run.stderr
    assert len(lines) <= 3 and lines[-1].startswith("orchard process: tile 0: ") and "too wide" in lines[-1]
    assert "--tile-size" in lines[-1]  # the hint, worded for the command line
    out = tmp_path / "out"
    assert not out.exists() or not any(out.rglob("*"))


def _children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_ctrl_c_during_a_tiled_run_prints_one_line(orchard_block, tmp_path, default_sigint):
    # a terminal's Ctrl-C goes to the whole process group: the dask workers each printed
    # a KeyboardInterrupt traceback (and the shutdown warnings) under "interrupted"
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "process", str(orchard_block), "--out", str(out),
         "--tile-size", "8", "--workers", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        while len(_children(proc.pid)) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(2.0)  # the workers are up and busy with tiles
        assert proc.poll() is None, "the run ended before it could be interrupted"
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "WARNING" not in err and "KeyboardInterrupt" not in err, err
    assert err.strip().splitlines()[-1] == "orchard: interrupted"
    assert not (out / "trees.parquet").exists()


@pytest.mark.slow
@pytest.mark.parametrize("pdal", ["a model of PDAL's splitter", "PDAL"])
def test_the_pdal_engine_gives_the_same_outputs(orchard_block, tmp_path, capsys, monkeypatch, pdal, dask_cluster):
    """The issue's case: a grid whose splitter adds buffer-only views of cells off the grid
    (5 of 24 trees found before). Every output equals the default engine's, byte for byte."""
    from workers.tiler import pdal_available

    if pdal == "PDAL" and not pdal_available():
        pytest.skip("PDAL's Python bindings are not installed")
    if pdal != "PDAL":
        from test_pdal_views import _FakePdal

        monkeypatch.setitem(sys.modules, "pdal", _FakePdal())
    outs = {}
    for engine in ("laspy", "pdal"):
        outs[engine] = tmp_path / engine
        # the tests' cluster (the engines differ in this process; the embedded cluster's
        # worker processes are test_process_tiled_with_embedded_cluster's)
        code, _, err = _run(capsys, orchard_block, "--out", outs[engine], "--tile-size", 20, "--engine", engine,
                            "--scheduler", dask_cluster.scheduler_address)
        assert code == 0, err
    names = sorted(p.name for p in outs["laspy"].iterdir())
    assert names == sorted(p.name for p in outs["pdal"].iterdir()) and "points.parquet" in names
    for name in names:  # the report and the map too: the tiler keeps the same sample
        assert (outs["laspy"] / name).read_bytes() == (outs["pdal"] / name).read_bytes(), name
