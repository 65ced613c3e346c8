"""``python -m bench.young``: young, dormant blocks with default settings.

Generated blocks of the ``young`` form (1-2.5 m whips, a stake beside each, no leaves)
at three in-row spacings, blocks of mixed ages, young trees among trellis posts, grown
blocks scanned leafless (dormant) and blocks with irrigation risers, scored the way a
user gets them (``run_job`` writes the Parquet files, ``evaluate_result`` scores them),
and the real young row of ``bench.real_data.young_row``. Evaluation seeds 0-2 by default
(the size floors and the branch test were set on seeds 100-101, the rules for risers on
seeds 100-107).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np

SETTINGS = ((1.0, 3.5), (1.5, 3.5), (2.0, 4.0))
#: blocks of mixed ages: replants (0.3-0.5 times a grown tree) among grown trees of each form;
#: and young trees among trellis posts taller than they are
MIXED = (
    ("vase, 5 m × 6 m, 2 × 6 slots, 30 % replants", dict(form="vase", rows=2, trees_per_row=6, replants=0.3)),
    ("vase, 5 m × 6 m, 2 × 6 slots, 50 % replants", dict(form="vase", rows=2, trees_per_row=6, replants=0.5)),
    ("tall spindle, 1.0 m × 3.5 m, 2 × 12 slots, 30 % replants",
     dict(form="spindle", rows=2, trees_per_row=12, spacing=1.0, row_spacing=3.5, replants=0.3)),
    ("hedge, 1.5 m × 4 m, 2 × 10 slots, 30 % replants",
     dict(form="hedge", rows=2, trees_per_row=10, spacing=1.5, row_spacing=4.0, replants=0.3)),
    ("young, dormant, trellised (a 2.8-3.2 m post every 2 gaps, wires), 1 m × 3.5 m, 2 × 8 trees",
     dict(form="young", rows=2, trees_per_row=8, spacing=1.0, row_spacing=3.5, trellis=2)),
)
#: grown blocks scanned in winter (leafless), and irrigation risers (0.3-1.0 m pipes by 30 % of
#: the trees and in 30 % of the gaps) among young and grown trees
DORMANT = (
    ("vase, leafless, 5 m × 6 m, 2 × 6 trees", dict(form="vase", rows=2, trees_per_row=6, leafless=True)),
    ("tall spindle, leafless, 1.0 m × 3.5 m, 2 × 12 trees",
     dict(form="spindle", rows=2, trees_per_row=12, spacing=1.0, row_spacing=3.5, leafless=True)),
    ("hedge, leafless, 1.5 m × 4 m, 2 × 10 trees",
     dict(form="hedge", rows=2, trees_per_row=10, spacing=1.5, row_spacing=4.0, leafless=True)),
    ("young, dormant, risers, 1 m × 3.5 m, 2 × 8 trees",
     dict(form="young", rows=2, trees_per_row=8, spacing=1.0, row_spacing=3.5, risers=0.3)),
    ("young, dormant, risers, 2 m × 4 m, 2 × 10 trees",
     dict(form="young", rows=2, trees_per_row=10, spacing=2.0, row_spacing=4.0, risers=0.3)),
    ("vase, risers, 5 m × 6 m, 2 × 6 trees", dict(form="vase", rows=2, trees_per_row=6, risers=0.3)),
)


def score(work: Path, spacing: float, row_spacing: float, seed: int) -> dict:
    return score_block(work, f"young-{spacing:g}", dict(form="young", rows=2, trees_per_row=10, spacing=spacing,
                                                        row_spacing=row_spacing), seed)


def score_block(work: Path, name: str, options: dict, seed: int) -> dict:
    """One generated block of ``options`` scored from the product path's outputs."""
    from bench.blocks import make_block
    from pipeline.errors import NoTreesError
    from simulator.scoring.result import evaluate_result
    from pipeline.jobparams import JobParams
    from pipeline.params import PipelineParams
    from simulator.simparams import SimulationParams
    from workers.job import run_job
    from workers.jobspec import JobSpec

    block = make_block(work, name, SimulationParams(**options, seed=seed))
    out = work / "young-results" / Path(block.las).stem
    shutil.rmtree(out, ignore_errors=True)
    try:
        run_job(JobSpec(input_path=block.las, out_dir=str(out), job=JobParams(pipeline=PipelineParams())))
        return evaluate_result(block.truth, str(out))
    except NoTreesError:
        return {"trunk_f1": 0.0, "v_measure": 0.0}
    finally:
        shutil.rmtree(out, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.young", description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3, help="evaluation seeds 0..N-1 (default 3)")
    p.add_argument("--work-dir", type=Path, default=Path("/tmp/orchard-bench"))
    p.add_argument("--mixed-only", action="store_true", help="only the blocks of mixed ages (and young among posts)")
    p.add_argument("--dormant-only", action="store_true", help="only the leafless grown blocks and the blocks with risers")
    args = p.parse_args(argv)
    tables = []
    if not args.dormant_only:
        tables.append(("block of mixed ages, or young among posts", "mixed", MIXED))
    if not args.mixed_only:
        tables.append(("grown block leafless, or with irrigation risers", "dormant", DORMANT))
    for header, prefix, blocks in tables:
        print(f"| {header} | seeds | trunk F1 per block | v-measure per block |")
        print("|---|---|---|---|")
        for name, options in blocks:
            rs = [score_block(args.work_dir, f"{prefix}-{options['form']}", options, s) for s in range(args.seeds)]
            f1 = ", ".join(f"{r['trunk_f1']:.2f}" for r in rs)
            vm = ", ".join(f"{r['v_measure']:.3f}" for r in rs)
            print(f"| {name} | 0–{args.seeds - 1} | {f1} | {vm} |", flush=True)
        print()
    if args.mixed_only or args.dormant_only:
        return 0
    print("| block | seeds | trunk F1 per block | v-measure per block |")
    print("|---|---|---|---|")
    for spacing, row_spacing in SETTINGS:
        rs = [score(args.work_dir, spacing, row_spacing, s) for s in range(args.seeds)]
        f1 = ", ".join(f"{r['trunk_f1']:.2f}" for r in rs)
        vm = ", ".join(f"{r['v_measure']:.3f}" for r in rs)
        print(f"| young, dormant, {spacing:g} m × {row_spacing:g} m, 20 trees | 0–{args.seeds - 1} | {f1} | {vm} |")
    from bench.real_data import REAL, _local, young_row
    from simulator.scoring.scores import score_labels
    from pipeline.params import PipelineParams
    from pipeline.process import process_points

    if (REAL / "AdTree").is_dir():
        f1, vm = [], []
        for seed in range(2):
            xyz, tid, bases = young_row(seed)
            org = np.floor(xyz.min(axis=0))
            r = process_points(_local(xyz), params=PipelineParams())
            s = score_labels(true_tree_id=tid, true_is_wood=np.zeros(len(tid), bool), true_trunks=bases[:, :2] - org[:2],
                             pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks[:, :2])
            f1.append(s["trunk_f1"])
            vm.append(s["v_measure"])
        print(f"| real trees scaled to 1.4–2.2 m, 0.9 m × 3.2 m, stakes (bench.real_data.young_row) | 0–1 | "
              f"{', '.join(f'{x:.2f}' for x in f1)} | {', '.join(f'{x:.3f}' for x in vm)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
