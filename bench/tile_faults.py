"""``python -m bench.tile_faults WORK TILE``: one tile task's CPU, fresh pages and peak.

Runs :func:`workers.tasks.process_tile` on tile ``TILE`` of a job's work store ``WORK``
(kept from a tiled job, e.g. ``bench.task_timeline --work-dir``; the task writes the
tile's results into it again) in this process, and prints one JSON line: user and system
CPU [s], minor page faults and the process's peak resident memory [MiB] of the task.

Each minor fault is a page the kernel hands out zeroed: a large temporary's first touch.
numpy asks for transparent huge pages on arrays of 4 MiB or more, so a fault may be a
2 MiB page; ``--small-pages`` turns that off, and the fault count then measures the bytes
first touched (4 KiB a fault). ``--profile`` prints the functions that took the most
faults (cProfile with the fault count as its clock) instead; ``--peak-steps`` the
pipeline's stack each time tracemalloc's peak rises by that many MiB (where the traced
peak is set).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import resource
import sys
import time
import tracemalloc
import traceback


def _params_json(work: str) -> str:
    from pipeline.jobparams import JobParams

    with open(f"{work}/job.json") as f:
        return JobParams.model_validate(json.load(f)["job"]).pipeline.model_dump_json()


def measure(work: str, tile: int) -> dict:
    """Run the task once; its user and system CPU [s], minor faults and the peak [MiB]."""
    from workers.tasks import process_tile

    params = _params_json(work)
    r0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    summary = process_tile(work, tile, params)
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return {"tile": tile, "user": round(r1.ru_utime - r0.ru_utime, 3), "sys": round(r1.ru_stime - r0.ru_stime, 3),
            "minflt": r1.ru_minflt - r0.ru_minflt, "maxrss_mib": round(r1.ru_maxrss / 1024, 1),
            "wall": round(time.perf_counter() - w0, 2), "n_core": summary["n_core"]}


def profile(work: str, tile: int, top: int) -> None:
    """Print the ``top`` functions by the minor faults taken in their own code."""
    from workers.tasks import process_tile

    params = _params_json(work)
    pr = cProfile.Profile(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt, 1.0)
    pr.enable()
    process_tile(work, tile, params)
    pr.disable()
    pstats.Stats(pr).sort_stats("tottime").print_stats(top)


def peak_steps(work: str, tile: int, step_mib: int) -> None:
    """Print tracemalloc's peak [MiB] and the innermost pipeline and worker frames each
    time the peak rises by ``step_mib`` or more (checked at every call and return)."""
    from workers.tasks import process_tile

    params = _params_json(work)
    last = [0]

    def hook(frame, event, arg):
        peak = tracemalloc.get_traced_memory()[1]
        if peak - last[0] >= step_mib << 20:
            last[0] = peak
            stack = [f"{f.f_code.co_filename.rsplit('/', 1)[-1]}:{line}:{f.f_code.co_name}"
                     for f, line in traceback.walk_stack(frame) if "/pipeline/" in f.f_code.co_filename
                     or "/workers/" in f.f_code.co_filename][::-1]
            print(peak >> 20, " > ".join(stack[-4:]), flush=True)

    tracemalloc.start(1)
    sys.setprofile(hook)
    try:
        process_tile(work, tile, params)
    finally:
        sys.setprofile(None)
    print("traced peak [MiB]", tracemalloc.get_traced_memory()[1] >> 20)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.tile_faults", description=__doc__.splitlines()[0])
    ap.add_argument("work", help="a tiled job's work store (its job.json and tiles/)")
    ap.add_argument("tile", type=int, help="the tile's id")
    ap.add_argument("--small-pages", action="store_true", help="no transparent huge pages for numpy's arrays")
    ap.add_argument("--profile", type=int, metavar="TOP", default=0,
                    help="print the TOP functions by minor faults instead (cProfile's tottime column)")
    ap.add_argument("--peak-steps", type=int, metavar="MIB", default=0,
                    help="print where tracemalloc's peak rises by MIB or more instead")
    args = ap.parse_args(argv)
    if args.small_pages:
        import numpy as np

        np._core.multiarray._set_madvise_hugepage(False)
    if args.profile:
        profile(args.work, args.tile, args.profile)
    elif args.peak_steps:
        peak_steps(args.work, args.tile, args.peak_steps)
    else:
        print(json.dumps(measure(args.work, args.tile)), flush=True)


if __name__ == "__main__":
    main()
