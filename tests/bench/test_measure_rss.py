"""bench.measure._maxrss_bytes: a process's own peak, not the one it was forked from."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def test_a_child_of_a_large_parent_reports_its_own_peak():
    held = np.ones(300 * 2**17)  # 300 MiB, touched, in this (the parent) process
    held[:] = 2.0
    out = subprocess.run(
        [sys.executable, "-c", "from bench.measure import _maxrss_bytes; print(_maxrss_bytes())"],
        capture_output=True, text=True, check=True, cwd=ROOT,
    )
    assert int(out.stdout) < 200 * 2**20  # getrusage's ru_maxrss says 300+ MiB here
    assert held[0] == 2.0
