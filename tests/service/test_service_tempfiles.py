"""Temporary files of service processes: each process's own locked folder, swept only
when its process is gone."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from service.tempfiles import process_dir, sweep


def _holder(tmp: Path) -> tuple[subprocess.Popen, Path]:
    proc = subprocess.Popen(
        [sys.executable, "-c",
         ("import sys, time; from pathlib import Path; from service.tempfiles import process_dir; "
          "d = process_dir(Path(sys.argv[1])); (d / 'upload-1.part').write_bytes(b'x'); "
          "print(d, flush=True); time.sleep(120)"), str(tmp)],
        stdout=subprocess.PIPE, text=True,
    )
    return proc, Path(proc.stdout.readline().strip())


def test_sweep_removes_only_the_folders_of_stopped_processes(tmp_path):
    tmp = tmp_path / "tmp"
    live, live_dir = _holder(tmp)
    dead, dead_dir = _holder(tmp)
    try:
        dead.kill()
        dead.wait()
        (tmp / "upload-old.part").write_bytes(b"from an older version")
        mine = process_dir(tmp)
        (mine / "inbox-2.part").write_bytes(b"y")
        assert sweep(tmp) == 1
        assert not dead_dir.exists() and not (tmp / "upload-old.part").exists()
        assert (live_dir / "upload-1.part").read_bytes() == b"x"
        assert (mine / "inbox-2.part").read_bytes() == b"y"
        assert process_dir(tmp) == mine  # one folder per process
    finally:
        live.kill()
        live.wait()
    assert sweep(tmp) == 1 and not live_dir.exists()
