"""Trellised rows: trellis posts among the trees, the post test off and on.

    python -m bench.trellis [--seeds 10] [--radius 0.08]

On the issue's two accuracy settings (``bench.oracles.SETTINGS``) it generates each
block without and with a trellis (``--trellis 2``: a post 2.8-3.2 m tall at both row
ends and in every second gap between trees, wires at 0.8, 1.6 and 2.4 m) and scores the
pipeline with the post test off, at its default (on where the measured in-row spacing
is 1.8 m or more) and on (``--trunks-max-post-radius``), over evaluation seeds 0..N-1
(2 rows each). Prints a
Markdown table: true trunks found, false trunks, pooled trunk F1, the mean v-measure on
true tree points with the lowest and highest block in brackets, and the share of the
trellis's points (posts and wires) that were put in a tree.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from bench import shoots
from bench.oracles import SETTINGS
from simulator.scoring.scores import score_labels
from pipeline.params import PipelineParams
from pipeline.process import process_points
from simulator.orchard import POST
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

#: the simulator's trellis setting of the blocks with a trellis
TRELLIS = 2


@dataclass(frozen=True)
class Score(shoots.Score):
    """One block under one setting of the post test."""

    post_in_tree: float  # share of the trellis's points in a tree (NaN: no trellis)


def score_block(sim: dict, seed: int, trellis: int, radii: tuple[float, ...]) -> list[Score]:
    """Generate one block; score the pipeline on it with the post test at each of ``radii``."""
    o = simulate_orchard(SimulationParams(seed=seed, trellis=trellis, **sim))
    origin = np.floor(o.xyz.min(axis=0))
    xyz = o.xyz - origin
    # the simulator's fence posts stand beyond the first alley; the trellis's posts and wires in the rows
    row_spacing = SimulationParams(**sim).row_spacing
    in_rows = (o.kind == POST) & (o.xyz[:, 1] > o.trunks[:, 1].min() - 0.5 * row_spacing)
    out = []
    for radius in radii:
        r = process_points(xyz, params=PipelineParams.model_validate({"trunks": {"max_post_radius": radius}}))
        s = score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=o.trunks - origin,
                         pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks)
        share = float((r.tree_id[in_rows] > 0).mean()) if in_rows.any() else float("nan")
        out.append(Score(s["trunk_tp"], s["trunk_fp"], s["trunk_fn"], s["v_measure"], share))
    return out


def table_row(setting: str, trellis: str, test: str, scores: list[Score]) -> str:
    """One Markdown row: totals over the blocks, pooled F1, mean [min, max] v-measure,
    mean share of trellis points in trees."""
    share = np.array([s.post_in_tree for s in scores])
    posts = "–" if np.isnan(share).all() else f"{np.nanmean(share) * 100:.0f} %"
    return f"| {setting} | {trellis} | {test} | {shoots.totals(scores)} | {posts} |"


HEADER = (
    "| setting | trellis | post test | blocks | trunks found | false trunks | trunk F1 | v-measure | trellis points in trees |\n"
    "|---|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.trellis", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10, help="evaluation seeds 0..N-1 per setting (default 10)")
    ap.add_argument("--radius", type=float, default=0.08, help="--trunks-max-post-radius of the 'on' rows [m] (default 0.08)")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error("--seeds must be at least 1")
    if not 0 < args.radius <= 1:
        ap.error(f"--radius must be above 0 and at most 1 m, got {args.radius}")
    radii = (0.0, None, args.radius)
    tests = ("off", "default (on where the spacing is 1.8 m or more)", f"on, radius {args.radius:g} m")
    print(HEADER, flush=True)
    for setting, sim in SETTINGS.items():
        for trellis, label in ((0, "none"), (TRELLIS, f"post every {TRELLIS} gaps")):
            blocks = [score_block(sim, seed, trellis, radii) for seed in range(args.seeds)]
            for i, test in enumerate(tests):
                print(table_row(setting, label, test, [b[i] for b in blocks]), flush=True)


if __name__ == "__main__":
    main()
