"""Accuracy of row addresses and empty slots against a simulator's planting plan.

Addresses are compared "up to the numbering rule": the simulator numbers its rows and
slots its own way, so a found numbering is right when it equals the true one after one
renumbering of the rows for the whole block (same or reversed order, shifted) and one of
the positions per row (same or reversed direction, shifted).
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from simulator.scoring.scores import trunk_scores


def _best_affine(found: np.ndarray, true: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Which of ``mask``'s entries satisfy ``true = ±found + c`` for the sign and shift
    that the most of them satisfy."""
    best = np.zeros(len(found), dtype=bool)
    for sign in (1, -1):
        if not mask.any():
            break
        shift, _ = Counter((true[mask] - sign * found[mask]).tolist()).most_common(1)[0]
        ok = mask & (true == sign * found + shift)
        if ok.sum() > best.sum():
            best = ok
    return best


def address_scores(
    true_xy: np.ndarray,
    true_row: np.ndarray,
    true_slot: np.ndarray,
    found_xy: np.ndarray,
    found_row: np.ndarray,
    found_position: np.ndarray,
    *,
    match_distance: float = 1.0,
    pairs: np.ndarray | None = None,
) -> dict:
    """Share of the found trees (matched to a true tree) that carry their true address.

    Parameters
    ----------
    true_xy : (k, 2) float64
        True trunk positions [m]; ``true_row``, ``true_slot`` (k,) their planting plan.
    found_xy : (m, 2) float64
        Found trunk positions [m]; ``found_row``, ``found_position`` (m,) their addresses.
    match_distance : float
        Largest trunk match distance [m].
    pairs : (p, 2) int64, optional
        The trunk matching (true index, found index) when already made
        (:func:`simulator.scoring.scores.trunk_scores`); made here otherwise.

    Returns
    -------
    dict
        ``address_accuracy`` (correct / matched, NaN without a match), ``n_matched``,
        ``n_correct``.
    """
    if pairs is None:
        pairs = trunk_scores(true_xy, found_xy, match_distance=match_distance)["pairs"]
    if not len(pairs):
        return {"address_accuracy": float("nan"), "n_matched": 0, "n_correct": 0}
    t_row = np.asarray(true_row)[pairs[:, 0]].astype(np.int64)
    t_slot = np.asarray(true_slot)[pairs[:, 0]].astype(np.int64)
    f_row = np.asarray(found_row)[pairs[:, 1]].astype(np.int64)
    f_pos = np.asarray(found_position)[pairs[:, 1]].astype(np.int64)
    row_ok = _best_affine(f_row, t_row, np.ones(len(pairs), dtype=bool))
    correct = np.zeros(len(pairs), dtype=bool)
    for r in np.unique(f_row):
        correct |= _best_affine(f_pos, t_slot, row_ok & (f_row == r))
    n = int(correct.sum())
    return {"address_accuracy": n / len(pairs), "n_matched": int(len(pairs)), "n_correct": n}


def gap_scores(true_xy: np.ndarray, found_xy: np.ndarray, *, match_distance: float) -> dict:
    """Precision and recall of the empty slots found (one-to-one within ``match_distance``).

    Returns
    -------
    dict
        ``gap_precision``, ``gap_recall`` (NaN when undefined), ``gap_tp``, ``gap_fp``,
        ``gap_fn``.
    """
    s = trunk_scores(np.asarray(true_xy).reshape(-1, 2), np.asarray(found_xy).reshape(-1, 2), match_distance=match_distance)
    n_true = s["tp"] + s["fn"]
    n_found = s["tp"] + s["fp"]
    return {
        "gap_precision": s["tp"] / n_found if n_found else float("nan"),
        "gap_recall": s["tp"] / n_true if n_true else float("nan"),
        "gap_tp": s["tp"],
        "gap_fp": s["fp"],
        "gap_fn": s["fn"],
    }


def score_layout(truth_path: str, result_dir: str, trees: dict, *, match_distance: float) -> dict:
    """Address, empty-slot and replant scores of a result folder against a truth file
    that records its planting plan; empty when either side lacks it.

    Parameters
    ----------
    truth_path : str
        Truth Parquet of :func:`simulator.truth.write_simulation`.
    result_dir : str
        Folder holding ``gaps.parquet`` beside the trees table.
    trees : dict
        Columns of ``trees.parquet`` (``trunk_x``, ``trunk_y``, ``row``, ``position``,
        ``young``).
    match_distance : float
        Largest trunk match distance [m]; empty slots match within half the spacing.
    """
    import os

    from pipeline.parquet import read_parquet_columns
    from simulator.truth import read_truth, read_truth_layout

    plan = read_truth_layout(truth_path)
    if plan["tree_row"] is None or "row" not in trees or "position" not in trees:
        return {}
    _, true_trunks = read_truth(truth_path)
    found = np.c_[np.asarray(trees["trunk_x"], np.float64), np.asarray(trees["trunk_y"], np.float64)]
    pairs = trunk_scores(true_trunks[:, :2], found, match_distance=match_distance)["pairs"]
    out = address_scores(true_trunks[:, :2], plan["tree_row"], plan["tree_slot"], found, trees["row"], trees["position"],
                         match_distance=match_distance, pairs=pairs)
    gaps_path = os.path.join(result_dir, "gaps.parquet")
    if os.path.exists(gaps_path):
        gaps, _ = read_parquet_columns(gaps_path, ["x", "y"], what="gaps.parquet")
        reach = 0.5 * (plan["spacing"] or 2.0 * match_distance)
        out.update(gap_scores(plan["empty_slots"][:, 2:4], np.c_[gaps["x"], gaps["y"]], match_distance=reach))
    if "young" in trees and plan["tree_young"] is not None:
        t = np.asarray(plan["tree_young"], bool)[pairs[:, 0]]
        f = np.asarray(trees["young"], bool)[pairs[:, 1]]
        out["young_true"] = int(np.asarray(plan["tree_young"], bool).sum())
        out["young_found"] = int(f.sum())
        out["young_correct"] = int((t & f).sum())
    return out
