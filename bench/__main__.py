"""``python -m bench [--quick]``: run the benchmark suite and write the results.

Writes ``bench/results.md``, PNG plots next to it, and the section of
``docs/benchmarks.md`` between ``<!-- bench:start -->`` and ``<!-- bench:end -->``
(nothing else on that page; the README only links it).
"""

from __future__ import annotations

import os

# One thread per process for the numeric libraries, before numpy is imported anywhere:
# "one core" must mean one core, and dask workers get one thread each.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DOCS_PAGE = ROOT / "docs" / "benchmarks.md"


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bench", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true",
                   help="fast subset: 4 accuracy blocks, sizes 1 M and 10 M (no 50 M), fewer repeats, one peer block")
    p.add_argument("--noises", type=_floats, help="noise levels σ [m], comma-separated (default 0,0.02,0.05,0.1; quick 0.02,0.1)")
    p.add_argument("--spacings", type=_floats, help="tree spacings [m], comma-separated (default 3,4,5,6,8; quick 4,6)")
    p.add_argument("--sizes", type=_floats, help="block sizes in millions of points (default 1,10,50; quick 1,10)")
    p.add_argument("--large", action="store_true",
                   help="add the 100 M-point block to the scaling table (not with --quick; about 10 minutes more on 2 cores)")
    p.add_argument("--stand-points", type=int, default=1_000_000, help="least points of the 3-tree stand (default 1000000)")
    p.add_argument("--repeats", type=int, help="timed runs of the stand (median reported; default 5, quick 3)")
    p.add_argument("--tile-size", type=float, default=20.0, help="tile core size for the tiled runs [m] (default 20)")
    p.add_argument("--workers", type=int, default=2, help="dask workers for the size runs (default 2)")
    p.add_argument("--workers-block", type=float, default=10.0, help="size of the 1-vs-2-workers block, millions of points (default 10)")
    p.add_argument("--tile-sizes", type=_floats, default=[20.0, 30.0, 40.0, 60.0],
                   help="tile sizes [m] compared on the --workers-block block, comma-separated (default 20,30,40,60)")
    p.add_argument("--skip", default="", help="comma-separated parts to skip: accuracy,real,stand,scaling,workers,tiles,peers")
    p.add_argument("--work-dir", type=Path, default=Path(os.environ.get("ORCHARD_BENCH_WORK", "/tmp/orchard-bench")),
                   help="folder for generated blocks and outputs (reused between runs; default /tmp/orchard-bench)")
    p.add_argument("--out-dir", type=Path, default=HERE, help="where results.md and the plots go (default bench/)")
    p.add_argument("--peers-venv", type=Path, default=Path.home() / ".cache" / "orchard-bench" / "peers",
                   help="virtualenv for peers from PyPI (created if missing)")
    p.add_argument("--peer-timeout", type=float, default=1800.0, help="seconds one peer run may take (default 1800)")
    p.add_argument("--no-docs", "--no-readme", dest="no_docs", action="store_true",
                   help="do not update the section of docs/benchmarks.md")
    p.add_argument("--render", type=Path, metavar="RESULTS_JSON",
                   help="measure nothing: re-render results.md, the plots and the docs/benchmarks.md section from the raw "
                        "data of an earlier run (the results.json it left in its work folder)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.render:
        data = json.loads(args.render.read_text())
        write_outputs(data, args.out_dir, page=None if args.no_docs else DOCS_PAGE, log=print)
        return 0
    quick = args.quick
    noises = args.noises or ([0.02, 0.1] if quick else [0.0, 0.02, 0.05, 0.1])
    spacings = args.spacings or ([4.0, 6.0] if quick else [3.0, 4.0, 5.0, 6.0, 8.0])
    repeats = args.repeats or (3 if quick else 5)
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    work: Path = args.work_dir
    work.mkdir(parents=True, exist_ok=True)
    args.out_dir.mkdir(parents=True, exist_ok=True)

    import threading

    from bench import machine, results_page

    t_start = time.perf_counter()
    loads: list[float] = []
    stop_load = threading.Event()

    def sample_load() -> None:  # the machine may be shared: record how busy it was
        while not stop_load.is_set():
            loads.append(os.getloadavg()[0])
            stop_load.wait(5.0)

    threading.Thread(target=sample_load, name="load-sampler", daemon=True).start()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t_start:7.1f} s] {msg}", flush=True)

    command = "python -m bench " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    data: dict = {"machine": machine.describe(), "command": command.strip(), "quick": quick}
    log(f"machine: {data['machine']['cpu']}, {data['machine']['usable_cores']} cores, {data['machine']['ram_gib']} GiB")

    if "accuracy" not in skip:
        from bench import accuracy

        log(f"accuracy: {len(noises)} noise levels x {len(spacings)} spacings")
        blocks = accuracy.run_grid(work, noises, spacings, log=log)
        data["accuracy"] = {"noises": noises, "spacings": spacings, "blocks": blocks, "summary": accuracy.summarise(blocks)}

    if "real" not in skip:
        from bench import real_data

        log("real data: ../shared/data/real")
        data["real_data_md"] = real_data.run() if real_data.REAL.is_dir() else "## Real data\n\nNot run: ../shared/data/real is absent.\n"

    stand = None
    if not {"stand", "scaling", "workers", "tiles"} <= skip:  # any part that needs the stand density
        from bench.blocks import count_points, stand_density, stand_params

        density = stand_density(args.stand_points)
        points_per_tree = count_points(stand_params(density)) / 3.0
    if "stand" not in skip:
        from bench import speed

        log("speed: 3-tree stand, one core")
        stand = speed.run_stand(work, min_points=args.stand_points, repeats=repeats, log=log)
        data["stand"] = stand
        log(f"  {stand['median_s']:.2f} s per stand ({stand['points_per_s'] / 1e6:.2f} M points/s)")

    if "scaling" not in skip:
        from bench import scaling

        targets, notes = scaling.targets(args.sizes, quick=quick, large=args.large)
        if notes:
            data["scaling_notes"] = notes
        log(f"scaling: {', '.join(f'{t / 1e6:g} M' for t in targets)} points")
        data["scaling"] = scaling.run_sizes(work, targets, density=density, points_per_tree=points_per_tree,
                                            tile_size=args.tile_size, workers=args.workers, log=log)
        log(f"  exponent {data['scaling']['exponent']:.2f}")

    if "workers" not in skip or "tiles" not in skip:
        from bench import scaling
        from bench.blocks import make_block, orchard_params

        target = int(args.workers_block * 1_000_000)
        block = make_block(work, f"size-{target // 1_000_000}M", orchard_params(target, density, points_per_tree))
    if "workers" not in skip:
        log(f"workers: 1 vs 2 on {block.n_points:,} points")
        data["workers"] = scaling.run_workers(work, block, tile_size=args.tile_size, log=log)
    if "tiles" not in skip:
        from pipeline.params import PipelineParams

        log(f"tile sizes: {', '.join(f'{s:g} m' for s in args.tile_sizes)} on {block.n_points:,} points")
        data["tiles"] = scaling.run_tile_sizes(work, block, tile_sizes=args.tile_sizes, workers=args.workers,
                                               buffer=PipelineParams().reach(), log=log)

    if "peers" not in skip:
        from bench import peers
        from bench.blocks import accuracy_params, make_block
        from bench.isolation import one_core

        log("peers: dendromatics")
        status = peers.prepare(work, args.peers_venv, log=log)
        runs = []
        if status.get("install") == "ok":
            cells = [(0.02, 5.0)] if quick else [(0.02, 5.0), (0.05, 4.0)]
            for i, (noise, spacing) in enumerate(cells):
                block = make_block(work, f"acc-n{noise:g}-s{spacing:g}", accuracy_params(noise, spacing, 100 + i))
                label = f"σ {noise:g} m, spacing {spacing:g} m, {block.n_points:,} points"
                from bench.accuracy import score_block

                with one_core():
                    ours = score_block(str(work), noise, spacing, 100 + i, baselines=False)
                runs.append({"method": "ours", "block": label, "metrics": dict(ours["methods"]["ours"], seconds=ours["seconds"]["ours"])})
                for config in ("3DFin defaults", "orchard stripe"):
                    log(f"  dendromatics ({config}) on {label}")
                    m = peers.run_on_block(status, block, work, config_name=config, timeout=args.peer_timeout, log=log)
                    runs.append({"method": f"dendromatics, {config}", "block": label, "metrics": m})
        note = ("*3DFin defaults* look for stems in a stripe 0.7–3.5 m above the ground (forest trees); "
                "*orchard stripe* lowers it to 0.15–0.7 m, the clear trunk of these orchard trees, and accepts "
                "stems of 200 points or more. A run that finds no stem at all ends in dendromatics with "
                "`ValueError: need at least one array to concatenate`. Both run pinned to one core. The peer's "
                "time is from its own process, excluding reading the file; ours is the whole job (reading the "
                "LAZ, processing, writing the Parquet files), cold (no warm-up run).")
        data["peers"] = {"status": status, "runs": runs, "note": note}

    data["elapsed_s"] = time.perf_counter() - t_start
    stop_load.set()
    data["load"] = {"min": min(loads), "max": max(loads), "mean": sum(loads) / len(loads)} if loads else None
    (work / "results.json").write_text(json.dumps(data, indent=1, default=str))
    log(f"raw data: {work / 'results.json'}")
    write_outputs(data, args.out_dir, page=None if args.no_docs else DOCS_PAGE, log=log)
    return 0


def write_outputs(data: dict, out: Path, *, page: Path | None, log) -> None:
    """results.md, the PNG plots and (unless ``page`` is None) its section of ``page``, from one run's data."""
    from bench import results_page

    out.mkdir(parents=True, exist_ok=True)
    if data.get("accuracy"):
        results_page.plot_accuracy(data["accuracy"]["blocks"], out / "accuracy.png")
    if data.get("stand"):
        results_page.plot_stages(data["stand"], out / "stages.png")
    if data.get("scaling"):
        results_page.plot_scaling(data["scaling"], out / "scaling.png")
    text = results_page.render(data)
    (out / "results.md").write_text(text)
    log(f"wrote {out / 'results.md'}")
    if page is not None:
        if results_page.splice_section(page, text, image_prefix=_relative_prefix(page.parent, out)):
            log(f"updated the section of {page} between the bench markers")
        else:
            log(f"{page} has no <!-- bench:start --> / <!-- bench:end --> markers; left it alone")


def _relative_prefix(page_dir: Path, out: Path) -> str:
    """How the page links to the plots in ``out``: ``../bench/`` for docs/ and bench/."""
    return Path(os.path.relpath(out.resolve(), page_dir.resolve())).as_posix() + "/"


if __name__ == "__main__":
    sys.exit(main())
