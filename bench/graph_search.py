"""Time the voxel graph's neighbour search both ways on a block at mobile density.

``python -m bench.graph_search [--rows 2 --trees-per-row 8 --seed 3] [--repeat 5]``

Generates the block (the simulator's default density: a vehicle-mounted scanner in
the alleys), takes its vegetation voxels as the pipeline does, and times, in CPU
seconds (the minimum of ``--repeat`` runs, so other processes on the machine count
less), the pair search at the larger radius and the two matrices built from it: the
k-d tree search with its two-pass symmetric matrix, and the voxel-offset search with
its one-pass matrix. Checks that both give the same arrays.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def _best(fn, repeat: int):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t)
    return best, out


def main(argv: list[str] | None = None) -> None:
    from pipeline.enrichment import neighbourhood_matrix
    from pipeline.graph import build_graph, node_pairs
    from pipeline.ground import classify_ground, ground_model
    from pipeline.reading import read_points
    from pipeline.params import PipelineParams
    from simulator.simparams import SimulationParams
    from simulator.truth import write_simulation
    from pipeline.voxels import voxelize

    ap = argparse.ArgumentParser(prog="python -m bench.graph_search", description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=2)
    ap.add_argument("--trees-per-row", type=int, default=8)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    params = PipelineParams()
    with tempfile.TemporaryDirectory() as tmp:
        las = Path(tmp) / "block.laz"
        sim = SimulationParams(rows=args.rows, trees_per_row=args.trees_per_row, seed=args.seed)
        write_simulation(sim, str(las), str(Path(tmp) / "truth.parquet"))
        xyz, _ = read_points(str(las))
    xyz = xyz - xyz.min(axis=0)
    gm = ground_model(xyz, params=params.ground)
    height, is_ground = classify_ground(xyz, gm, params=params.ground)
    vox = voxelize(xyz[~is_ground & (height > 0)], voxel_size=params.graph.voxel_size)
    nodes = vox.centroids
    edge, smooth = params.graph.edge_radius, params.matter.smoothing_radius
    wide = max(edge, smooth)

    def build(**keys):
        pairs = node_pairs(nodes, wide, **keys)
        return pairs, neighbourhood_matrix(nodes, radius=smooth, candidates=pairs), build_graph(nodes, radius=edge, candidates=pairs)

    voxel = {"keys": vox.keys, "voxel_size": params.graph.voxel_size}
    rows = []
    for name, keys in (("k-d tree", {}), ("voxel offsets", voxel)):
        search, _ = _best(lambda: node_pairs(nodes, wide, **keys), args.repeat)
        total, out = _best(lambda: build(**keys), args.repeat)
        rows.append((name, search, total, out))
    (_, _, _, (p0, a0, g0)), (_, _, _, (p1, a1, g1)) = rows
    same = len(p0) == len(p1) and all(
        np.array_equal(x.indptr, y.indptr) and np.array_equal(x.indices, y.indices) and np.array_equal(x.data, y.data)
        for x, y in ((a0, a1), (g0, g1))
    )
    print(f"{len(xyz):,} points, {len(nodes):,} vegetation voxels, {len(p0):,} pairs within {wide} m")
    print("| search | pair search [s] | search + both matrices [s] |")
    print("|---|---:|---:|")
    for name, search, total, _ in rows:
        print(f"| {name} | {search:.3f} | {total:.3f} |")
    print(f"same matrices: {same}")


if __name__ == "__main__":
    main()
