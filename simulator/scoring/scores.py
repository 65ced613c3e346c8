"""Accuracy metrics of the paper, on arrays of true and found labels.

- trunk detection: precision, recall and F1 with a one-to-one matching of detected to
  true trunks within ``match_distance`` (1 m), and the mean horizontal distance of the
  matched pairs;
- segmentation: V-measure (Rosenberg & Hirschberg 2007) of the tree labels on the
  points that truly belong to a tree;
- wood/leaf: F1 of the wood class on the points that truly belong to a tree.

:func:`score_labels` works on arrays (for tuning loops that call
:func:`pipeline.process.process_points` directly, and for labelled real trees);
:func:`simulator.scoring.result.evaluate_result` reads a truth file and a result folder.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

_UNMATCHABLE = 1e9


def _xy(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0:
        return np.empty((0, 2))
    if a.ndim != 2 or a.shape[1] < 2:
        raise ValueError(f"{name} must be (k, 2) or (k, 3), not {a.shape}")
    return a[:, :2]


def trunk_scores(true_xy: np.ndarray, found_xy: np.ndarray, *, match_distance: float = 1.0) -> dict:
    """Trunk detection scores with one-to-one matching.

    Strategy: Hungarian assignment (``scipy.optimize.linear_sum_assignment``) on the
    pairwise XY distances, where pairs farther apart than ``match_distance`` cost a
    prohibitive amount, so the assignment first maximises the number of pairs within
    range and then minimises their total distance; assigned pairs beyond the range are
    dropped.

    Parameters
    ----------
    true_xy : (k, 2) or (k, 3) float64
        True trunk positions [m] (only x, y are used).
    found_xy : (m, 2) or (m, 3) float64
        Detected trunk positions [m].
    match_distance : float
        Largest horizontal distance [m] of a match.

    Returns
    -------
    dict
        ``precision``, ``recall``, ``f1`` (0 when undefined), ``mean_distance`` [m] of
        the true positives (NaN without any), ``tp``, ``fp``, ``fn`` (int), and
        ``pairs`` ((tp, 2) int64 rows of (true index, found index)).
    """
    t = _xy(true_xy, "true_xy")
    f = _xy(found_xy, "found_xy")
    pairs = np.empty((0, 2), dtype=np.int64)
    dist = np.empty(0)
    if len(t) and len(f):
        d = np.hypot(t[:, None, 0] - f[None, :, 0], t[:, None, 1] - f[None, :, 1])
        cost = np.where(d <= match_distance, d, _UNMATCHABLE)
        rows, cols = linear_sum_assignment(cost)
        ok = d[rows, cols] <= match_distance
        pairs = np.c_[rows[ok], cols[ok]].astype(np.int64)
        dist = d[rows[ok], cols[ok]]
    tp = len(pairs)
    fp = len(f) - tp
    fn = len(t) - tp
    precision = tp / len(f) if len(f) else 0.0
    recall = tp / len(t) if len(t) else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "precision": float(precision),
        "recall": float(recall),
        "f1": float(f1),
        "mean_distance": float(dist.mean()) if tp else float("nan"),
        "tp": int(tp),
        "fp": int(fp),
        "fn": int(fn),
        "pairs": pairs,
    }


def _entropy(counts: np.ndarray) -> float:
    counts = counts[counts > 0].astype(np.float64)
    n = counts.sum()
    if n == 0:
        return 0.0
    p = counts / n
    return float(-(p * np.log(p)).sum())


def homogeneity_completeness_v_measure(labels_true: np.ndarray, labels_pred: np.ndarray, *, beta: float = 1.0) -> tuple[float, float, float]:
    """Homogeneity, completeness and V-measure of a clustering (Rosenberg & Hirschberg 2007).

    Strategy: the contingency table is built from the unique (class, cluster) pairs with
    ``np.unique``; H(C|K) and H(K|C) follow from it, so the cost is O(n log n) whatever
    the number of labels. Same conventions as scikit-learn: empty input or a single
    class and a single cluster score 1; a score whose entropy denominator is 0 is 1.

    Parameters
    ----------
    labels_true, labels_pred : (n,) integer arrays
        Class and cluster labels; the label values themselves do not matter.
    beta : float
        Weight of completeness relative to homogeneity (1 = harmonic mean).

    Returns
    -------
    (homogeneity, completeness, v_measure) : floats in [0, 1]
    """
    a = np.asarray(labels_true).ravel()
    b = np.asarray(labels_pred).ravel()
    if a.shape != b.shape:
        raise ValueError(f"label arrays differ in length: {a.shape[0]} and {b.shape[0]}")
    n = a.size
    if n == 0:
        return 1.0, 1.0, 1.0
    _, ci = np.unique(a, return_inverse=True)
    _, ki = np.unique(b, return_inverse=True)
    n_c, n_k = int(ci.max()) + 1, int(ki.max()) + 1
    if n_c == n_k == 1:
        return 1.0, 1.0, 1.0
    pair = ci.astype(np.int64) * n_k + ki
    cells, nij = np.unique(pair, return_counts=True)
    i, j = np.divmod(cells, n_k)
    a_i = np.bincount(ci, minlength=n_c).astype(np.float64)  # class sizes
    b_j = np.bincount(ki, minlength=n_k).astype(np.float64)  # cluster sizes
    nij = nij.astype(np.float64)
    h_c = _entropy(a_i)
    h_k = _entropy(b_j)
    # mutual information from the non-zero cells
    mi = float(np.sum(nij / n * (np.log(nij * n) - np.log(a_i[i]) - np.log(b_j[j]))))
    mi = max(mi, 0.0)
    homogeneity = mi / h_c if h_c > 0 else 1.0
    completeness = mi / h_k if h_k > 0 else 1.0
    homogeneity = min(homogeneity, 1.0)
    completeness = min(completeness, 1.0)
    if homogeneity + completeness == 0:
        v = 0.0
    else:
        v = (1 + beta) * homogeneity * completeness / (beta * homogeneity + completeness)
    return float(homogeneity), float(completeness), float(v)


def v_measure(labels_true: np.ndarray, labels_pred: np.ndarray, *, beta: float = 1.0) -> float:
    """V-measure of a clustering; see :func:`homogeneity_completeness_v_measure`."""
    return homogeneity_completeness_v_measure(labels_true, labels_pred, beta=beta)[2]


def wood_scores(true_wood: np.ndarray, pred_wood: np.ndarray) -> dict:
    """Precision, recall and F1 of the wood class.

    Parameters
    ----------
    true_wood, pred_wood : (n,) bool

    Returns
    -------
    dict
        ``precision``, ``recall``, ``f1``; each 0 when undefined (no predicted or no
        true wood), as scikit-learn does.
    """
    t = np.asarray(true_wood, dtype=bool).ravel()
    p = np.asarray(pred_wood, dtype=bool).ravel()
    if t.shape != p.shape:
        raise ValueError(f"wood arrays differ in length: {t.shape[0]} and {p.shape[0]}")
    tp = int(np.count_nonzero(t & p))
    fp = int(np.count_nonzero(~t & p))
    fn = int(np.count_nonzero(t & ~p))
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * tp / (2 * tp + fp + fn) if tp else 0.0
    return {"precision": float(precision), "recall": float(recall), "f1": float(f1)}


def wood_f1(true_wood: np.ndarray, pred_wood: np.ndarray) -> float:
    """F1 of the wood class: 2 TP / (2 TP + FP + FN); 0 when there is no TP."""
    return wood_scores(true_wood, pred_wood)["f1"]


def score_labels(
    *,
    true_tree_id: np.ndarray,
    true_is_wood: np.ndarray,
    true_trunks: np.ndarray,
    pred_tree_id: np.ndarray,
    pred_is_wood: np.ndarray,
    found_trunks: np.ndarray,
    match_distance: float = 1.0,
) -> dict:
    """All metrics of a block from arrays aligned point by point.

    Parameters
    ----------
    true_tree_id, pred_tree_id : (n,) int64
        Tree of each point, 0 = not a tree.
    true_is_wood, pred_is_wood : (n,) bool
    true_trunks, found_trunks : (k, 2|3), (m, 2|3) float64
        Trunk positions [m] in the same frame (only x, y are used).
    match_distance : float
        Largest trunk match distance [m].

    Returns
    -------
    dict of str to float/int
        ``trunk_precision``, ``trunk_recall``, ``trunk_f1``, ``trunk_mean_distance``,
        ``trunk_tp``, ``trunk_fp``, ``trunk_fn``, ``n_true_trees``, ``n_found_trees``;
        ``v_measure``, ``homogeneity``, ``completeness`` and ``wood_f1``,
        ``wood_precision``, ``wood_recall`` on the true tree points;
        ``n_points``, ``n_tree_points``.
    """
    true_tree_id = np.asarray(true_tree_id)
    pred_tree_id = np.asarray(pred_tree_id)
    if true_tree_id.shape != pred_tree_id.shape:
        raise ValueError(f"truth has {true_tree_id.size} points, prediction {pred_tree_id.size}")
    ts = trunk_scores(true_trunks, found_trunks, match_distance=match_distance)
    tree = true_tree_id > 0
    h, c, v = homogeneity_completeness_v_measure(true_tree_id[tree], pred_tree_id[tree])
    ws = wood_scores(np.asarray(true_is_wood)[tree], np.asarray(pred_is_wood)[tree])
    return {
        "trunk_precision": ts["precision"],
        "trunk_recall": ts["recall"],
        "trunk_f1": ts["f1"],
        "trunk_mean_distance": ts["mean_distance"],
        "trunk_tp": ts["tp"],
        "trunk_fp": ts["fp"],
        "trunk_fn": ts["fn"],
        "n_true_trees": int(len(true_trunks)),
        "n_found_trees": int(len(found_trunks)),
        "v_measure": v,
        "homogeneity": h,
        "completeness": c,
        "wood_f1": ws["f1"],
        "wood_precision": ws["precision"],
        "wood_recall": ws["recall"],
        "n_points": int(true_tree_id.size),
        "n_tree_points": int(np.count_nonzero(tree)),
    }


def score_result(orchard, result, *, origin=(0.0, 0.0, 0.0), match_distance: float = 1.0) -> dict:
    """Metrics of an in-memory pipeline result against an in-memory simulation.

    For tuning loops: ``result = process_points(orchard.xyz - origin, params=...)`` then
    ``score_result(orchard, result, origin=origin)``.

    Parameters
    ----------
    orchard : simulator.orchard.Orchard
        Truth (absolute coordinates).
    result : object with ``tree_id`` (n,), ``is_wood`` (n,) and ``trunks`` (m, 3)
        E.g. :class:`pipeline.blockresult.BlockResult`, aligned with ``orchard.xyz``.
    origin : (3,) float
        What was subtracted from ``orchard.xyz`` before processing [m].
    match_distance : float
        Largest trunk match distance [m].

    Returns
    -------
    dict
        As :func:`score_labels`.
    """
    found = np.asarray(result.trunks, dtype=np.float64).reshape(-1, 3) + np.asarray(origin, dtype=np.float64)
    return score_labels(
        true_tree_id=orchard.tree_id,
        true_is_wood=orchard.is_wood,
        true_trunks=orchard.trunks,
        pred_tree_id=np.asarray(result.tree_id),
        pred_is_wood=np.asarray(result.is_wood),
        found_trunks=found,
        match_distance=match_distance,
    )


def diameter_errors(
    true_xy: np.ndarray,
    true_diameter: np.ndarray,
    found_xy: np.ndarray,
    found_diameter: np.ndarray,
    *,
    match_distance: float = 1.0,
) -> dict:
    """How far measured trunk diameters are from the true ones, over matched trunks.

    Trunks are matched one to one as in :func:`trunk_scores`; a matched tree counts when
    both diameters are finite (a NaN measurement is "not measurable", counted apart).

    Parameters
    ----------
    true_xy, found_xy : (k, 2|3), (m, 2|3) float64 — trunk positions [m], same frame
    true_diameter, found_diameter : (k,), (m,) float64 [m]
    match_distance : float [m]

    Returns
    -------
    dict
        ``trunk_diameter_n`` (matched trees compared), ``trunk_diameter_unmeasured``
        (matched trees whose measurement is NaN), ``trunk_diameter_bias`` (mean of
        measured - true) and ``trunk_diameter_mae`` (mean absolute error) [m], NaN with
        nothing to compare.
    """
    pairs = trunk_scores(true_xy, found_xy, match_distance=match_distance)["pairs"]
    t = np.asarray(true_diameter, dtype=np.float64)[pairs[:, 0]]
    f = np.asarray(found_diameter, dtype=np.float64)[pairs[:, 1]]
    ok = np.isfinite(t) & np.isfinite(f)
    err = f[ok] - t[ok]
    return {
        "trunk_diameter_n": int(ok.sum()),
        "trunk_diameter_unmeasured": int((np.isfinite(t) & ~np.isfinite(f)).sum()),
        "trunk_diameter_bias": float(err.mean()) if err.size else float("nan"),
        "trunk_diameter_mae": float(np.abs(err).mean()) if err.size else float("nan"),
    }
