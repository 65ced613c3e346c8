"""Scoring a processed block (its result folder) against its simulation's truth file."""

from __future__ import annotations

import os

import numpy as np

from pipeline.errors import InputError
from simulator.scoring.addresses import score_layout
from simulator.scoring.scores import diameter_errors, score_labels


def _read_points_labels(path: str, n: int) -> tuple[np.ndarray, np.ndarray, int]:
    """tree_id and is_wood of points.parquet scattered to (n,) arrays by point_index;
    points absent from the file are tree 0, not wood. Also returns how many are absent."""
    from pipeline.parquet import read_parquet_columns

    table, meta = read_parquet_columns(path, ["point_index", "tree_id", "is_wood"], what="points.parquet")
    idx = table["point_index"].astype(np.int64)
    if len(idx) and (idx.min() < 0 or idx.max() >= n):
        raise InputError(f"{path} has point_index values outside the truth's 0..{n - 1}: is it the result of another block?")
    # `orchard process` writes every point of its block, unless tiles failed (a partial
    # result says which): fewer points than the truth's means another (smaller) block
    complete = b"orchard:input" in meta and b"orchard:failed_tiles" not in meta
    if complete and len(idx) != n:
        raise InputError(
            f"{path} holds {len(idx)} points and the truth {n}: is it the result of another block?"
        )
    tree_id = np.zeros(n, dtype=np.int64)
    is_wood = np.zeros(n, dtype=bool)
    tree_id[idx] = table["tree_id"]
    is_wood[idx] = table["is_wood"]
    seen = np.zeros(n, dtype=bool)
    seen[idx] = True
    return tree_id, is_wood, int(n - np.count_nonzero(seen))


def evaluate_result(truth_path: str, result_dir: str, *, match_distance: float = 1.0) -> dict:
    """Score a processed block against its simulation truth.

    Parameters
    ----------
    truth_path : str
        Truth Parquet written by :func:`simulator.truth.write_simulation`.
    result_dir : str
        Folder with ``trees.parquet`` (``trunk_x``, ``trunk_y``, absolute) and
        ``points.parquet`` (``point_index``, ``tree_id``, ``is_wood``).
    match_distance : float
        Largest trunk match distance [m].

    Returns
    -------
    dict
        The metrics of :func:`~simulator.scoring.scores.score_labels` plus ``n_missing_points`` (truth points
        absent from points.parquet; they count as tree 0, not wood) and, where the truth
        carries trunk radii and trees.parquet a ``trunk_diameter_m`` column, those of
        :func:`~simulator.scoring.scores.diameter_errors` (the truth's radius is at 0.3 m above the trunk base, the
        default ``metrics.trunk_height``).

    Raises
    ------
    InputError
        Missing or unreadable files, or point indices that do not fit the truth.
    """
    from pipeline.parquet import read_trees_parquet
    from simulator.truth import read_truth

    trees_path = os.path.join(result_dir, "trees.parquet")
    points_path = os.path.join(result_dir, "points.parquet")
    for p in (truth_path, trees_path, points_path):
        if not os.path.exists(p):
            raise InputError(f"{p} does not exist (expected a truth file and a result folder from `orchard process`)")
    truth, true_trunks = read_truth(truth_path)
    n = len(truth["tree_id"])
    if n and not np.array_equal(truth["point_index"], np.arange(n, dtype=truth["point_index"].dtype)):
        raise InputError(f"{truth_path}: point_index is not 0..{n - 1}")
    try:
        trees, _ = read_trees_parquet(trees_path)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is bad input
        raise InputError(f"{trees_path} is not a readable trees.parquet ({str(exc).splitlines()[0]})") from None
    if "trunk_x" not in trees or "trunk_y" not in trees:
        raise InputError(f"{trees_path} has no trunk_x/trunk_y columns")
    found = np.c_[np.asarray(trees["trunk_x"], dtype=np.float64), np.asarray(trees["trunk_y"], dtype=np.float64)]
    pred_tree, pred_wood, missing = _read_points_labels(points_path, n)
    out = score_labels(
        true_tree_id=truth["tree_id"],
        true_is_wood=truth["is_wood"],
        true_trunks=true_trunks,
        pred_tree_id=pred_tree,
        pred_is_wood=pred_wood,
        found_trunks=found,
        match_distance=match_distance,
    )
    out["n_missing_points"] = missing
    out.update(score_layout(truth_path, result_dir, trees, match_distance=match_distance))
    radius = truth.get("trunk_radius")
    if "trunk_diameter_m" in trees and radius is not None and len(radius) == len(true_trunks):
        out.update(diameter_errors(true_trunks, 2.0 * radius, found, np.asarray(trees["trunk_diameter_m"], dtype=np.float64),
                                   match_distance=match_distance))
    return out
