"""Run one :mod:`bench.measure` measurement in a fresh process, sampling its memory."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager

from bench.memory import TreeSampler, wait_sampled

#: one thread per process for the numeric libraries: "one core" means one core
SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
}


def pin_one_core() -> int:
    """Pin this process to the lowest-numbered core it may run on; returns that core."""
    core = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})
    return core


@contextmanager
def one_core() -> Iterator[int]:
    """Run the body on one core (:func:`pin_one_core`), then restore the affinity. SINGLE_THREAD_ENV caps the numeric libraries at one thread, but the LAZ
    decoder (lazrs, rayon threads) and pyarrow's writer still spread over every core they
    may use: a time said to be on one core is only that when the process is pinned."""
    before = os.sched_getaffinity(0)
    try:
        yield pin_one_core()
    finally:
        os.sched_setaffinity(0, before)


def pinned_to(core: int):
    """A ``preexec_fn`` for :mod:`subprocess` that pins the child to ``core``."""
    return lambda: os.sched_setaffinity(0, {core})


def measure(cfg: dict, *, timeout: float = 3600.0) -> dict:
    """Run ``python -m bench.measure cfg`` and return its result plus sampled peak RSS."""
    env = dict(os.environ, **SINGLE_THREAD_ENV)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [os.path.dirname(os.path.dirname(os.path.abspath(__file__))), env.get("PYTHONPATH")]))
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen([sys.executable, "-m", "bench.measure", json.dumps(cfg)], stdout=out, stderr=err, env=env)
        with TreeSampler(proc.pid, interval=0.1) as sampler:
            code = wait_sampled(proc, sampler, timeout)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    lines = [ln for ln in stdout.splitlines() if ln.startswith("BENCH-RESULT ")]
    if code != 0 or not lines:
        tail = "\n".join(stderr.strip().splitlines()[-8:])
        raise RuntimeError(f"measurement {cfg.get('kind')} failed (exit {code}):\n{tail}")
    result = json.loads(lines[-1][len("BENCH-RESULT "):])
    result["sampled_peak_total"] = sampler.peak_total
    result["load_before"] = load_before
    result["load_after"] = os.getloadavg()[0]
    result["sampled_peaks"] = sampler.by_label()
    return result
