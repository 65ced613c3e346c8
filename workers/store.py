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

    def remove(self, prefix: str = "") -> None:
        """Delete a folder of the store (the whole store when ``prefix`` is empty)."""
        path = self.path(prefix) if prefix else self.root
        if self.fs.exists(path):
            self.fs.rm(path, recursive=True)


def default_work_dir(out_dir: str) -> str:
    return str(Path(out_dir) / "_work")
