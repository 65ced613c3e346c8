"""Accuracy metrics: hand-checkable V-measure, trunk matching, wood F1 and diameter cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulator.scoring.scores import (
    diameter_errors,
    homogeneity_completeness_v_measure,
    score_labels,
    score_result,
    trunk_scores,
    v_measure,
    wood_f1,
    wood_scores,
)


def _h(*p):
    """Entropy (nats) of a distribution given by probabilities."""
    return -sum(q * math.log(q) for q in p if q > 0)


# ---------------------------------------------------------------- V-measure


def test_perfect_clustering_scores_one():
    assert v_measure([1, 1, 2, 2, 3], [1, 1, 2, 2, 3]) == pytest.approx(1.0)


def test_permuted_labels_score_one():
    assert homogeneity_completeness_v_measure([1, 1, 2, 2, 3, 3], [9, 9, 0, 0, 4, 4]) == pytest.approx((1.0, 1.0, 1.0))


def test_all_in_one_cluster_against_a_true_split():
    # one cluster: complete but not homogeneous at all
    assert homogeneity_completeness_v_measure([0, 0, 1, 1], [7, 7, 7, 7]) == pytest.approx((0.0, 1.0, 0.0))


def test_every_point_its_own_cluster_against_one_class():
    assert homogeneity_completeness_v_measure([3, 3, 3, 3], [0, 1, 2, 3]) == pytest.approx((1.0, 0.0, 0.0))


def test_hand_computed_case():
    # classes {a,a,b,b}; clusters {a,a,b} and {b}
    # H(C) = ln 2, H(C|K) = 3/4 H(2/3, 1/3);  H(K) = H(3/4, 1/4), H(K|C) = 1/2 H(1/2, 1/2)
    h = 1 - 0.75 * _h(2 / 3, 1 / 3) / math.log(2)
    c = 1 - 0.5 * _h(0.5, 0.5) / _h(0.75, 0.25)
    v = 2 * h * c / (h + c)
    got = homogeneity_completeness_v_measure([0, 0, 1, 1], [0, 0, 0, 1])
    assert got == pytest.approx((h, c, v), abs=1e-12)
    assert got == pytest.approx((0.311278, 0.383689, 0.343711), abs=1e-6)


def test_single_class_single_cluster_and_empty_input_score_one():
    assert homogeneity_completeness_v_measure([5, 5, 5], [2, 2, 2]) == (1.0, 1.0, 1.0)
    assert homogeneity_completeness_v_measure([], []) == (1.0, 1.0, 1.0)


def test_v_measure_matches_the_definition_on_random_labels():
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = int(rng.integers(2, 60))
        a = rng.integers(0, 4, n)
        b = rng.integers(0, 5, n)
        # definition via conditional entropies, computed naively
        pairs = {}
        for x, y in zip(a, b):
            pairs[(x, y)] = pairs.get((x, y), 0) + 1
        ca = {x: np.sum(a == x) for x in set(a)}
        kb = {y: np.sum(b == y) for y in set(b)}
        h_c = _h(*(v / n for v in ca.values()))
        h_k = _h(*(v / n for v in kb.values()))
        h_c_k = -sum(v / n * math.log(v / kb[y]) for (x, y), v in pairs.items())
        h_k_c = -sum(v / n * math.log(v / ca[x]) for (x, y), v in pairs.items())
        hom = 1.0 if h_c == 0 else 1 - h_c_k / h_c
        com = 1.0 if h_k == 0 else 1 - h_k_c / h_k
        v = 0.0 if hom + com == 0 else 2 * hom * com / (hom + com)
        assert homogeneity_completeness_v_measure(a, b) == pytest.approx((hom, com, v), abs=1e-9)


def test_label_lengths_must_agree():
    with pytest.raises(ValueError):
        v_measure([1, 2], [1])


# ---------------------------------------------------------------- trunks


def test_two_detections_at_one_trunk_are_one_tp_and_one_fp():
    s = trunk_scores(np.array([[0.0, 0.0], [5.0, 0.0]]), np.array([[0.1, 0.0], [-0.2, 0.1], [5.0, 0.3]]))
    assert (s["tp"], s["fp"], s["fn"]) == (2, 1, 0)
    assert s["precision"] == pytest.approx(2 / 3)
    assert s["recall"] == pytest.approx(1.0)
    assert s["f1"] == pytest.approx(0.8)
    assert s["mean_distance"] == pytest.approx((0.1 + 0.3) / 2)


def test_matches_are_within_the_match_distance():
    s = trunk_scores(np.array([[0.0, 0.0]]), np.array([[1.2, 0.0]]))
    assert (s["tp"], s["fp"], s["fn"]) == (0, 1, 1)
    assert s["f1"] == 0.0 and math.isnan(s["mean_distance"])
    s = trunk_scores(np.array([[0.0, 0.0]]), np.array([[1.2, 0.0]]), match_distance=1.5)
    assert s["tp"] == 1


def test_matching_is_optimal_not_greedy():
    # greedy nearest-first would pair found 0.9 with true 1.5 and leave 2 unmatched pairs
    true = np.array([[0.0, 0.0], [1.5, 0.0]])
    found = np.array([[0.9, 0.0], [2.4, 0.0]])
    s = trunk_scores(true, found)
    assert s["tp"] == 2 and s["f1"] == pytest.approx(1.0)
    assert s["mean_distance"] == pytest.approx(0.9)
    assert sorted(map(tuple, s["pairs"])) == [(0, 0), (1, 1)]


def test_trunk_scores_ignore_z_and_handle_empty_sets():
    s = trunk_scores(np.array([[0.0, 0.0, 100.0]]), np.array([[0.0, 0.0, 0.0]]))
    assert s["tp"] == 1 and s["mean_distance"] == 0.0
    s = trunk_scores(np.zeros((3, 2)) + [[0, 0], [5, 0], [10, 0]], np.empty((0, 2)))
    assert (s["precision"], s["recall"], s["f1"], s["fn"]) == (0.0, 0.0, 0.0, 3)
    s = trunk_scores(np.empty((0, 2)), np.array([[1.0, 1.0]]))
    assert (s["tp"], s["fp"], s["f1"]) == (0, 1, 0.0)


# ---------------------------------------------------------------- wood


def test_wood_f1_hand_cases():
    assert wood_f1([1, 1, 0, 0], [1, 1, 0, 0]) == 1.0
    assert wood_f1([1, 1, 0, 0], [1, 0, 1, 0]) == pytest.approx(0.5)  # TP 1, FP 1, FN 1
    assert wood_f1([1, 1, 1, 0], [1, 0, 0, 0]) == pytest.approx(0.5)  # P 1, R 1/3
    assert wood_f1([1, 0], [0, 1]) == 0.0
    assert wood_f1([0, 0], [0, 0]) == 0.0  # undefined -> 0, as scikit-learn
    s = wood_scores([1, 1, 1, 0], [1, 1, 0, 1])
    assert (s["precision"], s["recall"]) == pytest.approx((2 / 3, 2 / 3))


# ---------------------------------------------------------------- whole blocks


def test_scores_use_only_true_tree_points():
    true_tree = np.array([0, 0, 1, 1, 2, 2])
    true_wood = np.array([0, 0, 1, 0, 1, 0], bool)
    # prediction is wrong on the non-tree points only
    pred_tree = np.array([1, 2, 1, 1, 2, 2])
    pred_wood = np.array([1, 1, 1, 0, 1, 0], bool)
    m = score_labels(
        true_tree_id=true_tree, true_is_wood=true_wood, true_trunks=np.array([[0.0, 0.0], [5.0, 0.0]]),
        pred_tree_id=pred_tree, pred_is_wood=pred_wood, found_trunks=np.array([[0.1, 0.0], [5.0, 0.1]]),
    )
    assert m["v_measure"] == pytest.approx(1.0)
    assert m["wood_f1"] == pytest.approx(1.0)
    assert m["trunk_f1"] == pytest.approx(1.0)
    assert (m["n_points"], m["n_tree_points"], m["n_true_trees"], m["n_found_trees"]) == (6, 4, 2, 2)


def test_score_result_takes_a_local_frame_result():
    from types import SimpleNamespace

    from simulator.orchard import Orchard

    origin = np.array([500000.0, 6950000.0, 100.0])
    truth = Orchard(
        xyz=origin + np.arange(12.0).reshape(4, 3),
        tree_id=np.array([0, 1, 1, 2]),
        is_wood=np.array([0, 1, 0, 1], bool),
        kind=np.array([0, 2, 3, 2], np.uint8),
        trunks=origin + np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]]),
        trunk_radius=np.array([0.1, 0.1]),
    )
    result = SimpleNamespace(tree_id=np.array([0, 4, 4, 9]), is_wood=np.array([0, 1, 0, 1], bool),
                             trunks=np.array([[0.3, 0.0, 0.0], [5.0, 0.4, 0.0]]))
    m = score_result(truth, result, origin=origin)
    assert (m["trunk_f1"], m["v_measure"], m["wood_f1"]) == pytest.approx((1.0, 1.0, 1.0))
    assert m["trunk_mean_distance"] == pytest.approx(0.35)
    assert score_result(truth, result)["trunk_tp"] == 0  # frames must agree


def test_diameter_errors_by_hand():
    true_xy = np.array([[0.0, 0.0], [5.0, 0.0], [10.0, 0.0]])
    true_d = np.array([0.2, 0.3, 0.1])
    # found: near trunk 2 (0.26: -0.04), near trunk 1 (0.26: +0.06), a false one, none at trunk 3
    found_xy = np.array([[5.2, 0.0], [0.1, 0.1], [20.0, 0.0]])
    m = diameter_errors(true_xy, true_d, found_xy, np.array([0.26, 0.26, 0.9]))
    assert m["trunk_diameter_n"] == 2 and m["trunk_diameter_unmeasured"] == 0
    assert (m["trunk_diameter_bias"], m["trunk_diameter_mae"]) == pytest.approx((0.01, 0.05))
    m = diameter_errors(true_xy, true_d, found_xy, np.array([np.nan, np.nan, 0.9]))
    assert (m["trunk_diameter_n"], m["trunk_diameter_unmeasured"]) == (0, 2)
    assert np.isnan(m["trunk_diameter_bias"]) and np.isnan(m["trunk_diameter_mae"])
