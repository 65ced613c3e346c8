"""Temporary files of a service process: uploads and inbox copies being written.

Several processes may share one data folder (an API-only process beside the one that
runs jobs, or ``orchard schedules run`` from a shell). Each keeps its temporary files in
a folder of its own, ``<tmp>/proc-<id>/``, holding an exclusive lock (flock) on a file in
it for as long as it lives. `sweep` removes the folders whose lock is free: their
process is gone (crashed mid-upload), while the files of live processes (an upload
another process is still receiving) are never touched.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import threading
import uuid
from pathlib import Path
from typing import IO

log = logging.getLogger("orchard.tempfiles")

_PREFIX = "proc-"
_LOCK = ".lock"
_held: dict[Path, tuple[Path, IO]] = {}
_guard = threading.Lock()


def process_dir(tmp_dir: Path) -> Path:
    """This process's folder for temporary files under ``tmp_dir`` (created, and locked,
    at the first call; kept for the life of the process)."""
    tmp_dir = Path(tmp_dir)
    with _guard:
        held = _held.get(tmp_dir)
        if held is not None and held[0].is_dir():
            return held[0]
        tmp_dir.mkdir(parents=True, exist_ok=True)
        token = uuid.uuid4().hex
        # made and locked under a name sweep() ignores, then renamed: a sweep never
        # sees a folder of ours without its lock held
        making = tmp_dir / f".making-{token}"
        making.mkdir()
        fh = open(making / _LOCK, "w")  # noqa: SIM115 - held for the life of the process
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fh.write(f"pid {os.getpid()}\n")
        fh.flush()
        final = tmp_dir / f"{_PREFIX}{token}"
        os.rename(making, final)
        _held[tmp_dir] = (final, fh)
        return final


def sweep(tmp_dir: Path) -> int:
    """Remove the temporary folders of processes that are gone, and loose temporary
    files of versions before these folders; returns how many folders were removed."""
    tmp_dir = Path(tmp_dir)
    if not tmp_dir.is_dir():
        return 0
    own = {held[0] for held in _held.values()}
    removed = 0
    for folder in tmp_dir.glob(f"{_PREFIX}*"):
        if folder in own or not folder.is_dir():
            continue
        try:
            fh = open(folder / _LOCK, "a")  # noqa: SIM115 - closed below
        except OSError:  # no lock file: not one of ours
            continue
        try:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:  # its process is alive
                continue
            shutil.rmtree(folder, ignore_errors=True)
            removed += 1
        finally:
            fh.close()
    for pattern in ("upload-*", "inbox-*"):  # written straight into tmp/ by older versions
        for stale in tmp_dir.glob(pattern):
            stale.unlink(missing_ok=True)
    if removed:
        log.info("removed the temporary files of %d process(es) that had stopped", removed)
    return removed
