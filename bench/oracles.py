"""How much of the v-measure gap can a better trunk or wood step close? Oracles.

    python -m bench.oracles [--seeds 2]

On the issue's two accuracy settings (the paper's: sigma 0.02 m, 5 m spacing; high
density: 2.5 m x 4.5 m with low foliage) it prints the v-measure on true tree points of

- ``ours``: the pipeline as shipped;
- ``closest trunk``: every point to the horizontally nearest found trunk;
- ``wood oracle``: shortest paths on our voxel graph from the *true* wood voxels, each
  carrying its *true* tree: what geodesic segmentation gives with perfect trunks and
  perfect wood;
- ``voxel oracle``: every 0.1 m voxel takes its majority true tree: the ceiling of any
  method that labels voxels of this size.

Evaluation seeds (< 1000) only. Prints a Markdown table.
"""

from __future__ import annotations

import argparse

import numpy as np

from pipeline.baselines import closest_trunk
from pipeline.evaluate import v_measure
from pipeline.graph import shortest_paths
from pipeline.params import PipelineParams
from pipeline.process import analyse_nodes, process_points
from pipeline.simulate import SimulationParams, simulate_orchard

SETTINGS = {
    "paper setting (σ 0.02 m, 5 m × 6 m)": dict(rows=2, trees_per_row=4, noise=0.02, spacing=5.0, row_spacing=6.0),
    "high density (2.5 m × 4.5 m, low foliage)": dict(rows=2, trees_per_row=5, spacing=2.5, row_spacing=4.5, low_foliage=True),
}


def oracle_scores(sim: dict, seed: int, params: PipelineParams) -> dict[str, float]:
    o = simulate_orchard(SimulationParams(seed=seed, **sim))
    xyz = o.xyz - np.floor(o.xyz.min(axis=0))
    tree = o.tree_id > 0
    out = {}
    for name, fn in (("ours", process_points), ("closest trunk", closest_trunk)):
        out[name] = v_measure(o.tree_id[tree], fn(xyz, params=params).tree_id[tree])
    a = analyse_nodes(xyz, params=params)
    pv = a.vox.point_voxel
    t = o.tree_id[a.veg_idx]
    counts = np.zeros((a.vox.n, int(o.tree_id.max()) + 1))
    np.add.at(counts, (pv, t), 1)
    majority = counts.argmax(axis=1)
    wood = np.bincount(pv, weights=o.is_wood[a.veg_idx], minlength=a.vox.n) > 0.5 * a.vox.counts
    seeds = np.flatnonzero(wood & (majority > 0))
    sp = shortest_paths(a.graph, seeds)
    node = np.where(sp.source >= 0, majority[np.maximum(sp.source, 0)], 0)
    for name, lab in (("wood oracle", node), ("voxel oracle", majority)):
        pred = np.zeros(o.tree_id.shape[0], np.int64)
        pred[a.veg_idx] = lab[pv]
        out[name] = v_measure(o.tree_id[tree], pred[tree])
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=2, help="evaluation seeds 0..N-1 per setting")
    args = ap.parse_args(argv)
    params = PipelineParams()
    cols = ("ours", "closest trunk", "wood oracle", "voxel oracle")
    print("| setting | seed | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for label, sim in SETTINGS.items():
        for seed in range(args.seeds):
            s = oracle_scores(sim, seed, params)
            print(f"| {label} | {seed} | " + " | ".join(f"{s[c]:.3f}" for c in cols) + " |", flush=True)


if __name__ == "__main__":
    main()
