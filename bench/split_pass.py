"""``python -m bench.split_pass BLOCK [--worker-memory 2] [--workers 2] [--work DIR] [--check]``: the
pass over a plain LAS/LAZ block before its first tile, as a budgeted job makes it,
counted and then tiled (before) against split by cell once (:mod:`workers.cellranges`).

Both run in this process on one core, so their CPU seconds compare whatever the load:

- ``count then tile``: :func:`pipeline.reading.sample_density` of every point in runs of
  :data:`pipeline.chunks.CHUNK_POINTS` (the work of :func:`workers.counting.count_block`'s
  tasks), the budget's tile size, then :func:`workers.tiler.tile_block` on that grid
  (one pass, :data:`pipeline.chunks.CHUNK_POINTS` at a time);
- ``split``: :func:`workers.cellranges.split_block` (one decode: the same count, the
  points written once sorted by cell), the same tile size, :func:`workers.cellranges.index_from_cells`.

Prints, per way, CPU and wall seconds, the bytes in the work store after it and the
points written; ``--check`` then gathers every tile from the split and compares it with
the tile the tiler wrote (records equal, in the same order). Prints Markdown.
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
import tracemalloc
from pathlib import Path

import numpy as np

from pipeline.blockinfo import read_info
from pipeline.budget import job_tile_size
from pipeline.chunks import CHUNK_POINTS
from pipeline.jobparams import JobParams
from pipeline.reading import sample_density
from workers.cellranges import gather_tile, index_from_cells, split_block
from workers.jobspec import grid_origin, plan_tiles
from workers.runoptions import WORKERS
from workers.tiler import read_tile, tile_block
from workers.workstore import WorkStore


def _bytes(folder: Path) -> int:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())


def _timed(fn):
    c, w = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c, time.perf_counter() - w


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.split_pass", description=__doc__.split("\n\n")[0])
    p.add_argument("block", type=Path)
    p.add_argument("--worker-memory", type=float, default=2.0, help="memory budget of a worker [GB] (the service's default 2)")
    p.add_argument("--work", type=Path, default=Path("/tmp/orchard-split-pass"))
    p.add_argument("--check", action="store_true", help="compare every gathered tile with the written one")
    p.add_argument("--workers", type=int, default=WORKERS, help="workers the tiles are cut for (the embedded cluster's default)")
    args = p.parse_args(argv)
    info = read_info(args.block)
    job = JobParams()
    voxel = job.pipeline.graph.voxel_size
    origin = grid_origin(job.tiling, info)
    shutil.rmtree(args.work, ignore_errors=True)
    old, new = WorkStore(str(args.work / "old")), WorkStore(str(args.work / "new"))

    def size_of(sample):  # as workers.jobspec.auto_tiled chooses it
        return job_tile_size(sample, info.mins, info.maxs, budget=args.worker_memory * 1e9, buffer=job.buffer(),
                             grid_origin=origin, n_workers=args.workers)

    sample, c_count, w_count = _timed(lambda: sample_density(info.path, info=info, voxel_size=voxel,
                                                             chunk_points=CHUNK_POINTS))
    size = size_of(sample)
    grid = plan_tiles(job.with_tile_size(size) if size else job, info)
    idx_old, c_tile, w_tile = _timed(lambda: tile_block(info, grid, old, chunk_points=CHUNK_POINTS))

    def split():
        sample, cells, parts = split_block(info, origin, new, voxel_size=voxel)
        assert size_of(sample) == size, "the split's count chose another tile size"
        return index_from_cells(info, grid, cells, parts, new)

    idx_new, c_split, w_split = _timed(split)
    buffered = sum(t["n_buffered"] for t in idx_old["tiles"])
    rows = [("count then tile", c_count + c_tile, w_count + w_tile, _bytes(args.work / "old"), buffered),
            ("split by cell", c_split, w_split, _bytes(args.work / "new"), info.n_points)]
    print(f"{args.block.name}: {info.n_points:,} points; tiles of {size or 'one piece'} m, buffer {grid.buffer:g} m, "
          f"{len([t for t in idx_old['tiles'] if t['n_core']])} tiles; load average {os.getloadavg()[0]:.1f}\n")
    print("| before the first tile | CPU [s] | wall [s] | work store [MB] | points written |")
    print("|---|---|---|---|---|")
    for name, cpu, wall, nbytes, points in rows:
        print(f"| {name} | {cpu:.1f} | {wall:.1f} | {nbytes / 1e6:,.0f} | {points:,} |")
    print(f"\n(count {c_count:.1f} s CPU, tile {c_tile:.1f} s CPU)")
    assert [(t["id"], t["n_core"]) for t in idx_new["tiles"]] == [
        (t["id"], t["n_core"]) for t in idx_old["tiles"] if t["n_core"]]
    if args.check:
        tiles = [t["id"] for t in idx_old["tiles"]]
        gathered, c_gather, w_gather = _timed(lambda: [gather_tile(new, idx_new, t) for t in tiles])
        written, c_read, w_read = _timed(lambda: [read_tile(old, t) for t in tiles])
        for t, a, b in zip(tiles, gathered, written):
            np.testing.assert_array_equal(a, b, err_msg=f"tile {t}")
        del gathered, written
        largest = max(idx_old["tiles"], key=lambda t: t["n_buffered"])
        peaks = []
        for read in (lambda: gather_tile(new, idx_new, largest["id"]), lambda: read_tile(old, largest["id"])):
            tracemalloc.start()
            read()
            peaks.append(tracemalloc.get_traced_memory()[1])
            tracemalloc.stop()
        print(f"\nevery tile gathered from the split equals the tile written ({len(tiles)} tiles). Reading them "
              f"all once: gathered {c_gather:.1f} s CPU ({w_gather:.1f} s wall), written tiles {c_read:.1f} s CPU "
              f"({w_read:.1f} s wall); the largest ({largest['n_buffered']:,} points) allocates at most "
              f"{peaks[0] / 2**20:,.0f} MiB gathered, {peaks[1] / 2**20:,.0f} MiB read (tracemalloc)")
    shutil.rmtree(args.work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
