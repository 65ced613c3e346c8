"""Faults on a real cluster: ``dask scheduler`` + two ``dask worker`` processes on loopback.

A worker killed with SIGKILL mid-job → identical output, from relative paths given in a
folder that is not the workers'; a tile that raises is retried, then the job stops with
an error naming it (never hangs); the failed tile re-runs alone.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from pipeline.jobparams import JobParams, TilingParams
from workers.job import run_job
from workers.jobspec import JobSpec
from workers.workstore import WorkStore

pytestmark = pytest.mark.slow
TIMEOUT = 240


def _orchard(*args) -> list[str]:
    return [sys.executable, "-m", "service.cli", "process", *map(str, args)]


@pytest.fixture(scope="module")
def reference(small_block, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reference")
    run_job(JobSpec(str(small_block), str(out), job=JobParams(tiling=TilingParams(tile_size=10.0))))
    return out


def _same_outputs(a: Path, b: Path) -> None:
    assert pq.read_table(a / "points.parquet").to_pydict() == pq.read_table(b / "points.parquet").to_pydict()
    assert pq.read_table(a / "trees.parquet").equals(pq.read_table(b / "trees.parquet"))


def test_worker_killed_mid_job_and_relative_paths_mean_the_same_on_workers_in_other_folders(
        small_block, reference, loopback_cluster, tmp_path):
    # the workers run in a folder of their own: relative --out / --work / input paths
    # named files there (FileNotFoundError on .../tiles/index.json), so every local
    # path is made absolute before a task is sent
    import shutil

    here = tmp_path / "client"
    here.mkdir()
    shutil.copy(small_block, here / "block.laz")
    assert Path(os.getcwd()).resolve() != here.resolve()
    out, work = here / "out", here / "work"
    proc = subprocess.Popen(
        _orchard("block.laz", "--out", "out", "--tile-size", 10, "--scheduler", loopback_cluster.address,
                 "--work", "work"),
        cwd=here,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    loopback_cluster.ensure_workers(2)
    victim = loopback_cluster.workers[0]
    deadline = time.monotonic() + TIMEOUT
    done_at_kill = None
    while time.monotonic() < deadline and proc.poll() is None:
        results = list((work / "results").glob("*/summary.pkl")) if (work / "results").exists() else []
        if results:
            os.kill(victim.pid, signal.SIGKILL)
            done_at_kill = len(results)
            break
        time.sleep(0.02)
    try:
        _, err = proc.communicate(timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail("the job hung after a worker was killed")
    assert done_at_kill is not None, "the job ended before a worker could be killed"
    assert victim.wait(timeout=10) == -signal.SIGKILL
    assert proc.returncode == 0, err.decode()
    assert "dask dashboard:" in err.decode()
    total = int(err.decode().split("tile(s)")[0].split()[-1])
    assert done_at_kill < total, "every tile was done before the kill: the test proved nothing"
    _same_outputs(out, reference)


def _run_failing_tile(small_block, out: Path, work: Path, cluster, tile: int) -> subprocess.CompletedProcess:
    """``orchard process`` on the loopback cluster, 10 m tiles, with ``tile`` made to fail."""
    cluster.ensure_workers(2)
    return subprocess.run(
        _orchard(
            small_block, "--out", out, "--tile-size", 10, "--scheduler", cluster.address,
            "--work", work, "--inject-failure", tile,
        ),
        capture_output=True,
        timeout=TIMEOUT,
    )


def test_first_tile_failing_stops_the_job_naming_it_then_resume(small_block, reference, loopback_cluster, tmp_path):
    out, work = tmp_path / "out", tmp_path / "work"
    run = _run_failing_tile(small_block, out, work, loopback_cluster, 0)
    err = run.stderr.decode()
    assert run.returncode == 1, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("orchard process: tile 0 (core x") and "after 3 attempts" in last
    assert "Traceback" not in err
    assert len(WorkStore(str(work)).list("attempts/000000")) == 3  # first try + 2 retries
    assert not (out / "trees.parquet").exists() and not (out / "points.parquet").exists()

    resume = subprocess.run(
        _orchard(small_block, "--out", out, "--work", work, "--resume", "--scheduler", loopback_cluster.address),
        capture_output=True,
        timeout=TIMEOUT,
    )
    assert resume.returncode == 0, resume.stderr.decode()
    _same_outputs(out, reference)
    assert not work.exists()


def test_later_tile_failing_gives_partial_result_then_rerun_alone(small_block, reference, loopback_cluster, tmp_path):
    out, work = tmp_path / "out", tmp_path / "work"
    run = _run_failing_tile(small_block, out, work, loopback_cluster, 5)
    err = run.stderr.decode()
    assert run.returncode == 4, err
    assert "partial result: tiles [5] failed" in err and "--rerun-tile 5" in err
    assert len(WorkStore(str(work)).list("attempts/000005")) == 3
    rows = pq.ParquetFile(out / "points.parquet").metadata.num_rows
    # the summary says how many points the file holds (it gave the block's count alone)
    assert f"({rows} of them in points.parquet)" in err and rows < pq.ParquetFile(reference / "points.parquet").metadata.num_rows

    rerun = subprocess.run(
        _orchard(small_block, "--out", out, "--work", work, "--rerun-tile", 5), capture_output=True, timeout=TIMEOUT
    )
    assert rerun.returncode == 0, rerun.stderr.decode()
    _same_outputs(out, reference)
    assert not work.exists()
