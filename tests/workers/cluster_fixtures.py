"""Helpers of the worker tests that start dask processes."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path


def scheduler_address(scheduler_file: Path, proc: subprocess.Popen, timeout: float = 60.0) -> str:
    """The address a ``dask scheduler --port 0 --scheduler-file FILE`` reports in FILE once it listens."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the dask scheduler exited ({proc.returncode})")
        try:
            return json.loads(scheduler_file.read_text())["address"]
        except (FileNotFoundError, ValueError, KeyError):  # not written yet, or being written
            time.sleep(0.05)
    raise RuntimeError(f"the dask scheduler did not write {scheduler_file} within {timeout:g} s")
