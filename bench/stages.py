"""Time the pipeline's stages from the outside.

The kernels never time themselves (STYLE.md). To split a run by stage, the names
that the orchestration code calls (`pipeline.process`, `workers.job` and its rooms, and the
modules they call through, such as `pipeline.woodleaf` and `pipeline.reading`) are
temporarily replaced by timing wrappers, keyed by the module the function comes
from. Only the outermost wrapped call is timed, so a kernel calling another kernel
is not counted twice. Whatever is not inside a wrapped call is reported as "other"
(glue code, merging, label assembly).
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import threading
import time
import types
from collections import defaultdict

#: module of a function → stage name
STAGE_OF_MODULE = {
    "pipeline.ground": "ground",
    "pipeline.voxels": "graph",
    "pipeline.graph": "graph",
    "pipeline.enrichment": "graph",
    "pipeline.trunks": "trunks",
    "pipeline.segment": "segmentation",
    "pipeline.woodleaf": "matter",
    "pipeline.metrics": "metrics",
    "pipeline.blockinfo": "IO",
    "pipeline.reading": "IO",
    "pipeline.laswriting": "IO",
    "pipeline.parquet": "IO",
}
#: the order stages are reported in
STAGES = ("IO", "ground", "graph", "trunks", "segmentation", "matter", "metrics", "other")
#: namespaces whose references are wrapped
CALLERS = ("pipeline.process", "pipeline.blockresult", "workers.job", "workers.tasks", "workers.outputs", "workers.replay")
#: functions of the callers that are pure I/O
EXTRA_IO = {("workers.outputs", "write_outputs")}


class StageTimer:
    """Accumulates seconds per stage; ``wrap`` makes a timing wrapper."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self._local = threading.local()

    def wrap(self, fn, stage: str):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            if getattr(self._local, "active", False):
                return fn(*args, **kwargs)
            self._local.active = True
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[stage] += time.perf_counter() - t
                self.calls[stage] += 1
                self._local.active = False

        timed.__bench_wrapped__ = fn
        return timed

    def split(self, total: float) -> dict[str, float]:
        """Seconds per stage in :data:`STAGES` order; "other" = total − timed stages."""
        out = {s: float(self.seconds.get(s, 0.0)) for s in STAGES if s != "other"}
        out["other"] = max(0.0, total - sum(out.values()))
        return out


def _targets(module: types.ModuleType):
    """(owner, attribute, function, stage) for every stage function ``module`` calls."""
    for name, obj in list(vars(module).items()):
        if isinstance(obj, types.ModuleType) and obj.__name__ in STAGE_OF_MODULE:
            stage = STAGE_OF_MODULE[obj.__name__]
            for attr, fn in list(vars(obj).items()):
                if inspect.isfunction(fn) and fn.__module__ == obj.__name__ and not attr.startswith("__"):
                    yield obj, attr, fn, stage
        elif inspect.isfunction(obj):
            stage = STAGE_OF_MODULE.get(obj.__module__)
            if (module.__name__, name) in EXTRA_IO:
                stage = "IO"
            if stage is not None:
                yield module, name, obj, stage


@contextlib.contextmanager
def timed_stages():
    """Context manager: while active, stage functions are timed; yields a StageTimer."""
    import importlib

    timer = StageTimer()
    patched = []
    seen = set()
    try:
        for caller in CALLERS:
            module = importlib.import_module(caller)
            for owner, attr, fn, stage in _targets(module):
                key = (id(owner), attr)
                if key in seen:
                    continue
                seen.add(key)
                patched.append((owner, attr, fn))
                setattr(owner, attr, timer.wrap(fn, stage))
        yield timer
    finally:
        for owner, attr, fn in reversed(patched):
            setattr(owner, attr, fn)
