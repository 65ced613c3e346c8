"""Returns far below the ground (multipath) against the ground model.

    python -m bench.multipath [--draws 3]

The bench's 3-tree stand (``bench.speed``: 1 M points, sigma = 0.02 m) is processed
clean, then with a share of its points moved down under the ground: by 2-20 m each
(returns that bounced off something, at scattered depths), or all by 10 m (a ghost
of the ground one depth below it), and with five points 5-15 m down in one 0.25 m cell.
A draw passes when it finds the clean run's trees at the clean heights (within 0.1 m).
Prints a Markdown table of the draws that pass.
"""

from __future__ import annotations

import argparse

import numpy as np

from bench.blocks import stand_density, stand_params
from pipeline.params import PipelineParams
from pipeline.process import process_points
from simulator.simulate import simulate_orchard

SHARES = (0.0002, 0.0005, 0.001, 0.002, 0.005)
"""Shares of the points moved under the ground."""


def _heights(xyz: np.ndarray, params: PipelineParams) -> np.ndarray:
    r = process_points(xyz, params=params)
    return np.array([r.height[r.tree_id == k + 1].max() for k in range(r.n_trees)])


def _passes(xyz: np.ndarray, clean: np.ndarray, params: PipelineParams) -> bool:
    try:
        h = _heights(xyz, params)
    except Exception:  # noqa: BLE001 - "no trees found" and the like: the draw fails
        return False
    return h.shape == clean.shape and bool(np.abs(h - clean).max() < 0.1)


def run(draws: int = 3, min_points: int = 1_000_000) -> list[tuple[str, str, str]]:
    """Rows of (what, scattered depths, one depth): draws passed of ``draws``."""
    orchard = simulate_orchard(stand_params(stand_density(min_points)))
    xyz = orchard.xyz - orchard.xyz.min(axis=0)
    params = PipelineParams()
    clean = _heights(xyz, params)
    rows = []
    for share in SHARES:
        passed = []
        for depth in ("scattered", "one"):
            n = 0
            for seed in range(draws):
                rng = np.random.default_rng(seed)
                moved = xyz.copy()
                pick = rng.choice(len(xyz), int(share * len(xyz)), replace=False)
                moved[pick, 2] -= rng.uniform(2.0, 20.0, len(pick)) if depth == "scattered" else 10.0
                n += _passes(moved, clean, params)
            passed.append(f"{n}/{draws}")
        rows.append((f"{100 * share:.2f} % of the points ({int(share * len(xyz)):,})", *passed))
    n = 0
    for seed in range(draws):
        rng = np.random.default_rng(seed)
        moved = xyz.copy()
        pick = rng.choice(len(xyz), 5, replace=False)
        moved[pick, :2] = moved[pick[0], :2] + rng.uniform(0.0, 0.05, (5, 2))
        moved[pick, 2] -= rng.uniform(5.0, 15.0, 5)
        n += _passes(moved, clean, params)
    rows.append(("5 points 5-15 m down in one cell", f"{n}/{draws}", "-"))
    return rows


def table(rows) -> str:
    out = ["| returns under the ground | scattered depths (2-20 m) | one depth (10 m) |", "|---|---|---|"]
    out += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.multipath", description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=3, help="random draws per cell of the table")
    args = ap.parse_args(argv)
    print(table(run(args.draws)))


if __name__ == "__main__":
    main()
