"""``python -m bench.task_timeline BLOCK.laz``: where the wall time of a tiled job on a
cluster goes, task by task.

    python -m bench.task_timeline BLOCK.laz [--workers 2] [--worker-memory 2] [--work-dir DIR]

Runs the job the service runs on a block (``workers.job.run_job`` with a cluster and
the memory budget per worker, tiles chosen by it) on an embedded cluster made as the
service makes it (``workers.cluster.make_client``: worker processes, one thread each),
and prints Markdown: every task (dask's task stream: its start and end from the job's
start, its worker), each worker's idle time between its first task and the job's end
and inside each stage (split, ground, tiles, merge), the thread CPU seconds of each kind
of task (dask's fine performance metrics: ``thread-cpu`` of ``execute``, and beside it
``thread-noncpu``, the time the task's thread waited: for a core, for I/O), the tile
tasks that ran a second time (:func:`workers.dispatch.settle_slot_trees`) and the job's
phase timings. Wall figures move with the machine's load; the CPU seconds less so.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

#: the job's stages, by the prefix of their dask keys
STAGES = {"split-range": "split", "split-all": "split", "tile-range": "split", "tile-all": "split",
          "orchard-ground": "ground", "orchard-tile": "tiles", "orchard-merge": "merge"}


def _prefix(key: str) -> str:
    return next((p for p in STAGES if str(key).startswith(p)), str(key).split("-")[0])


def _tile(key: str) -> str:
    parts = str(key).split("-")
    return parts[2] if str(key).startswith(("orchard-ground", "orchard-tile")) else ""


def run(las: str, work: Path, n_workers: int, worker_memory: float) -> dict:
    """Run the job once; its task stream, the thread CPU per kind of task, the workers'
    process CPU and the job's timings."""
    from distributed import get_task_stream

    from pipeline.jobparams import JobParams
    from workers.cluster import make_client
    from workers.job import run_job
    from workers.jobspec import JobSpec
    from workers.runoptions import RunOptions

    client = make_client(n_workers=n_workers, threads_per_worker=1, dashboard=False, quiet=True)
    try:
        spec = JobSpec(input_path=las, out_dir=str(work / "out"), job=JobParams(),
                       run=RunOptions(workers=n_workers, worker_memory=worker_memory), work_dir=str(work / "work"))
        cpu0 = client.run(time.process_time)
        t0 = time.time()
        with get_task_stream(client) as ts:
            outcome = run_job(spec, client=client)
        t1 = time.time()
        cpu1 = client.run(time.process_time)
        time.sleep(3)  # the workers send their metrics with their heartbeats
        metrics = client.run_on_scheduler(lambda dask_scheduler: dict(dask_scheduler.cumulative_worker_metrics))
    finally:
        client.close()
    tasks = sorted((s["start"] - t0, s["stop"] - t0, str(d["key"]), d["worker"])
                   for d in ts.data for s in d["startstops"] if s["action"] == "compute")
    cpu = defaultdict(lambda: [0.0, 0.0])
    for k, v in metrics.items():
        if isinstance(k, tuple) and len(k) == 4 and k[0] == "execute" and k[2] in ("thread-cpu", "thread-noncpu"):
            cpu[_prefix(k[1])][k[2] == "thread-noncpu"] += v
    return {"tasks": tasks, "wall": t1 - t0, "thread_cpu": dict(cpu), "timings": outcome.timings,
            "worker_cpu": {w: cpu1[w] - cpu0[w] for w in cpu0}, "n_tiles": outcome.n_tiles}


def report(r: dict) -> str:
    tasks, wall = r["tasks"], r["wall"]
    workers = sorted({t[3] for t in tasks})
    name = {w: f"w{i}" for i, w in enumerate(workers)}
    lines = ["| task | tile | worker | start [s] | end [s] | wall [s] |", "|---|---:|---|---:|---:|---:|"]
    lines += [f"| {_prefix(k)} | {_tile(k)} | {name[w]} | {a:.2f} | {b:.2f} | {b - a:.2f} |" for a, b, k, w in tasks]
    stages = {}
    for a, b, k, _ in tasks:
        s = STAGES.get(_prefix(k), "other")
        lo, hi = stages.get(s, (a, b))
        stages[s] = (min(lo, a), max(hi, b))
    lines += ["", "| stage | from [s] | to [s] | " + " | ".join(f"{name[w]} idle [s]" for w in workers) + " |",
              "|---|---:|---:|" + "---:|" * len(workers)]
    for s, (lo, hi) in sorted(stages.items(), key=lambda x: x[1]):
        idle = []
        for w in workers:
            busy = sum(min(b, hi) - max(a, lo) for a, b, _, ww in tasks if ww == w and b > lo and a < hi)
            idle.append(f"{hi - lo - busy:.2f}")
        lines.append(f"| {s} | {lo:.2f} | {hi:.2f} | " + " | ".join(idle) + " |")
    tiles = [k for _, _, k, _ in tasks if _prefix(k) == "orchard-tile"]
    lines += ["", f"job wall {wall:.1f} s; {r['n_tiles']} tiles; tile tasks {len(tiles)} "
              f"({len(tiles) - len(set(_tile(k) for k in tiles))} run again after the slot trees)",
              "thread CPU [s] by task (and the time its thread waited meanwhile: for a core, for I/O): "
              + ", ".join(f"{k} {c:.2f} ({w:.2f})" for k, (c, w) in sorted(r["thread_cpu"].items())),
              "workers' process CPU [s]: " + ", ".join(f"{name.get(w, w)} {v:.2f}" for w, v in r["worker_cpu"].items()),
              "job phases [s]: " + ", ".join(f"{k} {v:.2f}" for k, v in r["timings"].items() if isinstance(v, float)),
              f"load average after: {os.getloadavg()[0]:.1f}"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.task_timeline", description=__doc__.splitlines()[0])
    p.add_argument("block", help="a LAS/LAZ block")
    p.add_argument("--workers", type=int, default=2, help="worker processes (default 2, the service's)")
    p.add_argument("--worker-memory", type=float, default=2.0, help="memory budget per worker [GB] (default 2)")
    p.add_argument("--work-dir", type=Path, help="folder for the job's work store and outputs (default: a temporary one)")
    args = p.parse_args(argv)
    print(f"load average at start {os.getloadavg()[0]:.1f}", flush=True)
    if args.work_dir:
        r = run(args.block, args.work_dir, args.workers, args.worker_memory)
    else:
        with tempfile.TemporaryDirectory(prefix="orchard-timeline-") as tmp:
            r = run(args.block, Path(tmp), args.workers, args.worker_memory)
    print(report(r))
    return 0


if __name__ == "__main__":  # the workers' processes import this module again: run only here
    sys.exit(main())
