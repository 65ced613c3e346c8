"""The data folder is the service user's alone: folders 0700, files 0600.

The job store, the farms' uploaded blocks and their results are readable by nobody
else on the machine. New folders and files are made so when the service creates them
(`private_dir`, `private_file`, and the ``umask`` that `orchard serve` sets), and a
data folder written by an earlier version, or copied in by hand, is tightened when the
service starts (`tighten`). Only group and other bits are removed; the owner's stay.
"""

from __future__ import annotations

import logging
import os
import stat
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger("orchard.service")

DIR_MODE = 0o700
FILE_MODE = 0o600
#: the process umask of the service: whatever it (or a local dask worker) creates is private
UMASK = 0o077


def private_dir(path: Path) -> Path:
    """``path`` as a folder (created with its parents if missing) that only its owner can enter."""
    path = Path(path)
    path.mkdir(mode=DIR_MODE, parents=True, exist_ok=True)
    _tighten_one(path)
    return path


def private_file(path: Path) -> Path:
    """``path`` as a file (created empty if missing) that only its owner can read."""
    path = Path(path)
    fd = os.open(path, os.O_CREAT | os.O_RDONLY, FILE_MODE)
    os.close(fd)
    _tighten_one(path)
    return path


def _tighten_one(path: Path, st: os.stat_result | None = None) -> bool:
    """Remove group and other bits of one folder or file; True if it changed (symlinks are
    left alone: their target may be anybody's)."""
    try:
        st = st or os.lstat(path)
        if stat.S_ISLNK(st.st_mode) or not st.st_mode & 0o077:
            return False
        os.chmod(path, stat.S_IMODE(st.st_mode) & ~0o077)
        return True
    except (FileNotFoundError, PermissionError):  # gone meanwhile, or another user's file
        return False


def tighten(root: Path, *, skip: Iterable[Path] = ()) -> int:
    """Remove group and other permissions from ``root`` and everything below it, except
    the folders in ``skip`` and their contents (inboxes: their files belong to the farms
    that copy captures in). Returns the number of folders and files changed."""
    root = Path(root)
    skipped = {os.path.abspath(p) for p in skip}
    changed = int(_tighten_one(root))
    for folder, dirs, files in os.walk(root):
        dirs[:] = [d for d in dirs if os.path.join(folder, d) not in skipped]
        for name in (*dirs, *files):
            changed += _tighten_one(Path(folder) / name)
    if changed:
        log.info("made %d folder(s) and file(s) under the data folder private to the service user", changed)
    return changed
