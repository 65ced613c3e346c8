"""The work store: where tiles and per-tile results live between the tiler, the dask
tasks and the merge. A local folder by default; any fsspec URL (``s3://``,
``memory://`` in tests) works, so workers on other machines read tiles directly
instead of receiving them through the scheduler."""

from __future__ import annotations

import io
import json
import os
import pickle
import uuid
from pathlib import Path

import fsspec
import numpy as np

#: What a work store writes at its root: the job record, the tiles, the tile results and
#: the attempt log (plus hidden temporary files of writes in progress). Nothing else
#: there is the store's to delete.
OWN_ENTRIES = ("job.json", "tiles", "results", "attempts")


def _own(name: str) -> bool:
    return name in OWN_ENTRIES or (name.startswith(".") and name.endswith(".tmp"))


class WorkStore:
    """Arrays, JSON and small pickles under one root (folder or fsspec URL).

    Writes are atomic on local folders (temporary name, then rename), so a task killed
    in the middle of a write leaves no half-written file that a retry would read.
    """

    def __init__(self, url: str):
        self.url = str(url)
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

    def _put(self, key: str, data: bytes) -> None:
        path = self.path(key)
        parent = path.rsplit("/", 1)[0]
        self.fs.makedirs(parent, exist_ok=True)
        if self.local:
            tmp = f"{parent}/.{path.rsplit('/', 1)[1]}.{uuid.uuid4().hex[:8]}.tmp"
            with open(tmp, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        else:
            self.fs.pipe_file(path, data)

    def _get(self, key: str) -> bytes:
        return self.fs.cat_file(self.path(key))

    def put_array(self, key: str, arr: np.ndarray) -> None:
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(arr), allow_pickle=False)
        self._put(key, buf.getvalue())

    def get_array(self, key: str, *, mmap: bool = False) -> np.ndarray:
        if mmap and self.local:
            return np.load(self.path(key), mmap_mode="r", allow_pickle=False)
        return np.load(io.BytesIO(self._get(key)), allow_pickle=False)

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

    def foreign(self) -> list[str]:
        """Names in the root folder that the store did not write (a folder that is not a
        work store, or not only one)."""
        return [n for n in self.entries() if not _own(n)]

    def remove(self, prefix: str = "") -> None:
        """Delete a folder of the store; with no ``prefix``, everything the store writes
        (:data:`OWN_ENTRIES`) and then the root folder if that leaves it empty. Files of
        anyone else in the root folder are never touched."""
        if prefix:
            path = self.path(prefix)
            if self.fs.exists(path):
                self.fs.rm(path, recursive=True)
            return
        for name in self.entries():
            if _own(name):
                self.fs.rm(self.path(name), recursive=True)
        if self.fs.exists(self.root) and not self.entries():
            try:
                self.fs.rm(self.root, recursive=True)  # empty: nothing but the folder goes
            except (OSError, ValueError):  # e.g. the working directory itself
                pass


def default_work_dir(out_dir: str) -> str:
    return str(Path(out_dir) / "_work")
