"""Where the wall time of one ``orchard process`` run goes, start-up and report included.

    python -m bench.cli_stages BLOCK.laz --out DIR [more orchard process options]

Runs the command line in this process with the functions below replaced by timing
wrappers (wall time, inclusive; the kernels never time themselves, STYLE.md) and prints
one Markdown row of :data:`CATEGORIES` [s].

- "start-up + imports" runs from the process's start (the kernel's start time of this
  process, so the interpreter's own start is in it) to the first header read, the
  command's own imports included. Each function is wrapped when the command first
  imports its module, so nothing is imported earlier than the command imports it.
- "imports after start-up" is every import the command makes after that (the job's
  scipy, pyarrow, the report's matplotlib); the stages' seconds leave it out.

Unlike :mod:`bench.stages` (the pipeline's stages inside a job), this covers the whole
command.
"""

from __future__ import annotations

import functools
import importlib._bootstrap as _bootstrap
import importlib.abc
import os
import sys
import time
from collections import defaultdict


def _process_age() -> float:
    """Seconds since this process started (its start time in /proc, 10 ms ticks); 0
    where there is no /proc."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, AttributeError, IndexError):
        return 0.0


T0 = time.perf_counter() - _process_age()

#: module:function pairs timed, as the command's modules call them
TIMED = (
    "pipeline.blockinfo:read_info pipeline.reading:read_points workers.jobspec:read_counted "
    "pipeline.process:ground_model pipeline.process:classify_ground pipeline.process:voxelize "
    "pipeline.process:node_pairs pipeline.process:neighbourhood_matrix pipeline.process:shape_features "
    "pipeline.process:build_graph pipeline.process:bridge_floating pipeline.process:detect_trunks "
    "pipeline.process:find_posts pipeline.process:slot_evidence pipeline.process:trees_on_slots "
    "pipeline.process:let_in pipeline.process:segment_nodes "
    "pipeline.process:analyse_nodes pipeline.blockresult:node_wood_score pipeline.blockresult:trunk_feet "
    "pipeline.blockresult:trunk_circles pipeline.blockresult:block_result workers.tasks:summarise "
    "workers.job:merge_and_write workers.outputs:write_outputs service.reports.report:write_report "
    "service.reports.report:write_trees_csv"
).split()

#: reported categories, in order
CATEGORIES = (
    "start-up + imports", "imports after start-up", "read", "ground", "voxels", "graph", "trunks and posts", "segmentation",
    "other node work", "wood/leaf", "trunk feet and circles", "label assembly", "metrics and canopy",
    "merge, trees, rows", "Parquet writers", "trees.csv", "report", "rest", "total",
)


def categories(s: dict[str, float], start_up: float, total: float, later_imports: float = 0.0) -> dict[str, float]:
    """Seconds per category from the inclusive seconds ``s`` of each timed function (by
    name, their imports left out), the start-up [s], the imports after it [s] and the
    whole run [s]."""
    s = defaultdict(float, s)
    out = {
        "start-up + imports": start_up,
        "imports after start-up": later_imports,
        "read": s["read_points"] + s["read_counted"],  # a block counted for its budget is read with the count
        "ground": s["ground_model"] + s["classify_ground"],
        "voxels": s["voxelize"],
        "graph": s["node_pairs"] + s["neighbourhood_matrix"] + s["shape_features"] + s["build_graph"]
        + s["bridge_floating"],
        "trunks and posts": s["detect_trunks"] + s["find_posts"] + s["slot_evidence"]
        + s["trees_on_slots"] + s["let_in"],
        "segmentation": s["segment_nodes"],
    }
    out["other node work"] = s["analyse_nodes"] - sum(out[k] for k in ("ground", "voxels", "graph", "trunks and posts", "segmentation"))
    out["wood/leaf"] = s["node_wood_score"]
    out["trunk feet and circles"] = s["trunk_feet"] + s["trunk_circles"]
    out["label assembly"] = s["block_result"] - s["node_wood_score"] - out["trunk feet and circles"]
    out["metrics and canopy"] = s["summarise"]
    out["merge, trees, rows"] = s["merge_and_write"] - s["write_outputs"]
    out["Parquet writers"] = s["write_outputs"]
    out["trees.csv"] = s["write_trees_csv"]
    out["report"] = s["write_report"]
    out["rest"] = total - sum(out.values())
    out["total"] = total
    return out


class _Imports:
    """Seconds spent in imports (the outermost ``import`` statements), counted from the
    first header read on; ``since(mark)`` gives those since an earlier ``mark()``."""

    def __init__(self) -> None:
        self.seconds, self.depth, self.counting = 0.0, 0, False
        self._find_and_load = _bootstrap._find_and_load

    def __enter__(self):
        def timed_import(name, import_):
            self.depth += 1
            t = time.perf_counter()
            try:
                return self._find_and_load(name, import_)
            finally:
                self.depth -= 1
                if self.depth == 0 and self.counting:
                    self.seconds += time.perf_counter() - t

        _bootstrap._find_and_load = timed_import  # what every import statement calls
        return self

    def __exit__(self, *exc) -> None:
        _bootstrap._find_and_load = self._find_and_load


def _wrap(seconds: dict, first: dict, imports: _Imports, owner, name: str) -> None:
    fn = getattr(owner, name)

    @functools.wraps(fn)
    def timed(*args, **kwargs):
        t = time.perf_counter()
        if not first:
            imports.counting = True  # start-up ends at the first header read
        first.setdefault(name, t)
        i0 = imports.seconds
        try:
            return fn(*args, **kwargs)
        finally:
            seconds[name] += time.perf_counter() - t - (imports.seconds - i0)

    setattr(owner, name, timed)


class _WrapOnImport(importlib.abc.MetaPathFinder):
    """Wraps a module's timed functions once the command imports it, as it runs."""

    def __init__(self, names: dict[str, list[str]], wrap) -> None:
        self.names, self.wrap = names, wrap

    def find_spec(self, fullname, path, target=None):
        if fullname not in self.names:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                break
        else:
            return None
        exec_module = spec.loader.exec_module

        def exec_and_wrap(module):
            exec_module(module)
            for name in self.names[fullname]:
                self.wrap(module, name)

        spec.loader.exec_module = exec_and_wrap  # this spec's own loader
        return spec


def main(argv: list[str] | None = None) -> int:
    seconds, first = defaultdict(float), {}
    names = defaultdict(list)
    for target in TIMED:
        module, name = target.split(":")
        names[module].append(name)
    with _Imports() as imports:
        wrap = functools.partial(_wrap, seconds, first, imports)
        for module in [m for m in names if m in sys.modules]:  # none but what this module needs
            for name in names.pop(module):
                wrap(sys.modules[module], name)
        finder = _WrapOnImport(names, wrap)
        sys.meta_path.insert(0, finder)
        try:
            import service.cli

            code = service.cli.main(["process", *(sys.argv[1:] if argv is None else argv)])
        finally:
            sys.meta_path.remove(finder)
    total = time.perf_counter() - T0
    start_up = min(first.values(), default=time.perf_counter()) - T0
    row = categories(seconds, start_up, total, imports.seconds)
    print("| " + " | ".join(CATEGORIES) + " |\n|" + "---:|" * len(CATEGORIES), file=sys.stderr)
    print("| " + " | ".join(f"{row[k]:.2f}" for k in CATEGORIES) + " |", file=sys.stderr)
    return code or 0


if __name__ == "__main__":
    sys.exit(main())
