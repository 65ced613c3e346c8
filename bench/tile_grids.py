"""``python -m bench.tile_grids BLOCK [--worker-memory 2] [--workers 1,2,3,4]``: the tile
grids a memory budget weighs for a block, and the one it takes for each number of workers.

Counts every point of the block (:func:`pipeline.reading.sample_density`, as a job's
workers do), then prints, for each whole-metre core from the budget's largest down to the
least that gives as many tiles along each axis (:func:`pipeline.budget.balanced_tile_size`'s
candidates): its tiles, their estimated buffered points in all and in the fullest, the
:func:`pipeline.budget.makespan` on each number of workers, and whether every tile keeps
the budget; then the core :func:`pipeline.budget.job_tile_size` takes for each, and the
core whose fullest tile holds the fewest points (the rule before the makespan). Prints
Markdown.
"""

from __future__ import annotations

import argparse
import math

from pipeline.blockinfo import read_info
from pipeline.budget import job_tile_size, makespan, sampled_tile_bytes, sampled_tile_points, smallest_tile, tile_size_for_sample
from pipeline.jobparams import JobParams
from pipeline.reading import sample_density
from workers.jobspec import grid_origin


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.tile_grids", description=__doc__.split("\n\n")[0])
    p.add_argument("block")
    p.add_argument("--worker-memory", type=float, default=2.0, help="memory budget of a worker [GB] (the service's default 2)")
    p.add_argument("--workers", default="1,2,3,4", help="numbers of workers, comma-separated")
    args = p.parse_args(argv)
    workers = [int(w) for w in args.workers.split(",")]
    info, job = read_info(args.block), JobParams()
    sample = sample_density(info.path, info=info, voxel_size=job.pipeline.graph.voxel_size)
    where = dict(budget=args.worker_memory * 1e9, buffer=job.buffer(), grid_origin=grid_origin(job.tiling, info))
    largest = tile_size_for_sample(sample, info.mins, info.maxs, **where)
    print(f"{info.path}: {info.n_points:,} points, budget {args.worker_memory:g} GB, buffer {where['buffer']:g} m, "
          f"largest core {largest} m\n")
    if largest is None:
        return 0

    def points(s):
        return sampled_tile_points(sample, float(s), where["buffer"], info.mins, info.maxs, where["grid_origin"])

    shape = points(largest).shape
    least = max(smallest_tile(where["buffer"]),
                *(math.floor((float(info.maxs[d]) - float(info.mins[d])) / shape[1 - d]) for d in range(2)))
    print("| core [m] | tiles | buffered points [M] | fullest [M] | "
          + " | ".join(f"makespan, {w} worker(s) [M]" for w in workers) + " | keeps the budget |")
    print("|---:|---:|---:|---:|" + "---:|" * len(workers) + "---|")
    fewest = None
    for s in range(int(largest), int(least) - 1, -1):
        tiles = points(s)
        if tiles.shape != shape:
            continue
        keeps = bool(sampled_tile_bytes(sample, float(s), where["buffer"], info.mins, info.maxs, where["grid_origin"]).max()
                     <= where["budget"])
        if keeps and (fewest is None or tiles.max() < fewest[1]):
            fewest = (s, float(tiles.max()))
        print(f"| {s} | {tiles.shape[1]} × {tiles.shape[0]} | {tiles.sum() / 1e6:.2f} | {tiles.max() / 1e6:.2f} | "
              + " | ".join(f"{makespan(tiles, w) / 1e6:.2f}" for w in workers) + f" | {'yes' if keeps else 'no'} |")
    print()
    for w in workers:
        size = job_tile_size(sample, info.mins, info.maxs, **where, n_workers=w)
        tiles = " ".join(f"{v / 1e6:.2f}" for v in sorted(points(size).ravel(), reverse=True))
        print(f"- {w} worker(s): {size:g} m; buffered points of its tiles [M]: {tiles}")
    print(f"- the fullest tile the least (the rule before): {fewest[0]} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
