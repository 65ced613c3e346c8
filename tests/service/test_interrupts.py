"""Ctrl-C on the command line: an interrupt Python drops inside a callback still stops the run."""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading
import time

import pytest

from service.interrupts import ctrl_c


@pytest.fixture
def python_sigint():
    """Python's own SIGINT handler, whatever the suite was started with."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _interrupt_inside_a_gc_callback() -> None:
    def slow(phase, info):
        if phase == "start":
            time.sleep(0.5)  # the signal arrives here

    gc.callbacks.append(slow)
    try:
        threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT)).start()
        gc.collect()
    finally:
        gc.callbacks.remove(slow)


def test_an_interrupt_lost_in_a_callback_sets_the_event_and_prints_nothing(python_sigint, capsys):
    seen = []
    previous_hook = sys.unraisablehook
    sys.unraisablehook = lambda info: seen.append(info.exc_type)  # what Python would print
    try:
        with ctrl_c() as interrupted:
            _interrupt_inside_a_gc_callback()  # no KeyboardInterrupt comes out of it
            assert interrupted.is_set()
    finally:
        sys.unraisablehook = previous_hook
    assert seen == []  # ctrl_c's hook swallowed it, and handed nothing else on
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_an_interrupt_elsewhere_raises_as_before(python_sigint):
    with ctrl_c() as interrupted:
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
    assert interrupted.is_set()


def test_an_ignored_sigint_stays_ignored():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a shell's background job
    try:
        with ctrl_c() as interrupted:
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert not interrupted.is_set()
    finally:
        signal.signal(signal.SIGINT, previous)
