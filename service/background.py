"""The service's background threads (the job runner, the schedule clock, the webhook
sender) share one shape: a daemon thread that sleeps until it is woken or its time
comes, and stops when told; `Background` holds that shape once."""

from __future__ import annotations

import threading


class Background(threading.Thread):
    """A daemon thread with ``wake()`` (look again now) and ``stop()`` (finish and join).

    Subclasses wait on ``self._wake`` in their loop and leave it once ``self._stopping``
    is set."""

    def __init__(self, name: str) -> None:
        super().__init__(name=name, daemon=True)
        self._stopping = threading.Event()
        self._wake = threading.Event()

    def wake(self) -> None:
        """Look again now (a job was queued, a schedule changed, an event was queued)."""
        self._wake.set()

    def stop(self, timeout: float | None = 10.0) -> None:
        """Ask the thread to finish, and wait for it up to ``timeout`` seconds."""
        self._stopping.set()
        self._wake.set()
        self._before_join()
        if self.is_alive():
            self.join(timeout)

    def _before_join(self) -> None:
        """What a subclass does between being told to stop and being waited for."""
