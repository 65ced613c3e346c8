"""Throughput and peak memory against block size, and 1 versus 2 workers.

Every size runs tiled on a fresh ``LocalCluster`` (single-threaded worker processes),
LAZ in → Parquet out, in a fresh process. Peak RSS is each process's own high-water
mark (``getrusage``), plus the largest sum over the process tree sampled every 0.1 s.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bench.blocks import make_block, orchard_params
from bench.isolation import measure


def fit_exponent(points, seconds) -> float:
    """Slope of log(time) against log(points), least squares (time ∝ points^slope)."""
    if len(points) < 2:
        return float("nan")
    slope, _ = np.polyfit(np.log(np.asarray(points, float)), np.log(np.asarray(seconds, float)), 1)
    return float(slope)


def _tiled_run(las: str, out: Path, *, workers: int, tile_size: float) -> tuple[dict, dict]:
    """One tiled job on a fresh cluster of ``workers``: (the measurement, its run)."""
    r = measure({"kind": "job", "input": las, "out": str(out), "workers": workers, "tile_size": tile_size, "repeats": 1},
                timeout=6 * 3600)
    return r, r["runs"][0]


def run_sizes(work: Path, targets: list[int], *, density: float, points_per_tree: float, tile_size: float,
              workers: int, log=print) -> dict:
    rows = []
    for target in targets:
        block = make_block(work, f"size-{target // 1_000_000}M", orchard_params(target, density, points_per_tree))
        log(f"  size ~{target / 1e6:g} M: {block.n_points:,} points, {block.n_trees} trees; tiled, {workers} workers")
        r, run = _tiled_run(block.las, work / "out" / f"size-{target}", workers=workers, tile_size=tile_size)
        d = measure({"kind": "decode", "input": block.las, "repeats": 1 if block.n_points > 20e6 else 3}, timeout=3600)
        rows.append({
            "target": target, "n_points": block.n_points, "n_trees": block.n_trees, "n_found": run["n_trees"],
            "n_tiles": run["n_tiles"], "wall_s": run["wall_s"], "cpu_s": run.get("cpu_s"), "timings": run["timings"],
            "points_per_s": block.n_points / run["wall_s"],
            "main_maxrss": r["main_maxrss"], "worker_maxrss": r.get("worker_maxrss", []),
            "tree_peak_total": r["sampled_peak_total"],
            "decode": d, "ratio_vs_decode": (block.n_points / run["wall_s"]) / d["laspy_xyz_only"]["points_per_s"],
            "block": block.__dict__,
        })
        log(f"    {run['wall_s']:.1f} s, {block.n_points / run['wall_s'] / 1e6:.2f} M points/s, "
            f"worker peak {max(r.get('worker_maxrss', [0])) / 2**30:.2f} GiB")
    exponent = fit_exponent([r["n_points"] for r in rows], [r["wall_s"] for r in rows])
    return {"rows": rows, "exponent": exponent, "tile_size": tile_size, "workers": workers}


def run_tile_sizes(work: Path, block, *, tile_sizes: list[float], workers: int, buffer: float, log=print) -> dict:
    """The same block tiled at each tile size, on ``workers`` single-threaded workers.

    Every tile is processed with its buffer (``buffer`` [m] on each side): an interior
    tile of size s reads ((s + 2 buffer) / s)^2 times the points of its core.
    """
    rows = []
    for size in tile_sizes:
        r, run = _tiled_run(block.las, work / "out" / f"tiles-{size:g}", workers=workers, tile_size=size)
        rows.append({"tile_size": size, "buffer_factor": ((size + 2 * buffer) / size) ** 2, "wall_s": run["wall_s"],
                     "cpu_s": run.get("cpu_s"), "timings": run["timings"], "n_tiles": run["n_tiles"],
                     "n_found": run["n_trees"], "points_per_s": block.n_points / run["wall_s"],
                     "worker_maxrss": r.get("worker_maxrss", [])})
        log(f"  {size:g} m tiles: {run['wall_s']:.1f} s ({run['n_tiles']} tiles), "
            f"worker peak {max(r.get('worker_maxrss', [0])) / 2**30:.2f} GiB")
    return {"rows": rows, "block": block.__dict__, "workers": workers, "buffer": buffer}


def run_workers(work: Path, block, *, tile_size: float, counts=(1, 2), log=print) -> dict:
    """The same tiled block on 1 and 2 workers."""
    rows = []
    for n in counts:
        r, run = _tiled_run(block.las, work / "out" / f"workers-{n}", workers=n, tile_size=tile_size)
        rows.append({"workers": n, "wall_s": run["wall_s"], "cpu_s": run.get("cpu_s"), "timings": run["timings"], "n_tiles": run["n_tiles"],
                     "worker_maxrss": r.get("worker_maxrss", []), "main_maxrss": r["main_maxrss"]})
        log(f"  {n} worker(s): {run['wall_s']:.1f} s ({run['n_tiles']} tiles)")
    base = rows[0]["wall_s"]
    for row in rows:
        row["speedup"] = base / row["wall_s"] if row["wall_s"] > 0 else math.nan
    return {"rows": rows, "block": block.__dict__, "tile_size": tile_size}
