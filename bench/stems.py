"""Trunk diameters of the stem-circle fit, plain against solid, on generated blocks.

    python -m bench.stems [--seeds 0,1] [--settings all]

Generates each setting's block for each seed, runs the pipeline with its defaults and
keeps what :func:`pipeline.metrics.trunk_circles` is given (the labelled points and the
detected trunks), then fits each tree's slice at 0.3 m twice: the plain circle (the fit before
``solid``: support only, the search run again with the noise band) and the solid one
(points deep inside count against a circle, the refit stays with it), which the
pipeline uses. Found trunks are matched to the nearest true trunk within 0.5 m; the
table gives, per setting, the trees compared, the mean absolute diameter error, the
bias, and the trees off by more than 3 and 10 cm. Evaluation seeds are 0-999; the
solid fit's ``SOLID_INSIDE_BANDS`` was chosen on seeds from 1000.
"""

from __future__ import annotations

import argparse
from contextlib import contextmanager

import numpy as np

import pipeline.blockresult as blockresult
from pipeline.process import process_points
from pipeline.metrics import trunk_circles
from pipeline.params import PipelineParams
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

SETTINGS: dict[str, dict] = {
    "spindle 1.0 m × 3.5 m": dict(form="spindle", rows=2, trees_per_row=14, spacing=1.0, row_spacing=3.5),
    "spindle 1.0 m × 3.5 m, mobile density": dict(form="spindle", rows=1, trees_per_row=12, spacing=1.0,
                                                  row_spacing=3.5, density=3.0),
    "hedge 1.35 m × 4 m": dict(form="hedge", rows=2, trees_per_row=12, spacing=1.35, row_spacing=4.0),
    "hedge 1.35 m × 4 m, mobile density": dict(form="hedge", rows=1, trees_per_row=10, spacing=1.35, row_spacing=4.0,
                                               density=3.0),
    "vase 5 m × 6 m, σ 0.02 m": dict(rows=2, trees_per_row=4, spacing=5.0, row_spacing=6.0, noise=0.02),
    "vase 4 m × 6 m, σ 0.05 m": dict(rows=2, trees_per_row=4, spacing=4.0, row_spacing=6.0, noise=0.05),
    "vase 5 m × 6 m, σ 0.1 m": dict(rows=2, trees_per_row=4, spacing=5.0, row_spacing=6.0, noise=0.1),
}
"""Simulator parameters of each setting (``SimulationParams`` fields, no seed)."""

MATCH = 0.5
"""A found trunk is compared with the nearest true trunk within this distance [m]."""


@contextmanager
def _kept_inputs(kept: dict):
    """Keep the arguments of the pipeline's ``trunk_circles`` call in ``kept``."""
    original = blockresult.trunk_circles

    def keeping(xyz, tree_id, trunks, **kwargs):
        kept.update(xyz=xyz, tree_id=tree_id, trunks=trunks.copy(), kwargs=kwargs)
        return original(xyz, tree_id, trunks, **kwargs)

    blockresult.trunk_circles = keeping
    try:
        yield
    finally:
        blockresult.trunk_circles = original


def errors(sim: dict, seed: int) -> dict[str, np.ndarray]:
    """Diameter errors [m] of the plain and the solid fit on one generated block."""
    o = simulate_orchard(SimulationParams(seed=seed, **sim))
    origin = np.floor(o.xyz.min(axis=0))
    kept: dict = {}
    params = PipelineParams()
    with _kept_inputs(kept):
        process_points(o.xyz - origin, params=params)
    if "trunks" not in kept:
        return {"plain": np.zeros(0), "solid": np.zeros(0)}
    trunks, truth = kept["trunks"], o.trunks - origin
    dist = np.hypot(trunks[:, None, 0] - truth[None, :, 0], trunks[:, None, 1] - truth[None, :, 1])
    nearest = dist.argmin(axis=1)
    matched = dist[np.arange(len(trunks)), nearest] < MATCH
    true_d = 2 * np.broadcast_to(o.trunk_radius, (len(truth),))[nearest[matched]]
    out = {}
    for name, solid in (("plain", False), ("solid", True)):
        _, d = trunk_circles(kept["xyz"], kept["tree_id"], trunks, **{**kept["kwargs"], "solid": solid})
        out[name] = d[matched] - true_d
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1", help="comma-separated simulator seeds (evaluation: below 1000)")
    ap.add_argument("--settings", default="all", help="comma-separated setting names, or all")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    names = list(SETTINGS) if args.settings == "all" else [s.strip() for s in args.settings.split(",")]
    print("| setting | seeds | trees | fit | not measured | bias [cm] | mean abs. error [cm] | off > 3 cm | off > 10 cm |")
    print("|---|---|---:|---|---:|---:|---:|---:|---:|")
    for name in names:
        runs = [errors(SETTINGS[name], seed) for seed in seeds]
        for fit in ("plain", "solid"):
            e = np.concatenate([r[fit] for r in runs])
            ok = np.isfinite(e)
            a = np.abs(e[ok])
            print(f"| {name} | {args.seeds} | {len(e)} | {fit} | {int((~ok).sum())} | {100 * e[ok].mean():+.2f} | "
                  f"{100 * a.mean():.2f} | {int((a > 0.03).sum())} | {int((a > 0.10).sum())} |", flush=True)


if __name__ == "__main__":
    main()
