"""Peak resident memory of a process tree, sampled from the outside.

`TreeSampler` polls a root process and all its descendants (dask workers included)
in a background thread with psutil and keeps, per process, the largest RSS seen and,
for the tree, the largest sum of RSS at one instant. Sampling can miss a short peak
between two samples; the measured processes also report their own exact high-water
mark (``resource.getrusage``), which the results prefer where available.
"""

from __future__ import annotations

import threading
import time

import psutil


def _label(proc: psutil.Process, root_pid: int) -> str:
    try:
        cmd = " ".join(proc.cmdline())
    except (psutil.Error, OSError):
        cmd = ""
    if proc.pid == root_pid:
        return "main"
    if "resource_tracker" in cmd:
        return "resource-tracker"
    if "spawn_main" in cmd or "forkserver" in cmd or "dask worker" in cmd or "distributed" in cmd:
        return "dask-worker"
    return cmd.split(" ")[0].rsplit("/", 1)[-1] or "process"


class TreeSampler:
    """Sample the RSS of ``pid`` and its descendants every ``interval`` seconds."""

    def __init__(self, pid: int, interval: float = 0.1):
        self.pid = pid
        self.interval = interval
        self.peaks: dict[int, tuple[str, int]] = {}
        self.peak_total = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)

    def _sample(self) -> None:
        try:
            root = psutil.Process(self.pid)
            procs = [root] + root.children(recursive=True)
        except psutil.Error:
            return
        total = 0
        for p in procs:
            try:
                rss = p.memory_info().rss
            except psutil.Error:
                continue
            total += rss
            label, best = self.peaks.get(p.pid, (None, 0))
            if label is None:
                label = _label(p, self.pid)
            self.peaks[p.pid] = (label, max(best, rss))
        self.peak_total = max(self.peak_total, total)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
            self._stop.wait(self.interval)

    def __enter__(self) -> "TreeSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def by_label(self) -> dict[str, list[int]]:
        """Peak RSS [bytes] of every sampled process, grouped by role label."""
        out: dict[str, list[int]] = {}
        for label, peak in self.peaks.values():
            out.setdefault(label, []).append(peak)
        return {k: sorted(v, reverse=True) for k, v in out.items()}


def wait_sampled(proc, sampler: TreeSampler, timeout: float) -> int:
    """Wait for a Popen ``proc`` while ``sampler`` runs; kill it after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while proc.poll() is None:
        if time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            raise TimeoutError(f"measurement took longer than {timeout:.0f} s")
        time.sleep(0.05)
    return proc.returncode
