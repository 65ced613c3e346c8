"""bench/build_pdal.sh and bench/engines.py: what can be checked without building PDAL."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from bench.engines import same_outputs

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "bench" / "build_pdal.sh"


def test_the_build_script_is_valid_shell_and_refuses_to_start_without_its_sources(tmp_path):
    assert subprocess.run(["bash", "-n", str(SCRIPT)], capture_output=True, timeout=30).returncode == 0
    env = {k: v for k, v in os.environ.items() if k not in ("PDAL_GIT", "PYPDAL_GIT")}
    env["PDAL_ROOT"] = str(tmp_path / "root")
    run = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True, env=env, timeout=30)
    assert run.returncode != 0 and "PDAL_GIT" in run.stderr and "github.com/PDAL/PDAL" in run.stderr
    assert not (tmp_path / "root").exists()  # nothing made, nothing installed


def test_same_outputs_names_the_files_that_differ(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    for d in (a, b):
        (d / "trees.csv").write_text("tree\n1\n")
    (a / "points.parquet").write_bytes(b"x")
    (b / "points.parquet").write_bytes(b"y")
    (a / "map.png").write_bytes(b"z")
    assert same_outputs(a, b) == ["map.png", "points.parquet"]
