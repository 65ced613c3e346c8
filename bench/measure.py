"""One measurement in a fresh process: ``python -m bench.measure '<json>'``.

Prints one JSON line (prefixed ``BENCH-RESULT ``) with what it measured. Kinds:

- ``job``: ``workers.job.run_job`` on a block, either in this process (``workers``
  0; optionally pinned to one core and split by stage) or tiled on a fresh
  ``LocalCluster`` of ``workers`` single-threaded worker processes. Reports wall
  time (after ``warmup`` untimed runs), the job's own timings, and exact peak RSS (``getrusage``) of this process
  and of every dask worker.
- ``decode``: raw LAZ decode throughput of a file with laspy chunk iteration, all
  point fields and x/y/z only, plus ``pipeline.reading.iter_points``.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import sys
import time

from bench.isolation import pin_one_core


def _maxrss_bytes() -> int:
    """Peak resident memory of this process since it started [bytes].

    Linux's VmHWM belongs to the process's own address space, made anew by ``exec``;
    ``getrusage``'s ``ru_maxrss`` keeps the high-water mark of the process it was forked
    from (a benchmark's parent holding a few hundred MB would show as this process's peak).
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: kB


def _cpu_seconds() -> float:
    """User + system CPU time of this process so far [s]."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _warm_up() -> bool:
    """Import the pipeline and run it once on a tiny generated block, so the timed runs
    measure steady-state work and not imports and first calls (long-lived workers are warm)."""
    import numpy as np

    from pipeline.params import PipelineParams
    from pipeline.process import process_points
    from simulator.simparams import SimulationParams
    from simulator.simulate import simulate_orchard

    o = simulate_orchard(SimulationParams(rows=1, trees_per_row=1, density=0.3, seed=1))
    process_points(o.xyz - np.floor(o.xyz.min(axis=0)), params=PipelineParams())
    return True


def run_job_measure(cfg: dict) -> dict:
    from pipeline.jobparams import JobParams, TilingParams
    from pipeline.params import PipelineParams
    from workers.job import run_job
    from workers.jobspec import JobSpec

    params = PipelineParams.model_validate(cfg.get("params") or {})
    repeats = int(cfg.get("repeats", 1))
    workers = int(cfg.get("workers", 0))
    out = {"kind": "job", "workers": workers, "runs": []}
    if workers == 0 and cfg.get("one_core", True):
        out["pinned_cpu"] = pin_one_core()
    client = cluster = None
    if workers > 0:
        from distributed import Client, LocalCluster

        from workers.cluster import worker_allocator

        with worker_allocator():  # the allocator settings of orchard's own embedded workers
            cluster = LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True,
                dashboard_address=None, memory_limit=cfg.get("memory_limit", "4GiB"),
            )
        client = Client(cluster)
        client.run(_warm_up)
    try:
        for _ in range(int(cfg.get("warmup", 0))):  # imports, caches, first-touch page faults
            warm_dir = os.path.join(cfg["out"], "warmup")
            run_job(JobSpec(input_path=cfg["input"], out_dir=warm_dir, job=JobParams(pipeline=params, tiling=TilingParams(tile_size=cfg.get("tile_size"))), work_dir=cfg.get("work_dir")), client=client)
            shutil.rmtree(warm_dir, ignore_errors=True)
        for r in range(repeats):
            out_dir = os.path.join(cfg["out"], f"run{r}")
            shutil.rmtree(out_dir, ignore_errors=True)
            spec = JobSpec(
                input_path=cfg["input"], out_dir=out_dir, job=JobParams(pipeline=params, tiling=TilingParams(tile_size=cfg.get("tile_size"))), work_dir=cfg.get("work_dir"),
            )
            cpu0 = _cpu_seconds()
            wcpu0 = sum(client.run(_cpu_seconds).values()) if client is not None else 0.0
            if cfg.get("stages") and workers == 0:
                from bench.stages import timed_stages

                with timed_stages() as timer:
                    t = time.perf_counter()
                    outcome = run_job(spec)
                    wall = time.perf_counter() - t
                stages = timer.split(wall)
            else:
                t = time.perf_counter()
                outcome = run_job(spec, client=client)
                wall = time.perf_counter() - t
                stages = None
            cpu = _cpu_seconds() - cpu0
            if client is not None:
                cpu += sum(client.run(_cpu_seconds).values()) - wcpu0
            out["runs"].append({
                "wall_s": wall, "cpu_s": cpu, "load": os.getloadavg()[0], "timings": outcome.timings, "stages": stages,
                "n_points": outcome.n_points, "n_trees": outcome.n_trees, "n_tiles": outcome.n_tiles,
                "partial": outcome.partial,
            })
            if r < repeats - 1:
                shutil.rmtree(out_dir, ignore_errors=True)
        if client is not None:
            peaks = client.run(_maxrss_bytes)
            out["worker_maxrss"] = sorted(peaks.values(), reverse=True)
    finally:
        if client is not None:
            client.close()
            cluster.close()
    out["main_maxrss"] = _maxrss_bytes()
    return out


def run_decode_measure(cfg: dict) -> dict:
    import laspy

    from pipeline.reading import iter_points

    path = cfg["input"]
    chunk = int(cfg.get("chunk_points", 2_000_000))
    repeats = int(cfg.get("repeats", 1))
    pin_one_core()
    res = {"kind": "decode", "chunk_points": chunk}

    def all_fields():
        n = 0
        with laspy.open(path) as f:
            for pts in f.chunk_iterator(chunk):
                x, y, z = pts.x, pts.y, pts.z  # scaled float64, like the pipeline needs
                n += len(x)
        return n

    def xyz_only():
        n = 0
        sel = laspy.DecompressionSelection.XY_RETURNS_CHANNEL | laspy.DecompressionSelection.Z
        with laspy.open(path, decompression_selection=sel) as f:
            for pts in f.chunk_iterator(chunk):
                x, y, z = pts.x, pts.y, pts.z
                n += len(x)
        return n

    def pipeline_reader():
        n = 0
        for _, xyz in iter_points(path, chunk_points=chunk):
            n += len(xyz)
        return n

    for name, fn in (("laspy_all_fields", all_fields), ("laspy_xyz_only", xyz_only), ("pipeline_iter_points", pipeline_reader)):
        best = None
        for _ in range(repeats):
            t = time.perf_counter()
            n = fn()
            dt = time.perf_counter() - t
            best = dt if best is None else min(best, dt)
        res[name] = {"seconds": best, "n_points": n, "points_per_s": n / best}
    res["main_maxrss"] = _maxrss_bytes()
    return res


def main(argv: list[str]) -> int:
    cfg = json.loads(argv[0])
    kind = cfg["kind"]
    if kind == "job":
        result = run_job_measure(cfg)
    elif kind == "decode":
        result = run_decode_measure(cfg)
    else:
        raise SystemExit(f"unknown measurement kind {kind!r}")
    print("BENCH-RESULT " + json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
