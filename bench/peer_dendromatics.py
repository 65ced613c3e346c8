"""Tree segmentation with dendromatics (the 3DFin library), run in its own virtualenv.

Usage: ``PYTHON peer_dendromatics.py POINTS.npy OUT.npz CONFIG_JSON``. Imports only
numpy and dendromatics (this project is not installed in that environment). Follows
3DFin's standard processing (``three_d_fin.processing.abstract_processing``): cloth
simulation DTM → normalised heights → stem stripe → verticality clustering → tree
individualisation by distance to the stem axes. Writes per-point tree ids (0 = none),
the stem positions (x, y of the stem centroids in the stripe) and the seconds taken.
"""

import json
import sys
import time

import dendromatics as dm
import numpy as np

NO_ID = 100000  # dendromatics' id for points farther than d_max from every axis


def main(points_path: str, out_path: str, cfg_json: str) -> None:
    cfg = json.loads(cfg_json)
    xyz = np.load(points_path)
    t0 = time.perf_counter()
    cloth = dm.generate_dtm(xyz, cloth_resolution=cfg["res_cloth"])
    dtm = dm.clean_cloth(cloth)
    z0 = dm.normalize_heights(xyz, dtm)
    coords = np.column_stack([xyz, z0])
    lower, upper = cfg["lower_limit"], cfg["upper_limit"]
    stripe = coords[(coords[:, 3] > lower) & (coords[:, 3] < upper), 0:4]
    clust_stripe = dm.verticality_clustering(
        stripe, cfg["verticality_scale"], cfg["verticality_thresh"], cfg["number_of_points"],
        cfg["number_of_iterations"], cfg["res_xy_stripe"], cfg["res_z_stripe"], 5,
    )
    assigned, trees, _heights = dm.individualize_trees(
        coords, clust_stripe, cfg["res_z"], cfg["res_xy"], lower, upper, cfg["height_range"],
        cfg["maximum_d"], cfg["minimum_points"], cfg["distance_to_axis"], cfg["maximum_dev"],
        cfg["res_heights"], 5, 0, 1, 2, tree_id_field=-1,
    )
    seconds = time.perf_counter() - t0
    raw = assigned[:, 4].astype(np.int64)
    tree_id = np.where(raw == NO_ID, 0, raw + 1)  # cluster ids start at 0
    trees = np.asarray(trees).reshape(len(trees), -1) if len(trees) else np.zeros((0, 9))
    stems = trees[:, [0, 4, 5]] if len(trees) else np.zeros((0, 3))
    np.savez(out_path, tree_id=tree_id, stems=stems, seconds=seconds)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3])
