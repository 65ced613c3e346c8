"""The two tiling engines side by side: time and memory of the tiling alone and of
``orchard process`` end to end on one generated block, and whether every output is the
same file.

Run with a Python that has PDAL's bindings (``bench/build_pdal.sh`` makes one)::

    PYTHONPATH=$PWD ~/.cache/pdal-build/venv/bin/python -m bench.engines --points 10000000

Each measurement runs in a fresh process; its peak RSS is the kernel's (``wait4``), the
end-to-end one adds the sampled peaks of the workers it starts.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.blocks import count_points, make_block, orchard_params, stand_density, stand_params
from bench.density import CliFailed, _wait, run_cli

_TILE = """
import json, sys, time
from pipeline.blockinfo import read_info
from pipeline.tiling import plan_grid
from workers.tiler import tile_block
from workers.workstore import WorkStore
las, work, engine, size, buffer = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]), float(sys.argv[5])
info = read_info(las)
grid = plan_grid(info.mins, info.maxs, tile_size=size, buffer=buffer, grid_origin=info.origin[:2])
store = WorkStore(work)
t = time.perf_counter()
idx = tile_block(info, grid, store, engine=engine)
print(json.dumps({"seconds": time.perf_counter() - t, "tiles": len(idx["tiles"])}))
store.remove()
"""


def tile_alone(las: str, work: Path, engine: str, tile_size: float, buffer: float) -> dict:
    """``tile_block`` of one engine in a fresh process: seconds, tiles, peak RSS [bytes]."""
    with open(os.devnull, "w") as null:
        proc = subprocess.Popen([sys.executable, "-c", _TILE, las, str(work), engine, str(tile_size), str(buffer)],
                                stdout=subprocess.PIPE, stderr=null, text=True)
        rss = _wait(proc, 3600)
        out = proc.stdout.read()
    if proc.returncode != 0:
        raise RuntimeError(f"tiling with {engine} exited {proc.returncode}")
    return dict(json.loads(out), maxrss=rss)


def same_outputs(a: Path, b: Path) -> list[str]:
    """Names of the files of ``a`` that are not byte for byte in ``b`` (or missing)."""
    return [p.name for p in sorted(a.iterdir()) if not (b / p.name).is_file() or (b / p.name).read_bytes() != p.read_bytes()]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.engines", description=__doc__.split("\n\n")[0])
    p.add_argument("--points", type=int, default=10_000_000, help="about this many points (default 10000000)")
    p.add_argument("--tile-size", type=float, default=20.0)
    p.add_argument("--buffer", type=float, default=6.15, help="tile buffer [m] of the tiling-alone runs (the reach)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--work-dir", type=Path, default=Path(os.environ.get("ORCHARD_BENCH_WORK", "/tmp/orchard-bench")))
    args = p.parse_args(argv)
    work = args.work_dir
    density = stand_density(1_000_000)  # the main bench's blocks (python -m bench): same file, cached
    block = make_block(work, f"size-{args.points // 1_000_000}M", orchard_params(args.points, density, count_points(stand_params(density)) / 3.0))
    print(f"block {block.las}: {block.n_points:,} points, {block.n_trees} trees", file=sys.stderr, flush=True)
    rows, outs = {}, {}
    for engine in ("laspy", "pdal"):
        alone = tile_alone(block.las, work / f"engines-work-{engine}", engine, args.tile_size, args.buffer)
        outs[engine] = work / "engines-out" / engine
        try:
            e2e = run_cli(block.las, outs[engine], extra=("--tile-size", str(args.tile_size), "--workers", str(args.workers), "--engine", engine))
        except CliFailed as exc:
            e2e = {"error": str(exc)}
        rows[engine] = {"tile": alone, "process": e2e}
        print(f"  {engine}: {json.dumps(rows[engine])}", file=sys.stderr, flush=True)
    differ = same_outputs(outs["laspy"], outs["pdal"])
    print(f"\nblock: {block.n_points:,} points, {block.n_trees} trees; tile size {args.tile_size:g} m, "
          f"{args.workers} workers; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n")
    print("| engine | tiling alone | its peak RSS | tiles | `orchard process` | its peak RSS (main) | all processes (sampled) |")
    print("|---|---|---|---|---|---|---|")
    for engine, r in rows.items():
        t, e = r["tile"], r["process"]
        end = (f"{e['wall_s']:.1f} s | {e['main_maxrss'] / 2**30:.2f} GiB | {e['sampled_total'] / 2**30:.2f} GiB"
               if "wall_s" in e else f"{e['error']} | | ")
        print(f"| {engine} | {t['seconds']:.1f} s | {t['maxrss'] / 2**30:.2f} GiB | {t['tiles']} | {end} |")
    print(f"\noutputs byte for byte the same: {'yes' if not differ else 'no: ' + ', '.join(differ)}")
    return 0 if not differ else 1


if __name__ == "__main__":
    sys.exit(main())
