"""The memory budget against the memory the workers really take.

    python -m bench.budget BLOCK.laz [BLOCK.laz ...] [--worker-memory GB]
    python -m bench.budget BLOCK.laz --tile-size M --per-tile

The first form runs each block as ``orchard process`` does (tiles chosen for the
budget, 2 embedded dask workers) and prints one JSON line per block: the tile size
chosen and how long choosing took, the tiles, the budget's estimate for the grid's
largest tile, the peak resident memory (VmHWM) of every worker and of the submitting
process, and the job's wall time.

The second (the calibration of :mod:`pipeline.budget`) runs the block in tiles of the
given size on one worker, resets the worker's VmHWM before each task, and prints one
JSON line per tile: its buffered points and occupied voxels (counted from the points on
the job's grid), the worker's resident memory when the tile began and its peak during
it; then one line with the peak of each kind of task (tiler ranges, ground, tiles).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time

import numpy as np
from distributed.diagnostics.plugin import WorkerPlugin

from bench.measure import _maxrss_bytes
from pipeline.blockinfo import read_info
from pipeline.budget import sampled_tile_bytes
from pipeline.jobparams import JobParams, TilingParams
from pipeline.params import PipelineParams
from pipeline.reading import read_points, sample_density
from workers.cluster import close_client, make_client
from workers.job import run_job
from workers.jobspec import JobSpec, auto_tiled, grid_origin, plan_tiles
from workers.runoptions import RunOptions


def _status(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field):
                return int(line.split()[1]) * 1024
    return 0


class TaskPeaks(WorkerPlugin):
    """On a worker: VmHWM reset as each task starts; the resident memory then and the
    peak when it ends, per task key."""

    name = "task-peaks"

    def setup(self, worker):
        self.peaks = {}
        self.start = {}

    def transition(self, key, start, finish, **kwargs):
        if finish == "executing":
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # resets VmHWM to the current resident memory
            self.start[str(key)] = _status("VmRSS")
        if start == "executing":
            self.peaks[str(key)] = (self.start.get(str(key), 0), _status("VmHWM"))


def default_budget(path: str, gb: float) -> dict:
    spec = JobSpec(path, tempfile.mkdtemp(prefix="budget-"), job=JobParams(pipeline=PipelineParams()), run=RunOptions(worker_memory=gb))
    counted = []  # the sample auto_tiled counts, kept for the estimate below

    def count(info, voxel_size):
        counted.append(sample_density(info.path, info=info, voxel_size=voxel_size))
        return counted[-1]

    t = time.perf_counter()
    chosen = auto_tiled(spec, count=count)
    t_choose = time.perf_counter() - t
    out = {"block": path, "budget_gb": gb, "tile_size": chosen.tiling.tile_size, "choose_s": round(t_choose, 2)}
    if chosen.tiling.tile_size is not None:
        info = read_info(path)
        buffer = chosen.job.buffer()
        est = sampled_tile_bytes(counted[0], chosen.tiling.tile_size, buffer, info.mins, info.maxs,
                                 grid_origin(chosen.tiling, info))
        out["estimate_largest_tile"] = float(est.max())
    client = make_client(None, n_workers=2, quiet=True)
    try:
        t = time.perf_counter()
        outcome = run_job(chosen, client=client)
        out["wall_s"] = round(time.perf_counter() - t, 1)
        out["worker_peaks"] = sorted(client.run(_maxrss_bytes).values(), reverse=True)
    finally:
        close_client(client)
    out.update(n_points=outcome.n_points, n_tiles=outcome.n_tiles, n_trees=outcome.n_trees, main_peak=_maxrss_bytes())
    return out


def per_tile(path: str, tile_size: float, voxel_size: float = 0.1) -> list[dict]:
    spec = JobSpec(path, tempfile.mkdtemp(prefix="budget-"), job=JobParams(pipeline=PipelineParams(), tiling=TilingParams(tile_size=tile_size)))
    xyz, info = read_points(path)
    grid = plan_tiles(spec.job, info)
    stats = {}
    absolute = xyz[:, :2] + np.asarray(info.origin[:2])
    for t in grid.tiles():
        x0, y0, x1, y1 = t.buffered
        inside = (absolute[:, 0] > x0) & (absolute[:, 0] < x1) & (absolute[:, 1] > y0) & (absolute[:, 1] < y1)
        if inside.any():
            keys = np.unique(np.floor(xyz[inside] / voxel_size).astype(np.int64), axis=0)
            stats[t.id] = (int(inside.sum()), len(keys))
    del xyz, absolute
    client = make_client(None, n_workers=1, quiet=True)
    try:
        client.register_plugin(TaskPeaks())
        run_job(spec, client=client)
        peaks = client.run(lambda dask_worker: dask_worker.plugins[TaskPeaks.name].peaks)
    finally:
        close_client(client)
    rows, kinds = {}, {}
    for by_key in peaks.values():
        for key, (rss0, hwm) in by_key.items():
            kind = "-".join(key.split("-")[:2])
            kinds[kind] = max(kinds.get(kind, 0), hwm)
            if key.startswith("orchard-tile-"):
                tid = int(key.split("-")[2])
                rows[tid] = max(rows.get(tid, (0, 0)), (hwm, rss0))
    out = [{"block": path, "tile": tid, "points": stats.get(tid, (0, 0))[0], "voxels": stats.get(tid, (0, 0))[1],
            "rss_before": rss0, "peak": hwm} for tid, (hwm, rss0) in sorted(rows.items())]
    out.append({"block": path, "task_peaks": kinds})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.budget", description=__doc__.split("\n\n")[0])
    ap.add_argument("blocks", nargs="+")
    ap.add_argument("--worker-memory", type=float, default=2.0, help="budget [GB] (default 2)")
    ap.add_argument("--tile-size", type=float, help="with --per-tile: the tile core [m]")
    ap.add_argument("--per-tile", action="store_true", help="one worker, each tile's peak")
    args = ap.parse_args(argv)
    if args.per_tile and args.tile_size is None:
        ap.error("--per-tile needs --tile-size")
    for path in args.blocks:
        lines = per_tile(path, args.tile_size) if args.per_tile else [default_budget(path, args.worker_memory)]
        for line in lines:
            print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
