"""How does segmentation accuracy depend on how far crowns reach into each other?

    python -m bench.overlap [--seeds 4] [--ratios 0.4,0.45,0.5,0.55,0.6]

The issue's accuracy targets are measured on generated blocks whose crowns overlap; how
much they overlap is a simulator setting, ``SimulationParams.crown_radius`` (default
0.55 x the in-row spacing, with twigs and leaves filling an envelope 1.12 times that
wide, so every tree reaches past the midpoint into its neighbours' crowns). This sweep
keeps everything else of the issue's two settings (``bench.oracles.SETTINGS``) and
varies that radius, to show where the pipeline meets the targets and where it does not.

For each crown radius (as a multiple of the spacing) it prints the mean over the seeds of

- ``beyond midpoint``: the share of tree points lying horizontally closer to another
  tree's trunk than to their own (``bench.oracles.midpoint_ratio`` > 0.5): how much
  material a closest-trunk split must get wrong;
- trunk F1 and the v-measure on true tree points of the pipeline (``ours``) and of the
  closest-trunk baseline, with the lowest and highest block in brackets.

Evaluation seeds (< 1000) only; the simulator itself is not changed. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np
from pydantic import ValidationError

from bench.baselines import nearest_trunk_labels
from bench.oracles import SETTINGS, overlap_shares
from simulator.scoring.scores import score_labels
from pipeline.params import PipelineParams
from pipeline.process import process_points
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

DEFAULT_RATIOS = (0.4, 0.45, 0.5, 0.55, 0.6)
"""Crown radii of the sweep, as multiples of the in-row spacing (0.55 is the simulator's default)."""


@dataclass(frozen=True)
class BlockScore:
    """One generated block of the sweep."""

    ratio: float
    seed: int
    beyond_midpoint: float
    trunk_f1: float
    v_measure: float
    v_measure_closest: float


def sim_params(sim: dict, ratio: float, seed: int) -> SimulationParams:
    """The setting ``sim`` with crown radius ``ratio`` x its in-row spacing."""
    spacing = sim.get("spacing", SimulationParams.model_fields["spacing"].default)
    return SimulationParams(seed=seed, crown_radius=ratio * spacing, **sim)


def score_block(sim: dict, ratio: float, seed: int, params: PipelineParams) -> BlockScore:
    """Generate one block with crown radius ``ratio`` x spacing and score both methods.

    Parameters
    ----------
    sim : dict — ``SimulationParams`` fields of the setting (``spacing`` among them, or its default)
    ratio : float — crown radius as a multiple of the in-row spacing
    seed : int
    params : PipelineParams
    """
    o = simulate_orchard(sim_params(sim, ratio, seed))
    origin = np.floor(o.xyz.min(axis=0))
    xyz = o.xyz - origin
    trunks = o.trunks - origin
    result = process_points(xyz, params=params)
    ours, closest = (
        score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=trunks,
                     pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks)
        for r in (result, nearest_trunk_labels(xyz, result))
    )
    return BlockScore(ratio, seed, overlap_shares(o)["all"], ours["trunk_f1"], ours["v_measure"], closest["v_measure"])


def table_rows(label: str, blocks: list[BlockScore]) -> list[str]:
    """Markdown rows, one per crown radius: means over the seeds, [lowest, highest] block."""

    def cell(v: np.ndarray, digits: int = 3) -> str:
        return f"{v.mean():.{digits}f} [{v.min():.{digits}f}, {v.max():.{digits}f}]"

    rows = []
    for ratio in sorted({b.ratio for b in blocks}):
        bs = [b for b in blocks if b.ratio == ratio]
        col = {k: np.array([getattr(b, k) for b in bs]) for k in ("beyond_midpoint", "trunk_f1", "v_measure", "v_measure_closest")}
        rows.append(
            f"| {label} | {ratio:.2f} | {len(bs)} | {100 * col['beyond_midpoint'].mean():.1f} % | "
            f"{cell(col['trunk_f1'], 2)} | {cell(col['v_measure'])} | {cell(col['v_measure_closest'])} |"
        )
    return rows


HEADER = (
    "| setting | crown radius ÷ spacing | blocks | beyond midpoint | trunk F1 | v-measure, ours | v-measure, closest trunk |\n"
    "|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.overlap", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=4, help="evaluation seeds 0..N-1 per setting and radius (default 4)")
    ap.add_argument("--ratios", default=",".join(str(r) for r in DEFAULT_RATIOS),
                    help="crown radii as multiples of the in-row spacing, comma-separated (default %(default)s)")
    args = ap.parse_args(argv)
    try:
        ratios = [float(x) for x in args.ratios.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--ratios must be comma-separated numbers, got {args.ratios!r}")
    if args.seeds < 1 or not ratios:
        ap.error("--seeds must be at least 1 and --ratios name at least one radius")
    for sim in SETTINGS.values():
        for r in ratios:
            try:
                sim_params(sim, r, 0)
            except ValidationError as e:
                ap.error(f"--ratios {r}: not a crown radius the simulator accepts ({e.errors()[0]['msg']})")
    params = PipelineParams()
    print(HEADER, flush=True)
    for label, sim in SETTINGS.items():
        blocks = [score_block(sim, r, s, params) for r in ratios for s in range(args.seeds)]
        print("\n".join(table_rows(label, blocks)), flush=True)


if __name__ == "__main__":
    main()
