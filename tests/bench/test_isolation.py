"""Pinning helpers of the benchmarks: a time said to be on one core is on one core."""

from __future__ import annotations

import os
import subprocess
import sys

from bench.isolation import one_core, pinned_to


def test_one_core_pins_the_body_and_restores_the_affinity():
    before = os.sched_getaffinity(0)
    with one_core() as core:
        assert os.sched_getaffinity(0) == {core}
        assert core == min(before)
    assert os.sched_getaffinity(0) == before


def test_one_core_restores_the_affinity_after_an_error():
    before = os.sched_getaffinity(0)
    try:
        with one_core():
            raise RuntimeError("boom")
    except RuntimeError:
        pass
    assert os.sched_getaffinity(0) == before


def test_pinned_to_pins_a_child_process():
    core = min(os.sched_getaffinity(0))
    out = subprocess.run([sys.executable, "-c", "import os; print(sorted(os.sched_getaffinity(0)))"],
                         capture_output=True, text=True, check=True, preexec_fn=pinned_to(core))
    assert out.stdout.strip() == f"[{core}]"


def test_pin_one_core_in_a_child_returns_its_core():
    code = "from bench.isolation import pin_one_core; import os; c = pin_one_core(); print(c, sorted(os.sched_getaffinity(0)))"
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root)
    core = min(os.sched_getaffinity(0))
    assert out.stdout.strip() == f"{core} [{core}]"
