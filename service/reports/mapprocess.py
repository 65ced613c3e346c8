"""The report's map drawn by a process forked when a run starts, ready when the run ends.

matplotlib's import (about 0.4 s) and the map's drawing (about 0.3 s) came after the
pipeline in ``orchard process``, a fifth of a run on a block of a million points. A
:class:`MapProcess` forks as the run starts (numpy loaded, shared with the child); the
child imports matplotlib on the other core while the parent reads and processes the
block, then draws the map while the parent builds the report's data: the same function
(:func:`service.reports.mapimage.render_map_png`) on the same arrays, so the same bytes.

Only a process with a single Python thread forks (a thread holding a lock at the fork
would hold it in the child forever), and only on Linux. Anywhere else, and whenever the
child fails, the map is drawn in this process as before.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys
import threading
from collections.abc import Callable


class MapProcess:
    """A child process that draws one map (:func:`start` forks it; None fields: none).

    ``draw(...)`` takes :func:`service.reports.mapimage.render_map_png`'s arguments and
    returns a function that returns the PNG; :meth:`close` ends the child, used or not.
    """

    def __init__(self, pid: int | None = None, to_child=None, from_child=None):
        self.pid, self._to, self._from = pid, to_child, from_child

    @classmethod
    def start(cls) -> MapProcess:
        """Fork the child; a `MapProcess` that draws in this process where it cannot."""
        if not sys.platform.startswith("linux") or threading.active_count() != 1:
            return cls()
        try:
            down_r, down_w = os.pipe()
            up_r, up_w = os.pipe()
        except OSError:
            return cls()
        try:
            pid = os.fork()
        except OSError:
            for fd in (down_r, down_w, up_r, up_w):
                os.close(fd)
            return cls()
        if pid == 0:  # the child: never returns
            os.close(down_w)
            os.close(up_r)
            _serve(down_r, up_w)
        os.close(down_r)
        os.close(up_w)
        return cls(pid, os.fdopen(down_w, "wb"), os.fdopen(up_r, "rb"))

    def draw(self, *args, **kwargs) -> Callable[[], bytes]:
        """Send the map's arguments to the child; the returned function waits for its PNG
        (drawn here if the child fails)."""
        from service.reports.mapimage import render_map_png

        if self.pid is None:
            png = render_map_png(*args, **kwargs)
            return lambda: png
        try:
            pickle.dump((args, kwargs), self._to, protocol=pickle.HIGHEST_PROTOCOL)
            self._to.close()  # the whole request: the child reads to its end
        except OSError:  # the child is gone (BrokenPipeError)
            self.close()
            png = render_map_png(*args, **kwargs)
            return lambda: png

        def result() -> bytes:
            try:
                ok, png = pickle.load(self._from)
            except (OSError, EOFError, pickle.UnpicklingError):
                ok, png = False, None
            finally:
                self.close()
            return png if ok else render_map_png(*args, **kwargs)

        return result

    def close(self) -> None:
        """End the child (at once if it has not answered) and reap it."""
        if self.pid is None:
            return
        pid, self.pid = self.pid, None
        for f in (self._to, self._from):
            try:
                f.close()
            except OSError:
                pass
        try:
            os.kill(pid, signal.SIGKILL)  # not waited for when unused (a run that failed)
        except OSError:
            pass
        try:
            os.waitpid(pid, 0)
        except ChildProcessError:
            pass


def _serve(down: int, up: int) -> None:
    """The child: import matplotlib, draw the one map asked for, exit."""
    code = 1
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's; it ends the child
        import matplotlib.backends.backend_agg  # noqa: F401 - what the map needs, loaded before it is asked for
        import matplotlib.figure  # noqa: F401

        from service.reports.mapimage import render_map_png

        with os.fdopen(down, "rb") as inp, os.fdopen(up, "wb") as out:
            try:
                args, kwargs = pickle.load(inp)
            except EOFError:  # the run ended without a map
                code = 0
                return
            try:
                answer = (True, render_map_png(*args, **kwargs))
            except Exception:  # noqa: BLE001 - the parent draws it again and says what is wrong
                answer = (False, None)
            pickle.dump(answer, out, protocol=pickle.HIGHEST_PROTOCOL)
        code = 0
    except BaseException:  # noqa: BLE001 - nothing of the child may reach the parent's code
        pass
    finally:
        os._exit(code)
