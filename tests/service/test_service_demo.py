"""`orchard demo`, the README's main command, end to end (smaller block than its default)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


def test_demo_runs_the_service_end_to_end(tmp_path):
    cmd = [sys.executable, "-m", "service.cli", "demo", "--data-dir", str(tmp_path / "data"),
           "--rows", "1", "--trees-per-row", "3", "--density", "0.3", "--tile-size", "20"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert "Traceback" not in proc.stderr
    assert "job done" in proc.stderr and "shutting" in proc.stderr
    report = Path(re.search(r"report page:\s+(\S+)", proc.stdout).group(1))
    assert report.exists() and "data:image/png;base64," in report.read_text()
    table = proc.stdout.split("\n\n")[1].splitlines()
    assert table[0].split()[0] == "tree"
    assert 2 <= len(table) - 1 <= 4  # 3 simulated trees
    assert (tmp_path / "data" / "demo" / "trees.csv").exists()
