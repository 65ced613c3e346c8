"""The memory budget's constants against measured tiles.

    python -m bench.budget BLOCK.laz --tile-size M --per-tile > BLOCK.jsonl   # per block
    python -m bench.budget_fit BLOCK.jsonl [...] [--constants FIXED,POINT,NODE ...]

Reads the per-tile lines of :mod:`bench.budget` (one worker ran each block's tiles in
tile order), fits ``peak = fixed + a * points + b * voxels`` by least squares on the
tiles that raised their worker's peak (a tile below an earlier one's peak starts on
the heap that one left, and is bounded by it), and prints one Markdown row per tile:
its points, voxels, the worker's resident memory as it began and its peak, and what
:func:`pipeline.budget.bytes_needed` (or each ``--constants``) estimates, with the
estimate's ratio to the peak. Then the least ratio over the tiles that raised the peak
and over all, and the points of the largest tile each rule allows at 2 GB for 0.04,
0.062 and 0.38 voxels a point (a mobile spindle, a vase block, a sparse orchard).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pipeline import budget


def read_tiles(paths: list[str]) -> list[dict]:
    """Each file's tile lines, with ``run`` (the file's stem) and ``raised``: its peak is
    above every earlier tile's of the same file."""
    tiles = []
    for path in paths:
        highest = 0
        for line in Path(path).read_text().splitlines():
            row = json.loads(line)
            if "tile" not in row:
                continue
            row.update(run=Path(path).stem, raised=row["peak"] > highest)
            highest = max(highest, row["peak"])
            tiles.append(row)
    return tiles


def fit(tiles: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """(fixed [B], per point [B], per voxel [B]) and the residuals [B] of the least-squares fit."""
    a = np.array([[1.0, t["points"], t["voxels"]] for t in tiles])
    y = np.array([float(t["peak"]) for t in tiles])
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    return coef, y - a @ coef


def estimate(constants: tuple[float, float, float], points: float, voxels: float) -> float:
    fixed, per_point, per_node = constants
    return fixed + per_point * points + per_node * min(voxels, points)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.budget_fit", description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", help="JSON lines of python -m bench.budget --per-tile")
    ap.add_argument("--constants", action="append", default=[], metavar="FIXED,POINT,NODE",
                    help="bytes: fixed, per point, per node (default: pipeline.budget's)")
    args = ap.parse_args(argv)
    rules = [(budget.FIXED_BYTES, budget.BYTES_PER_POINT, budget.BYTES_PER_NODE)]
    rules += [tuple(float(v) for v in c.split(",")) for c in args.constants]
    tiles = read_tiles(args.files)
    raised = [t for t in tiles if t["raised"]]
    coef, res = fit(raised)
    print(f"least squares on the {len(raised)} tiles that raised their worker's peak: {coef[0] / 1e6:.0f} MB + "
          f"{coef[1]:.1f} B a point + {coef[2]:.1f} B a voxel (residuals {res.min() / 1e6:+.0f} to {res.max() / 1e6:+.0f} MB)\n")
    names = [f"{f / 1e6:.0f} MB + {p:g} B + {n:g} B" for f, p, n in rules]
    print("| block run | tile | points | voxels | voxels a point | resident at start [MB] | peak [MB] | raised | "
          + " | ".join(f"estimate, {n} [MB] (÷ peak)" for n in names) + " |")
    print("|---|---:|---:|---:|---:|---:|---:|---|" + "---:|" * len(rules))
    for t in tiles:
        cells = [f"{estimate(r, t['points'], t['voxels']) / 1e6:,.0f} ({estimate(r, t['points'], t['voxels']) / t['peak']:.2f})" for r in rules]
        print(f"| {t['run']} | {t['tile']} | {t['points']:,} | {t['voxels']:,} | {t['voxels'] / max(t['points'], 1):.3f} | "
              f"{t['rss_before'] / 1e6:,.0f} | {t['peak'] / 1e6:,.0f} | {'yes' if t['raised'] else ''} | " + " | ".join(cells) + " |")
    print()
    for name, r in zip(names, rules):
        low_raised = min(estimate(r, t["points"], t["voxels"]) / t["peak"] for t in raised)
        low_all = min(estimate(r, t["points"], t["voxels"]) / t["peak"] for t in tiles)
        most = ", ".join(f"{(2e9 - r[0]) / (r[1] + v * r[2]) / 1e6:.2f} M at {v}" for v in (0.04, 0.062, 0.38))
        print(f"{name}: estimate ÷ peak at least {low_raised:.2f} (tiles that raised the peak), {low_all:.2f} (all); "
              f"largest tile at 2 GB: {most} voxels a point")
    return 0


if __name__ == "__main__":
    sys.exit(main())
