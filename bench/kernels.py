"""Time two numeric kernels of a tile against the forms they replaced.

``python -m bench.kernels BLOCK.laz [--repeat 5]``

On the block's vegetation voxels, as the pipeline takes them, times in CPU seconds (the
minimum of ``--repeat`` runs, so other processes on the machine count less) and peak
traced memory (``tracemalloc``, which numpy reports its arrays to):

- the packed voxel keys of the vegetation points (``pipeline.voxels.packed_keys``),
  against their packing from (n, 3) arrays;
- ``neighbourhood_max`` over the neighbourhood matrix, against scipy's row maximum of a
  copy of the matrix holding the values.

Both forms of each must give the same arrays, bit for bit (checked).
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np


def _measure(fn, repeat: int):
    """(least CPU seconds of ``repeat`` runs, peak traced bytes of one run, result)."""
    best = float("inf")
    for _ in range(repeat):
        t = time.process_time()
        fn()
        best = min(best, time.process_time() - t)
    tracemalloc.start()
    out = fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return best, peak, out


def _voxel_keys_before(xyz: np.ndarray, voxel_size: float) -> np.ndarray:
    """The packed voxel keys as :func:`pipeline.voxels.voxelize` computed them before."""
    keys = np.empty(xyz.shape, np.int64)
    for d in range(3):
        keys[:, d] = np.floor((xyz[:, d] - 0.0) / voxel_size)
    lo = np.array([keys[:, d].min() for d in range(3)])
    rel = keys - lo
    span = np.array([rel[:, d].max() for d in range(3)]) + 1
    return (rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2]


def _neighbourhood_max_before(values: np.ndarray, adjacency) -> np.ndarray:
    a = adjacency.tocsr(copy=True)
    a.data = values[a.indices].astype(np.float64)
    return np.asarray(a.max(axis=1).todense()).ravel()


def main(argv: list[str] | None = None) -> None:
    from pipeline.enrichment import neighbourhood_matrix
    from pipeline.graph import node_pairs
    from pipeline.ground import classify_ground, ground_model
    from pipeline.params import PipelineParams
    from pipeline.reading import read_points
    from pipeline.voxels import packed_keys, voxelize
    from pipeline.woodleaf import neighbourhood_max

    ap = argparse.ArgumentParser(prog="python -m bench.kernels", description=__doc__.splitlines()[0])
    ap.add_argument("block", help="a LAS/LAZ block")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    params = PipelineParams()
    xyz, _ = read_points(args.block)
    gm = ground_model(xyz, params=params.ground)
    height, is_ground = classify_ground(xyz, gm, params=params.ground)
    veg = np.ascontiguousarray(xyz[~is_ground & (height > 0)])
    size = params.graph.voxel_size
    vox = voxelize(veg, voxel_size=size)
    pairs = node_pairs(vox.centroids, params.matter.smoothing_radius)
    adjacency = neighbourhood_matrix(vox.centroids, radius=params.matter.smoothing_radius, candidates=pairs)
    values = np.random.default_rng(0).random(vox.n)
    print(f"{len(xyz):,} points, {len(veg):,} vegetation points, {vox.n:,} voxels, {len(pairs):,} pairs within "
          f"{params.matter.smoothing_radius} m")
    print("| kernel | before [CPU s] | now [CPU s] | before peak [MB] | now peak [MB] |")
    print("|---|---:|---:|---:|---:|")
    rows = [
        ("packed voxel keys", lambda: _voxel_keys_before(veg, size), lambda: packed_keys(veg, size, (0.0, 0.0, 0.0))[0],
         np.array_equal),
        ("neighbourhood_max", lambda: _neighbourhood_max_before(values, adjacency),
         lambda: neighbourhood_max(values, adjacency), np.array_equal),
    ]
    for name, before, now, same in rows:
        t0, m0, r0 = _measure(before, args.repeat)
        t1, m1, r1 = _measure(now, args.repeat)
        if not same(r0, r1):
            raise SystemExit(f"{name}: the two forms differ")
        print(f"| {name} | {t0:.3f} | {t1:.3f} | {m0 / 1e6:.0f} | {m1 / 1e6:.0f} |")


if __name__ == "__main__":
    main()
