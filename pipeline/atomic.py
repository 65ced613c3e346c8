"""Writing a file atomically: under a temporary name in its destination folder, renamed
when complete, so a failed or interrupted run leaves no partial file behind."""

from __future__ import annotations

import os
import uuid
from pathlib import Path


def temp_name(path: Path) -> Path:
    """A hidden, unique name beside ``path`` (same folder, so the rename is atomic)."""
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")


class AtomicWriter:
    """Base of the streaming writers: the file is written under ``self._tmp``
    by ``self._writer`` (opened by ``_open`` if not yet) and renamed by ``close``; ``abort``
    (and an exception inside ``with``) deletes it, leaving nothing behind."""

    _tmp: Path
    _writer = None
    _closed = False

    def close(self) -> None:
        """Finish the file and move it to its final name."""
        if self._closed:
            return
        self._closed = True
        if self._writer is None:
            self._writer = self._open()
        self._writer.close()
        os.replace(self._tmp, self.path)

    def _open(self):  # writers that open lazily (LasBlockWriter) override this
        raise RuntimeError("the writer was never opened")

    def abort(self) -> None:
        """Stop and delete the temporary file; nothing is left behind."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._writer is not None:
                self._writer.close()
        except Exception:
            pass
        self._tmp.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

