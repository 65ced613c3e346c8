"""Blocks at the point density of a vehicle-mounted mobile scan: per point, per tree, per hectare.

    python -m bench.density [--sizes 1,4] [--forms all] [--work-dir DIR]

**Assumed scanner.** A 16-line spinning lidar (Velodyne VLP-16 class) emitting
``PULSE_RATE`` = 300,000 pulses/s, single return, on a vehicle driven at ``SPEED`` =
1.5 m/s down every alley. We take ``RETURN_FRACTION`` = 0.5 of the pulses to come back
from inside the block (beams above the canopy, and near-horizontal beams along the
alley past the block's end, return nothing or fall outside it). One pass sweeps one
alley, ``row_spacing`` wide, so the block holds

    points per m² = PULSE_RATE × RETURN_FRACTION / (SPEED × row_spacing)

(28,600 /m² at 3.5 m between rows, 16,700 /m² at 6 m) and a tree, which owns
``spacing × row_spacing`` of the block, ``points per m² × spacing × row_spacing`` points
(100,000 for tall spindle at 1.0 m × 3.5 m, 500,000 for vase trees at 5 m × 6 m). A
slower vehicle or a faster scanner gives more; ``--pulse-rate``, ``--speed`` and
``--return-fraction`` change the assumption.

**Blocks.** For each form (``FORMS``) the simulator's ``density`` is set so that the
block's points divided by its planted area (rows × row_spacing × trees × spacing) equal
that figure: it is calibrated from a count at a tenth of the density (point counts are
linear in it). The scaling table grows the vase block at the same density to about each
of ``--sizes`` million points.

**Measured per block**, in one run: ``orchard process BLOCK.laz --out DIR`` with its
defaults (it tiles by itself when the block would not fit its memory budget), a fresh
process, wall time from start to exit (LAZ in, every output written, start-up included);
its own peak RSS (``os.wait4``) and that of every process it starts (dask workers:
sampled every 0.1 s by :class:`bench.memory.TreeSampler`); and the raw decode rate of the
same file: ``laspy.read`` of the whole file in a fresh process free to use every core,
as the end-to-end run is (the "fraction of the decoder" figure is the ratio of the two
rates), and the :mod:`bench.measure` ``decode`` rate (laspy chunks, all point fields,
pinned to one core). Prints Markdown.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from bench.blocks import count_points, make_block
from bench.isolation import SINGLE_THREAD_ENV, measure
from bench.memory import TreeSampler
from simulator.simparams import SimulationParams

PULSE_RATE = 300_000.0
"""Pulses per second of the assumed scanner [1/s]."""

SPEED = 1.5
"""Driving speed down each alley [m/s]."""

RETURN_FRACTION = 0.5
"""Share of the pulses that return from inside the block."""

FORMS: dict[str, dict] = {
    "vase 5 m × 6 m": dict(rows=2, trees_per_row=3, spacing=5.0, row_spacing=6.0, noise=0.02),
    "tall spindle 1.0 m × 3.5 m": dict(form="spindle", rows=2, trees_per_row=12, spacing=1.0, row_spacing=3.5),
    "hedge 1.35 m × 4 m": dict(form="hedge", rows=2, trees_per_row=10, spacing=1.35, row_spacing=4.0),
}
"""Block layouts (``SimulationParams`` fields, no seed or density), one per tree form."""

SEED = 0
"""Seed of every generated block."""


@dataclass(frozen=True)
class Scanner:
    """A mobile scanner driven down every alley."""

    pulse_rate: float = PULSE_RATE  # [1/s]
    speed: float = SPEED  # [m/s]
    return_fraction: float = RETURN_FRACTION

    def points_per_m2(self, row_spacing: float) -> float:
        """Points per m² of block when one pass sweeps one alley ``row_spacing`` [m] wide."""
        return self.pulse_rate * self.return_fraction / (self.speed * row_spacing)

    def points_per_tree(self, spacing: float, row_spacing: float) -> float:
        """Points of a tree owning ``spacing`` × ``row_spacing`` [m] of the block."""
        return self.points_per_m2(row_spacing) * spacing * row_spacing


def planted_area(sim: dict) -> float:
    """Planted area of a layout [m²]: every slot owns spacing × row_spacing."""
    return sim["rows"] * sim["trees_per_row"] * sim["spacing"] * sim["row_spacing"]


def mobile_density(sim: dict, scanner: Scanner, seed: int = SEED) -> float:
    """The simulator ``density`` whose block has ``scanner``'s points per m² of planted area."""
    probe = 0.1
    per_unit = count_points(SimulationParams(seed=seed, density=probe, **sim)) / probe
    return round(scanner.points_per_m2(sim["row_spacing"]) * planted_area(sim) / per_unit, 3)


def grown(sim: dict, n_trees: int) -> dict:
    """``sim`` with about ``n_trees`` trees in a roughly square block (rows × trees per row)."""
    length = sim["spacing"] / sim["row_spacing"]  # a row of k trees is k × this many alleys long
    rows = max(1, round((n_trees * length) ** 0.5))
    return dict(sim, rows=rows, trees_per_row=max(3, round(n_trees / rows)))


def _wait(proc: subprocess.Popen, timeout: float) -> int:
    """Wait for ``proc``; its own peak RSS [bytes] (``os.wait4``). Kills it after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            return usage.ru_maxrss * 1024  # Linux: kB
        if time.monotonic() > deadline:
            proc.kill()
        time.sleep(0.05)


class CliFailed(RuntimeError):
    """``orchard process`` exited with an error; ``message`` is its last line."""

    def __init__(self, code: int, message: str):
        super().__init__(f"orchard process exited {code}: {message}")
        self.code, self.message = code, message


def run_cli(las: str, out: Path, *, extra: tuple[str, ...] = (), timeout: float = 3600.0) -> dict:
    """``orchard process LAS --out OUT [extra]`` (its defaults otherwise) in a fresh
    process: wall time [s], its own peak RSS and the sampled peak RSS of every process it
    started [bytes]. Raises :class:`CliFailed` when it exits with an error."""
    shutil.rmtree(out, ignore_errors=True)
    env = dict(os.environ, **SINGLE_THREAD_ENV)
    with tempfile.TemporaryFile("w+") as log:
        t = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "process", las, "--out", str(out), *extra],
                                stdout=log, stderr=subprocess.STDOUT, env=env)
        with TreeSampler(proc.pid, interval=0.1) as sampler:
            main_rss = _wait(proc, timeout)
        wall = time.perf_counter() - t
        log.seek(0)
        text = log.read()
    if proc.returncode != 0:
        lines = text.strip().splitlines()
        raise CliFailed(proc.returncode, lines[-1] if lines else "")
    peaks = sampler.by_label()
    peaks.pop("main", None)
    children = sorted((p for ps in peaks.values() for p in ps), reverse=True)
    return {"wall_s": wall, "main_maxrss": main_rss, "children_rss": children,
            "tiled": "tiles of" in text, "sampled_total": sampler.peak_total}


_READ = """
import resource, sys, time
import laspy
t = time.perf_counter()
las = laspy.read(sys.argv[1])
x, y, z = las.x, las.y, las.z  # scaled float64, as the pipeline needs them
print(time.perf_counter() - t, len(x), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
"""


def read_whole(las: str) -> tuple[float, int]:
    """``laspy.read`` of ``las`` in a fresh process on every core: (seconds, its peak RSS [bytes])."""
    out = subprocess.run([sys.executable, "-c", _READ, las], capture_output=True, text=True, check=True, timeout=3600)
    seconds, _, rss = out.stdout.split()
    return float(seconds), int(rss)


def measure_block(work: Path, name: str, sim: dict, density: float, extra: tuple[str, ...] = ()) -> dict | str:
    """Generate (or reuse) one block, run it end to end (``orchard process`` options
    ``extra``) and decode it; the figures of one table row, or a row saying why
    ``orchard process`` refused the block."""
    params = SimulationParams(seed=SEED, density=density, **sim)
    block = make_block(work, f"density-{name}", params)
    print(f"  {name}: {block.n_points:,} points, {block.n_trees} trees", file=sys.stderr, flush=True)
    try:
        e2e = run_cli(block.las, work / "density-out" / name, extra=extra)
    except CliFailed as exc:
        return f"| {name} | {block.n_points:,} | {block.n_trees} | {planted_area(sim) / 1e4:.3f} | {exc} |"
    read_s, read_rss = read_whole(block.las)
    decode = measure({"kind": "decode", "input": block.las, "repeats": 1})
    area = planted_area(sim)
    return {"name": name, "n_points": block.n_points, "n_trees": block.n_trees, "area_m2": area,
            "decode_s": read_s, "decode_rss": read_rss, "decode_1core_s": decode["laspy_all_fields"]["seconds"], **e2e}


def block_row(r: dict | str) -> str:
    """One Markdown row of :data:`HEADER` (a string is a row already)."""
    if isinstance(r, str):
        return r
    wall, n, ha = r["wall_s"], r["n_points"], r["area_m2"] / 1e4
    rss = [r["main_maxrss"], *r["children_rss"]]
    procs = " + ".join(f"{x / 2**20:,.0f}" for x in rss)
    return (f"| {r['name']} | {n:,} | {r['n_trees']} | {ha:.3f} | {n / r['area_m2']:,.0f} | {n / max(r['n_trees'], 1):,.0f} "
            f"| {wall:.1f} | {n / wall / 1e3:,.0f} | {wall / ha / 60:.1f} | {wall / max(r['n_trees'], 1):.2f} "
            f"| {n / r['decode_s'] / 1e6:.2f} | {n / r['decode_1core_s'] / 1e6:.2f} | {100 * r['decode_s'] / wall:.1f} % "
            f"| {'yes' if r['tiled'] else 'no'} "
            f"| {procs} | {max(rss) / n:,.0f} | {r['decode_rss'] / 2**20:,.0f} |")


HEADER = (
    "| block | points | trees | planted ha | points / m² | points / tree | end to end [s] | k points / s | min / ha "
    "| s / tree | laspy.read [M points/s] | decode, 1 core [M points/s] | end to end / laspy.read | tiled "
    "| peak RSS per process [MiB] | bytes / point | laspy.read peak RSS [MiB] |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def density_table(scanner: Scanner, forms: dict[str, dict]) -> str:
    """The assumption's arithmetic per form, as Markdown."""
    lines = ["| form | in row × between rows [m] | points / m² | points / tree |", "|---|---|---|---|"]
    for name, sim in forms.items():
        lines.append(f"| {name} | {sim['spacing']:g} × {sim['row_spacing']:g} | "
                     f"{scanner.points_per_m2(sim['row_spacing']):,.0f} | "
                     f"{scanner.points_per_tree(sim['spacing'], sim['row_spacing']):,.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.density", description=__doc__.splitlines()[0])
    p.add_argument("--forms", default="all", help="forms to run, comma-separated name fragments, or 'all' or '' (default all)")
    p.add_argument("--sizes", default="1,4",
                   help="vase blocks at mobile density for the scaling table, millions of points, comma-separated "
                        "(default 1,4; '' for none)")
    p.add_argument("--pulse-rate", type=float, default=PULSE_RATE, help=f"scanner pulses per second (default {PULSE_RATE:,.0f})")
    p.add_argument("--speed", type=float, default=SPEED, help=f"driving speed [m/s] (default {SPEED})")
    p.add_argument("--return-fraction", type=float, default=RETURN_FRACTION,
                   help=f"share of pulses returning from inside the block (default {RETURN_FRACTION})")
    p.add_argument("--work-dir", type=Path, default=Path(os.environ.get("ORCHARD_BENCH_WORK", "/tmp/orchard-bench")),
                   help="folder for the blocks and outputs (default /tmp/orchard-bench)")
    p.add_argument("--worker-memory", type=float, help="pass --worker-memory GB to orchard process (default: its own)")
    args = p.parse_args(argv)
    if args.pulse_rate <= 0 or args.speed <= 0 or not 0 < args.return_fraction <= 1:
        p.error("--pulse-rate and --speed must be positive, --return-fraction in (0, 1]")
    try:
        sizes = [float(s) for s in args.sizes.split(",") if s.strip()]
    except ValueError:
        p.error(f"--sizes must be numbers, got {args.sizes!r}")
    if any(s <= 0 for s in sizes):
        p.error("--sizes must be positive")
    scanner = Scanner(args.pulse_rate, args.speed, args.return_fraction)
    extra = () if args.worker_memory is None else ("--worker-memory", f"{args.worker_memory:g}")
    wanted = [w.strip() for w in args.forms.split(",") if w.strip()]
    forms = {k: v for k, v in FORMS.items() if "all" in wanted or any(w in k for w in wanted)}
    print(f"Scanner: {scanner.pulse_rate:,.0f} pulses/s, {scanner.speed:g} m/s, "
          f"{scanner.return_fraction:g} of the pulses returning from the block.\n")
    print(density_table(scanner, FORMS) + "\n")
    print(HEADER, flush=True)
    vase_name, vase = next(iter(FORMS.items()))
    densities = {}
    for name, sim in forms.items():
        densities[name] = mobile_density(sim, scanner)
        print(block_row(measure_block(args.work_dir, sim.get("form", "vase"), sim, densities[name], extra)), flush=True)
    if sizes:
        density = densities.get(vase_name) or mobile_density(vase, scanner)
        per_tree = scanner.points_per_tree(vase["spacing"], vase["row_spacing"])
        for size in sizes:
            sim = grown(vase, max(1, round(size * 1e6 / per_tree)))
            row = measure_block(args.work_dir, f"vase-{size:g}M", sim, density, extra)
            print(block_row(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
