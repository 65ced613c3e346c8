"""Ctrl-C on the command line, kept even where Python would drop it.

Python raises ``KeyboardInterrupt`` wherever the main thread is when the signal arrives.
Inside a callback (the embedded dask scheduler's garbage-collection diagnostics run in
this process) the exception is only printed as "Exception ignored" and lost, and a tiled
run went on to its end. Within :func:`ctrl_c`, a SIGINT also sets an event that a job
watches as its cancel flag, and such a lost interrupt is not printed.

An interrupt that leaves an ``exec`` of source text (dataclasses and namedtuples build
their methods so, at import) makes CPython 3.11 end ``python -m ...`` by killing itself
with SIGINT even where the interrupt was handled; :func:`ctrl_c` clears that mark.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager


@contextmanager
def ctrl_c():
    """Yield an event that a SIGINT sets (and then raises ``KeyboardInterrupt`` as
    Python's own handler does). Outside the main thread, or where SIGINT is not
    Python's own handler (ignored in a shell's background job, or replaced), the event
    is yielded and nothing else changes."""
    interrupted = threading.Event()
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield interrupted
        return

    def on_sigint(signum, frame):
        interrupted.set()
        raise KeyboardInterrupt

    def unraisable(info):
        if isinstance(info.exc_value, KeyboardInterrupt) and interrupted.is_set():
            return  # lost inside a callback: the event carries it
        previous_hook(info)

    previous_hook = sys.unraisablehook
    signal.signal(signal.SIGINT, on_sigint)
    sys.unraisablehook = unraisable
    try:
        yield interrupted
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.unraisablehook = previous_hook
        if interrupted.is_set():
            _forget_unhandled_interrupt()


def _forget_unhandled_interrupt() -> None:
    # CPython marks "unhandled KeyboardInterrupt" when one leaves any exec() of a string,
    # caught or not, and Py_RunMain then exits with SIGINT instead of the status asked
    # for; every exec() of a string clears the mark as it starts.
    exec("")  # noqa: S102
