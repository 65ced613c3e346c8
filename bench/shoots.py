"""Trunk tests against shoots touching down: high-density blocks, each test on and off.

    python -m bench.shoots [--seeds 10] [--noises 0.02,0.05]

On high-density blocks (``bench.oracles.SETTINGS``: 2.5 m x 4.5 m, foliage hanging to
0.2-0.5 m above the grass) bundles of drooping shoots become ground contacts that drain
a crown like a trunk. For each range noise it scores the pipeline with the stem test
(``--trunks-stem-ratio``, on by default) off and on, and with the opt-in foot test
(``--trunks-min-foot-ratio 1.0``) added, over evaluation seeds 0..N-1 (2 x 5 trees each).
Prints a Markdown table: true trunks found, false trunks, pooled trunk F1 and the mean
v-measure on true tree points with the lowest and highest block in brackets.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from bench.oracles import SETTINGS
from simulator.scoring.scores import score_labels
from pipeline.params import PipelineParams
from pipeline.process import process_points
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

HIGH_DENSITY = SETTINGS["high density (2.5 m × 4.5 m, low foliage)"]

VARIANTS = {
    "neither test": {"stem_ratio": 0},
    "stem test (default)": {},
    "stem and foot tests": {"min_foot_ratio": 1.0},
}
"""``TrunkParams`` overrides of each row."""


@dataclass(frozen=True)
class Score:
    """One block under one variant."""

    tp: int
    fp: int
    fn: int
    v_measure: float


def score_blocks(noise: float, seed: int, variants: dict[str, dict] = VARIANTS) -> dict[str, Score]:
    """Generate the high-density block for ``noise`` and ``seed`` once; score every variant on it."""
    o = simulate_orchard(SimulationParams(seed=seed, noise=noise, **HIGH_DENSITY))
    origin = np.floor(o.xyz.min(axis=0))
    xyz = o.xyz - origin
    out = {}
    for name, trunks in variants.items():
        r = process_points(xyz, params=PipelineParams.model_validate({"trunks": trunks}))
        s = score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=o.trunks - origin,
                         pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks)
        out[name] = Score(s["trunk_tp"], s["trunk_fp"], s["trunk_fn"], s["v_measure"])
    return out


def totals(scores: list[Score]) -> str:
    """Markdown cells over the blocks: their number, true trunks found of all, false
    trunks, pooled F1, mean [min, max] v-measure."""
    tp = sum(s.tp for s in scores)
    fp = sum(s.fp for s in scores)
    fn = sum(s.fn for s in scores)
    f1 = 2 * tp / max(2 * tp + fp + fn, 1)
    v = np.array([s.v_measure for s in scores])
    return f"{len(scores)} | {tp} of {tp + fn} | {fp} | {f1:.2f} | {v.mean():.3f} [{v.min():.3f}, {v.max():.3f}]"


def table_row(noise: float, variant: str, scores: list[Score]) -> str:
    """One Markdown row: totals over the blocks, pooled F1, mean [min, max] v-measure."""
    return f"| {noise:g} | {variant} | {totals(scores)} |"


HEADER = (
    "| noise σ [m] | trunk tests | blocks | trunks found | false trunks | trunk F1 | v-measure |\n"
    "|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.shoots", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10, help="evaluation seeds 0..N-1 per noise (default 10)")
    ap.add_argument("--noises", default="0.02,0.05", help="range noise levels [m], comma-separated (default %(default)s)")
    args = ap.parse_args(argv)
    try:
        noises = [float(x) for x in args.noises.split(",") if x.strip()]
        for n in noises:
            SimulationParams(noise=n)
    except ValueError as e:
        ap.error(f"--noises must be comma-separated noise levels from 0 to 0.1 m, got {args.noises!r} ({e})")
    if args.seeds < 1 or not noises:
        ap.error("--seeds must be at least 1 and --noises name at least one level")
    print(HEADER, flush=True)
    for noise in noises:
        blocks = [score_blocks(noise, seed) for seed in range(args.seeds)]
        for variant in VARIANTS:
            print(table_row(noise, variant, [b[variant] for b in blocks]), flush=True)


if __name__ == "__main__":
    main()
