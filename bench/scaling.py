"""Throughput and peak memory against block size, and 1 versus 2 workers.

Every size runs tiled on a fresh ``LocalCluster`` (single-threaded worker processes),
LAZ in → Parquet out, in a fresh process. The memory of every process of the job is
kept: the submitting process's own high-water mark (VmHWM; the ``LocalCluster`` runs its
scheduler and the workers' nannies in that process's event loop, so there is no
scheduler process of its own), each dask worker process's (VmHWM, through
``client.run``), the sampled peak of every other process of the tree (multiprocessing's
resource tracker), and the largest sum over the tree, all sampled every 0.1 s.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bench.blocks import make_block, orchard_params
from bench.isolation import measure


#: block sizes of the scaling table [points]: the default ones and the one ``large`` adds
SIZES = (1_000_000, 10_000_000, 50_000_000)
LARGE = 100_000_000


def targets(sizes_m: list[float] | None, *, quick: bool, large: bool) -> tuple[list[int], list[str]]:
    """The scaling table's block sizes [points] and notes on the sizes left out.

    ``sizes_m``: sizes asked for [millions of points] (None: :data:`SIZES`, without the
    50 M block when ``quick``); ``large`` adds :data:`LARGE` (never with ``quick``).
    """
    chosen = [int(s * 1_000_000) for s in sizes_m] if sizes_m else list(SIZES)
    notes = []
    if quick and any(t >= 50_000_000 for t in chosen):
        chosen = [t for t in chosen if t < 50_000_000]
    if large and not quick and LARGE not in chosen:
        chosen.append(LARGE)
    if not any(t >= 50_000_000 for t in chosen):
        notes.append("The 50 M point block is only run without --quick." if quick else "No 50 M point block in --sizes.")
    if not any(t >= LARGE for t in chosen):
        notes.append("The 100 M point block is only run with --large, never with --quick (it adds its block's "
                     "generation and several minutes of processing).")
    return sorted(chosen), notes


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
            "tree_peak_total": r["sampled_peak_total"], "sampled_peaks": r.get("sampled_peaks", {}),
            "tile_size": tile_size,
            "decode": d, "ratio_vs_decode": (block.n_points / run["wall_s"]) / d["laspy_xyz_only"]["points_per_s"],
            "block": block.__dict__,
        })
        log(f"    {run['wall_s']:.1f} s ({run.get('cpu_s', float('nan')):.1f} s CPU), "
            f"{block.n_points / run['wall_s'] / 1e6:.2f} M points/s, submitting process {r['main_maxrss'] / 2**30:.2f} GiB, "
            f"workers {' / '.join(f'{w / 2**30:.2f}' for w in r.get('worker_maxrss', []))} GiB, "
            f"all processes {r['sampled_peak_total'] / 2**30:.2f} GiB")
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
