"""``python -m bench.paper_setting``: the paper's method on the paper's own setting, and why
it collapses on our blocks.

The paper's virtual stands (SimTreeLS) are trees on bare, flat ground, 6 m apart in rows
8 m apart, with σ = 0.02 m of noise; it reports trunk F1 0.687 and v-measure 0.884 on
them. Our accuracy blocks add grass patches, a slope with undulations, fence posts, a
vehicle and a bin, outliers and registration ghosting. This bench generates the paper's
setting and adds our block's features back one group at a time, and runs on each block
the paper as published (``bench.baselines.paper_as_published``), the same with its
trunk-finding sources taken only 1 m or more above the ground, and ours (defaults).
Evaluation seeds 0..N-1; nothing here was tuned.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

#: the paper's virtual setting: 6 m in the row, 8 m between rows, sigma 0.02 m
PAPER = dict(rows=2, trees_per_row=4, spacing=6.0, row_spacing=8.0, noise=0.02)
#: SimTreeLS stands: bare flat ground, nothing but trees
BARE = dict(posts=False, vehicle=False, bin=False, grass=0.0, slope=0.0, undulation=0.0, outliers=0.0, ghosting=0.0)
VARIANTS: dict[str, dict] = {
    "paper's setting (bare flat ground, trees only)": BARE,
    "+ grass (our blocks' patches)": {**BARE, "grass": 0.5},
    "+ posts, a vehicle and a bin": {**BARE, "posts": True, "vehicle": True, "bin": True},
    "our block at the paper's spacing (all of the above, slope, outliers, ghosting)": {},
}
#: the sources' height floor of the second paper variant [m]
SOURCE_MIN_HEIGHT = 1.0


def score_block(name: str, seed: int) -> dict:
    """Each method on one block: {method: (trunk F1, precision, recall, found, v-measure)}."""
    from bench.baselines import paper_as_published
    from pipeline.params import PipelineParams
    from pipeline.process import process_points
    from simulator.scoring.scores import score_labels
    from simulator.simparams import SimulationParams
    from simulator.simulate import simulate_orchard

    o = simulate_orchard(SimulationParams(**PAPER, **VARIANTS[name], seed=seed))
    origin = np.floor(o.xyz.min(axis=0))
    xyz = o.xyz - origin
    params = PipelineParams()
    runs = {
        "paper as published": lambda: paper_as_published(xyz, params=params),
        f"paper, sources ≥ {SOURCE_MIN_HEIGHT:g} m up": lambda: paper_as_published(
            xyz, params=params, source_min_height=SOURCE_MIN_HEIGHT),
        "ours": lambda: process_points(xyz, params=params),
    }
    out = {}
    for method, run in runs.items():
        t = time.perf_counter()
        r = run()
        s = score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=o.trunks[:, :2] - origin[:2],
                         pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=np.asarray(r.trunks)[:, :2])
        out[method] = (s["trunk_f1"], s["trunk_precision"], s["trunk_recall"], len(r.trunks), s["v_measure"],
                       time.perf_counter() - t)
    return {"n_trees": len(o.trunks), "methods": out}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.paper_setting", description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=2, help="evaluation seeds 0..N-1 (default 2)")
    args = p.parse_args(argv)
    print("| block | seed | method | trunks found (true) | trunk precision | trunk recall | trunk F1 | v-measure |")
    print("|---|---|---|---|---|---|---|---|")
    for name in VARIANTS:
        for seed in range(args.seeds):
            res = score_block(name, seed)
            for method, (f1, prec, rec, found, vm, _) in res["methods"].items():
                print(f"| {name} | {seed} | {method} | {found} ({res['n_trees']}) | {prec:.2f} | {rec:.2f} | {f1:.2f} | {vm:.3f} |",
                      flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
