"""Where the wall time of one ``orchard process`` run goes, start-up and report included.

    python -m bench.cli_stages BLOCK.laz --out DIR [more orchard process options]

Runs the command line in this process with the functions below replaced by timing
wrappers (wall time, inclusive; the kernels never time themselves, STYLE.md) and prints
one Markdown row of :data:`CATEGORIES` [s]. "start-up + imports" runs from this
module's start to the first header read: the interpreter's own start (about 0.05 s) is
not in it. matplotlib is imported when the report draws its map, so its import counts in
"report". Unlike :mod:`bench.stages` (the pipeline's stages inside a job), this covers
the whole command.
"""

from __future__ import annotations

import functools
import importlib
import sys
import time
from collections import defaultdict

T0 = time.perf_counter()

#: module:function pairs timed, as the command's modules call them
TIMED = (
    "pipeline.blockinfo:read_info pipeline.reading:read_points workers.jobspec:read_counted "
    "pipeline.process:ground_model pipeline.process:classify_ground pipeline.process:voxelize "
    "pipeline.process:node_pairs pipeline.process:neighbourhood_matrix pipeline.process:shape_features "
    "pipeline.process:build_graph pipeline.process:bridge_floating pipeline.process:detect_trunks "
    "pipeline.process:find_posts pipeline.process:slot_evidence pipeline.process:trees_on_slots "
    "pipeline.process:let_in pipeline.process:segment_nodes "
    "pipeline.process:analyse_nodes pipeline.process:node_wood_score pipeline.process:trunk_feet "
    "pipeline.process:trunk_circles pipeline.process:block_result workers.tasks:summarise "
    "workers.job:merge_and_write workers.outputs:write_outputs service.report:write_report "
    "service.report:write_trees_csv"
).split()

#: reported categories, in order
CATEGORIES = (
    "start-up + imports", "read", "ground", "voxels", "graph", "trunks and posts", "segmentation",
    "other node work", "wood/leaf", "trunk feet and circles", "label assembly", "metrics and canopy",
    "merge, trees, rows", "Parquet writers", "trees.csv", "report", "rest", "total",
)


def categories(s: dict[str, float], start_up: float, total: float) -> dict[str, float]:
    """Seconds per category from the inclusive seconds ``s`` of each timed function (by
    name), the start-up [s] and the whole run [s]."""
    s = defaultdict(float, s)
    out = {
        "start-up + imports": start_up,
        "read": s["read_points"] + s["read_counted"],  # a block counted for its budget is read with the count
        "ground": s["ground_model"] + s["classify_ground"],
        "voxels": s["voxelize"],
        "graph": s["node_pairs"] + s["neighbourhood_matrix"] + s["shape_features"] + s["build_graph"]
        + s["bridge_floating"],
        "trunks and posts": s["detect_trunks"] + s["find_posts"] + s["slot_evidence"]
        + s["trees_on_slots"] + s["let_in"],
        "segmentation": s["segment_nodes"],
    }
    out["other node work"] = s["analyse_nodes"] - sum(out[k] for k in CATEGORIES[2:7])
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


def _wrap(seconds: dict, first: dict, target: str) -> None:
    module, name = target.split(":")
    owner = importlib.import_module(module)
    fn = getattr(owner, name)

    @functools.wraps(fn)
    def timed(*args, **kwargs):
        t = time.perf_counter()
        first.setdefault(name, t)
        try:
            return fn(*args, **kwargs)
        finally:
            seconds[name] += time.perf_counter() - t

    setattr(owner, name, timed)


def main(argv: list[str] | None = None) -> int:
    seconds, first = defaultdict(float), {}
    import service.cli

    for target in TIMED:
        _wrap(seconds, first, target)
    code = service.cli.main(["process", *(sys.argv[1:] if argv is None else argv)])
    total = time.perf_counter() - T0
    row = categories(seconds, first.get("read_info", T0) - T0, total)
    print("| " + " | ".join(CATEGORIES) + " |\n|" + "---:|" * len(CATEGORIES), file=sys.stderr)
    print("| " + " | ".join(f"{row[k]:.2f}" for k in CATEGORIES) + " |", file=sys.stderr)
    return code or 0


if __name__ == "__main__":
    sys.exit(main())
