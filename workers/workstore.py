"""The work store: where tiles and per-tile results live between the tiler, the dask
tasks and the merge. A local folder by default; any fsspec URL (``s3://``,
``memory://`` in tests) works, so workers on other machines read tiles directly
instead of receiving them through the scheduler."""

from __future__ import annotations

import contextlib
import fcntl
import io
import json
import os
import pickle
import time
import uuid
from pathlib import Path

import numpy as np

from pipeline.errors import ParameterError

#: The job record: what the job was given, its plan and its failed tiles.
JOB_KEY = "job.json"

#: What a work store writes at its root: the job record, the tiles, the tile results and
#: the attempt log (plus hidden temporary files of writes in progress). Nothing else
#: there is the store's to delete, and these only in a folder the store has marked.
OWN_ENTRIES = (JOB_KEY, "tiles", "results", "attempts")

#: The mark a work store leaves in its root folder: only a marked folder's entries of the
#: names above are the store's (a user's own "tiles" folder is not).
MARKER = ".orchard-work-store"

#: Held (flock) by the process running a job on a local store: one job per store.
LOCK = ".orchard-lock"


def own_entry(name: str) -> bool:
    return name in OWN_ENTRIES or name in (MARKER, LOCK) or (name.startswith(".") and name.endswith(".tmp"))


def absolute_url(url: str) -> str:
    """A work-store address that means the same in every process: a local path made
    absolute (a worker resolved a relative one against its own folder); URLs as given."""
    url = os.fspath(url)
    if "://" in url:
        return url
    return os.path.abspath(os.path.expanduser(url))


def check_work_url(url: str, *, shared: bool) -> None:
    """ParameterError unless this process can use the work store at ``url``; ``shared``:
    dask worker processes must reach it too (``memory://`` lives in one process only).
    An fsspec URL whose file-system package is not installed (``s3://`` without s3fs)
    is refused here, before any job starts."""
    url = os.fspath(url)
    if shared and url.startswith("memory://"):
        raise ParameterError(
            f"work store {url} lives in this process only, and the dask workers are other processes: "
            "give a folder all of them share or a shared URL (s3://...)"
        )
    import fsspec  # with asyncio, only where a store is used: a run in one piece needs none

    try:
        fsspec.core.url_to_fs(url)
    except ImportError as exc:
        raise ParameterError(f"work store {url}: {exc} (pip install it here and on every dask worker)") from None
    except ValueError as exc:
        raise ParameterError(f"work store {url}: {exc}; give a folder or an fsspec URL such as s3://bucket/orchard") from None


class WorkStore:
    """Arrays, JSON and small pickles under one root (folder or fsspec URL).

    Writes are atomic on local folders (temporary name, then rename), so a task killed
    in the middle of a write leaves no half-written file that a retry would read.
    """

    def __init__(self, url: str):
        import fsspec

        self.url = absolute_url(url)
        self.fs, root = fsspec.core.url_to_fs(self.url)
        self.root = root.rstrip("/")
        self.local = "file" in (self.fs.protocol if isinstance(self.fs.protocol, tuple) else (self.fs.protocol,))

    def __reduce__(self):
        return (WorkStore, (self.url,))

    def path(self, key: str) -> str:
        return f"{self.root}/{key}"

    def local_path(self, key: str) -> str | None:
        """Filesystem path of a key when the store is a local folder, else None."""
        return self.path(key) if self.local else None

    def _put(self, key: str, data: bytes | None, write=None) -> None:
        """Write ``data``, or on a local folder what ``write(file)`` writes (None: ``data``)."""
        path = self.path(key)
        parent = path.rsplit("/", 1)[0]
        self.fs.makedirs(parent, exist_ok=True)
        if self.local:
            tmp = f"{parent}/.{path.rsplit('/', 1)[1]}.{uuid.uuid4().hex[:8]}.tmp"
            with open(tmp, "wb") as f:
                write(f) if write is not None else f.write(data)
            os.replace(tmp, path)
        else:
            self.fs.pipe_file(path, data)

    def _get(self, key: str) -> bytes:
        return self.fs.cat_file(self.path(key))

    def put_array(self, key: str, arr: np.ndarray) -> None:
        arr = np.ascontiguousarray(arr)
        if self.local:  # straight to the file: a tile's records are hundreds of MB, not copied twice first
            self._put(key, None, lambda f: np.save(f, arr, allow_pickle=False))
            return
        buf = io.BytesIO()
        np.save(buf, arr, allow_pickle=False)
        self._put(key, buf.getvalue())

    def get_array(self, key: str) -> np.ndarray:
        if self.local:  # read into the array itself, not through two copies
            return np.load(self.path(key), allow_pickle=False)
        return np.load(io.BytesIO(self._get(key)), allow_pickle=False)

    def open_array(self, key: str) -> StoredArray:
        """A stored 1-d array, read later a range of rows at a time (never whole)."""
        return StoredArray(self.fs, self.path(key))

    def put_json(self, key: str, obj) -> None:
        self._put(key, json.dumps(obj, indent=1).encode())

    def get_json(self, key: str):
        return json.loads(self._get(key))

    def put_object(self, key: str, obj) -> None:
        self._put(key, pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))

    def get_object(self, key: str):
        return pickle.loads(self._get(key))

    def exists(self, key: str) -> bool:
        return self.fs.exists(self.path(key))

    def list(self, prefix: str) -> list[str]:
        """Keys directly under ``prefix`` (a folder), sorted."""
        path = self.path(prefix)
        if not self.fs.exists(path):
            return []
        names = [p.rstrip("/").rsplit("/", 1)[-1] for p in self.fs.ls(path, detail=False)]
        return sorted(f"{prefix.rstrip('/')}/{n}" for n in names if not n.startswith("."))

    def entries(self) -> list[str]:
        """Names directly in the store's root folder, sorted (none if it does not exist)."""
        if not self.fs.exists(self.root):
            return []
        return sorted(p.rstrip("/").rsplit("/", 1)[-1] for p in self.fs.ls(self.root, detail=False))

    def marked(self) -> bool:
        return self.fs.exists(self.path(MARKER))

    def foreign(self) -> list[str]:
        """Names in the root folder that are not the store's: all of them in a folder the
        store has not marked, else those it does not write."""
        names = self.entries()
        if not self.marked():
            return [n for n in names if n != LOCK]
        return [n for n in names if not own_entry(n)]

    def check_free(self) -> None:
        """ParameterError if the root folder holds files that are not a work store's."""
        foreign = self.foreign()
        if foreign:
            shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
            raise ParameterError(
                f"work folder {self.url} holds files that are not a work store's ({shown}); ",
                hint="give {job.work_dir} a new or empty folder", param="job.work_dir", value=self.url,
            )

    def claim(self) -> None:
        """Mark the root folder as a work store (created if missing); ParameterError if
        it holds files that are not a work store's."""
        self.check_free()
        self._put(MARKER, b"orchard work store: deleted with the job\n")

    @contextlib.contextmanager
    def lock(self):
        """Hold the store for one job (local folders; a no-op elsewhere).

        Raises
        ------
        ParameterError
            Another process holds it: two jobs would delete each other's tiles.
        """
        if not self.local:
            yield
            return
        os.makedirs(self.root, exist_ok=True)
        fh = open(os.path.join(self.root, LOCK), "a+")  # noqa: SIM115 - held for the whole job
        try:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise ParameterError(
                    f"work folder {self.url} is in use by another run; ",
                    hint="give each run its own {job.out_dir} or {job.work_dir}", param="job.work_dir", value=self.url,
                ) from None
            yield
        finally:
            try:  # the lock file goes with the lock, and the folder if nothing else is left
                os.unlink(os.path.join(self.root, LOCK))
                if not os.listdir(self.root):
                    os.rmdir(self.root)
            except OSError:
                pass
            finally:
                fh.close()

    def remove(self, prefix: str = "") -> None:
        """Delete a folder of the store; with no ``prefix``, everything the store writes
        (:data:`OWN_ENTRIES`), its mark, and then the root folder if that leaves it empty.
        Files of anyone else are never touched, nor anything in an unmarked folder.

        Tolerant of tiles still writing meanwhile (a job that stopped while tasks ran):
        what cannot be deleted is left, and no error replaces the job's own.
        """
        if prefix:
            self._rm(self.path(prefix))
            return
        if not self.marked():
            return
        for name in self.entries():
            if own_entry(name) and name not in (MARKER, LOCK):
                self._rm(self.path(name))
        self._rm(self.path(MARKER))
        self._drop_stale_lock()  # (a held lock stays: its holder removes it when it lets go)
        if not self.entries():
            self._rm(self.root)  # empty: nothing but the folder goes

    def _drop_stale_lock(self) -> None:
        """Delete the lock file of a local store if no process holds it (its holder was
        killed before it could let go)."""
        if not self.local:
            return
        path = os.path.join(self.root, LOCK)
        try:
            fh = open(path, "r+")  # noqa: SIM115 - closed below
        except OSError:
            return
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.unlink(path)  # while holding it: no run can take it meanwhile and lose it
        except OSError:  # held (BlockingIOError), or gone
            pass
        finally:
            fh.close()

    def _rm(self, path: str) -> None:
        for _ in range(3):
            try:
                if self.fs.exists(path):
                    self.fs.rm(path, recursive=True)
                return
            except (OSError, ValueError):  # a writer added or took files meanwhile; or the working directory
                time.sleep(0.05)


class StoredArray:
    """A 1-d ``.npy`` array of a work store whose rows are read by range.

    Each read asks the file system for those bytes only (a local ``pread``-like read,
    or a range request), so nothing stays mapped or resident after it: a memory map
    would keep the kernel's read-ahead around every page it touched (8 MB each here),
    and a store that is not a local folder could only be read whole.
    """

    def __init__(self, fs, path: str):
        self.fs, self.path = fs, path
        with fs.open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            fmt = np.lib.format
            read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, fortran, dtype = read_header(f)
            self._offset = f.tell()
        if len(shape) != 1 or fortran or dtype.hasobject:
            raise ValueError(f"{path}: not a 1-d array of plain values")
        self.dtype = np.dtype(dtype)
        self.shape = (int(shape[0]),)

    def __len__(self) -> int:
        return self.shape[0]

    def rows(self, lo: int, hi: int) -> np.ndarray:
        """Rows ``lo`` to ``hi - 1`` (clamped to the array) as a new array."""
        lo, hi = max(int(lo), 0), min(int(hi), len(self))
        if hi <= lo:
            return np.zeros(0, self.dtype)
        size = self.dtype.itemsize
        data = self.fs.cat_file(self.path, start=self._offset + lo * size, end=self._offset + hi * size)
        return np.frombuffer(data, dtype=self.dtype)


def default_work_dir(out_dir: str) -> str:
    return str(Path(out_dir) / "_work")
