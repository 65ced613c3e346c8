"""Time per 3-tree stand (single process, one core) with the split by stage."""

from __future__ import annotations

import statistics
from pathlib import Path

from bench.blocks import make_block, stand_density, stand_params
from bench.isolation import measure

#: the paper's average runtime for a 3-tree stand (matter classification, "49s against 1752s")
PAPER_STAND_SECONDS = 49.0


def run_stand(work: Path, *, min_points: int, repeats: int, log=print) -> dict:
    """LAZ in → Parquet out on a generated 3-tree stand of >= ``min_points`` points."""
    from simulator.scoring.result import evaluate_result

    density = stand_density(min_points)
    block = make_block(work, "stand", stand_params(density))
    log(f"  stand: {block.n_points:,} points, {block.n_trees} trees (density {density})")
    out = work / "out" / "stand"
    r = measure({"kind": "job", "input": block.las, "out": str(out), "workers": 0, "one_core": True,
                 "stages": True, "repeats": repeats, "warmup": 1})
    walls = [run["wall_s"] for run in r["runs"]]
    median = statistics.median(walls)
    best_run = min(r["runs"], key=lambda run: abs(run["wall_s"] - median))
    accuracy = evaluate_result(block.truth, str(out / f"run{repeats - 1}"))
    decode = measure({"kind": "decode", "input": block.las, "repeats": 3})
    return {
        "block": block.__dict__,
        "density": density,
        "walls": walls,
        "median_s": median,
        "points_per_s": block.n_points / median,
        "cpu_s": best_run.get("cpu_s"),
        "stages": best_run["stages"],
        "job_timings": best_run["timings"],
        "n_trees_found": best_run["n_trees"],
        "accuracy": accuracy,
        "peak_rss": r["main_maxrss"],
        "decode": decode,
        "paper_s": PAPER_STAND_SECONDS,
    }
