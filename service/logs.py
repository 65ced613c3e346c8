"""The service's log: rate-limited warnings, and an optional rotated file.

A flood of one failure (a refused connection each millisecond, ``accept()`` out of file
handles) must not fill the disk: `RateLimit` lets through at most `BURST` records of
one kind (logger and first line of the message) at WARNING or above per `WINDOW_S`
seconds, and then one line saying how many it dropped. With ``log_file`` the log goes
to that file, rotated at ``max_mb`` with ``backups`` old files kept (at most
``(backups + 1) * max_mb`` on disk); without it, to stderr (a supervisor's or
container's log, which rotates it).
"""

from __future__ import annotations

import logging
import logging.handlers
import threading
import time
from pathlib import Path

WINDOW_S = 60.0
BURST = 20
FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class RateLimit(logging.Filter):
    """At most ``burst`` records of a kind at WARNING and above per ``window_s`` seconds."""

    def __init__(self, burst: int = BURST, window_s: float = WINDOW_S, clock=time.monotonic) -> None:
        super().__init__()
        self.burst, self.window_s, self.clock = burst, window_s, clock
        self._lock = threading.Lock()
        self._kinds: dict[tuple[str, str], list] = {}  # kind -> [window start, passed, dropped]

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        kind = (record.name, str(record.msg).split("\n", 1)[0][:120])
        now = self.clock()
        with self._lock:
            seen = self._kinds.get(kind)
            if seen is None or now - seen[0] >= self.window_s:
                dropped = seen[2] if seen else 0
                if len(self._kinds) > 1000:  # many kinds: forget the old windows
                    self._kinds = {k: v for k, v in self._kinds.items() if now - v[0] < self.window_s}
                self._kinds[kind] = [now, 1, 0]
                if dropped:
                    record.msg = f"{record.msg} ({dropped} more like it in the last {self.window_s:g} s were not logged)"
                return True
            if seen[1] < self.burst:
                seen[1] += 1
                return True
            seen[2] += 1
            return False


def configure(level: str = "INFO", *, log_file: Path | None = None, max_mb: float = 10.0, backups: int = 5) -> logging.Handler:
    """Send every logger's records (uvicorn's and asyncio's too) to one rate-limited handler."""
    if log_file is not None:
        Path(log_file).parent.mkdir(parents=True, exist_ok=True)
        handler: logging.Handler = logging.handlers.RotatingFileHandler(
            log_file, maxBytes=int(max_mb * 2**20), backupCount=backups, encoding="utf-8")
    else:
        handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter(FORMAT))
    handler.addFilter(RateLimit())
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
    return handler
