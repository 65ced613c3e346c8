"""Trunks at any spacing: hedgerows, high density and vase blocks, one table.

    python -m bench.hedgerows [--seeds 3] [--fixed] [--post-radius R]

Generates small blocks of every tree form at its in-row spacing (``SETTINGS``: tall
spindle at 1.0 and 1.5 m, hedge at 1.2 and 1.5 m, the high-density vase setting at
2.5 m and the paper's vase setting at 5 m) over evaluation seeds 0..N-1, runs the
pipeline with its defaults (radii that follow the measured spacing) and prints a
Markdown table: true trunks, trunks found, false trunks, pooled trunk precision, recall
and F1, the mean v-measure on true tree points with the lowest and highest block in
brackets, and the range of the measured spacing. Trunks match one-to-one within half the
spacing, at most 1 m. ``--fixed`` adds a row per setting with the free-standing trees'
fixed radii (cluster 0.8 m, satellite 2.0 m, unreached 0.6 m: the defaults before they
followed the spacing); ``--post-radius`` one with the post test on at that radius.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from simulator.scoring.scores import score_labels
from pipeline.params import PipelineParams
from pipeline.process import process_points
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

SETTINGS: dict[str, dict] = {
    "spindle 1.0 m × 3.5 m": dict(form="spindle", rows=2, trees_per_row=14, spacing=1.0, row_spacing=3.5),
    "spindle 1.5 m × 3.5 m": dict(form="spindle", rows=2, trees_per_row=12, spacing=1.5, row_spacing=3.5),
    "hedge 1.2 m × 4 m": dict(form="hedge", rows=2, trees_per_row=12, spacing=1.2, row_spacing=4.0),
    "hedge 1.5 m × 4 m": dict(form="hedge", rows=2, trees_per_row=12, spacing=1.5, row_spacing=4.0),
    "high density vase 2.5 m × 4.5 m, low foliage": dict(rows=2, trees_per_row=5, spacing=2.5, row_spacing=4.5, low_foliage=True),
    "paper setting vase 5 m × 6 m": dict(rows=2, trees_per_row=4, spacing=5.0, row_spacing=6.0, noise=0.02),
}
"""Simulator parameters of each setting (``simulator.simparams.SimulationParams``)."""

FIXED = {"trunks": {"cluster_radius": 0.8, "satellite_radius": 2.0}, "segment": {"unreached_radius": 0.6}}
"""The radii fixed for free-standing trees (the defaults before they followed the spacing)."""


@dataclass(frozen=True)
class Score:
    """One block under one set of parameters."""

    tp: int
    fp: int
    fn: int
    v_measure: float
    spacing: float  # measured in-row spacing [m]; NaN: none


def match_distance(spacing: float) -> float:
    """Trunks match within half the in-row spacing, at most 1 m [m]."""
    return min(1.0, 0.5 * spacing)


def score_block(sim: dict, seed: int, variants: dict[str, dict]) -> dict[str, Score]:
    """Generate one block; score the pipeline on it under each variant's parameters."""
    o = simulate_orchard(SimulationParams(seed=seed, **sim))
    origin = np.floor(o.xyz.min(axis=0))
    xyz = o.xyz - origin
    out = {}
    for name, params in variants.items():
        r = process_points(xyz, params=PipelineParams.model_validate(params))
        s = score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=o.trunks - origin,
                         pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks,
                         match_distance=match_distance(sim["spacing"]))
        spacing = float("nan") if r.spacing is None else r.spacing
        out[name] = Score(s["trunk_tp"], s["trunk_fp"], s["trunk_fn"], s["v_measure"], spacing)
    return out


def table_row(setting: str, variant: str, scores: list[Score]) -> str:
    """One Markdown row: totals over the blocks, pooled precision, recall and F1, mean
    [min, max] v-measure, range of the measured spacing."""
    tp, fp, fn = (sum(getattr(s, f) for s in scores) for f in ("tp", "fp", "fn"))
    precision = tp / max(tp + fp, 1)
    recall = tp / max(tp + fn, 1)
    f1 = 2 * tp / max(2 * tp + fp + fn, 1)
    v = np.array([s.v_measure for s in scores])
    sp = np.array([s.spacing for s in scores])
    spacing = "–" if np.isnan(sp).all() else f"{np.nanmin(sp):.2f}–{np.nanmax(sp):.2f}"
    return (f"| {setting} | {variant} | {len(scores)} | {tp + fn} | {tp + fp} | {fp} | {precision:.3f} | {recall:.3f} | "
            f"**{f1:.3f}** | {v.mean():.3f} [{v.min():.3f}, {v.max():.3f}] | {spacing} |")


HEADER = (
    "| setting | radii | blocks | true trunks | found | false | precision | recall | trunk F1 | v-measure | measured spacing [m] |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.hedgerows", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3, help="evaluation seeds 0..N-1 per setting (default 3)")
    ap.add_argument("--fixed", action="store_true", help="add rows with the fixed radii of free-standing trees")
    ap.add_argument("--post-radius", type=float, default=0.0, help="add rows with the post test on at this radius [m]")
    ap.add_argument("--only", default="", help="run only the settings whose name contains this text")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error("--seeds must be at least 1")
    if not 0 <= args.post_radius <= 1:
        ap.error(f"--post-radius must be between 0 and 1 m, got {args.post_radius}")
    variants: dict[str, dict] = {"follow the spacing (default)": {}}
    if args.fixed:
        variants["fixed (0.8 / 2.0 / 0.6 m)"] = FIXED
    if args.post_radius > 0:
        variants[f"default, post test {args.post_radius:g} m"] = {"trunks": {"max_post_radius": args.post_radius}}
    print(HEADER, flush=True)
    for setting, sim in SETTINGS.items():
        if args.only not in setting:
            continue
        blocks = [score_block(sim, seed, variants) for seed in range(args.seeds)]
        for name in variants:
            print(table_row(setting, name, [b[name] for b in blocks]), flush=True)


if __name__ == "__main__":
    main()
