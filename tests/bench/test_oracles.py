"""bench.oracles helpers (direction_paths, midpoint_ratio, error_breakdown, cross_edges, auc) on inputs small enough to check by hand."""

import numpy as np
import pytest
from scipy import sparse

from bench.oracles import (
    auc,
    cross_edges,
    direction_paths,
    error_breakdown,
    midpoint_ratio,
    noisy_edge_scores,
    twig_visibility,
)
from pipeline.graph import shortest_paths


def _graph(nodes, edges):
    i, j = np.array(edges).T
    w = np.linalg.norm(nodes[i] - nodes[j], axis=1)
    g = sparse.coo_matrix((w, (i, j)), shape=(len(nodes),) * 2)
    return (g + g.T).tocsr()


@pytest.mark.parametrize("smoothing", [None, 0.85])
def test_a_straight_path_beats_a_shorter_sharp_turn(smoothing):
    # trunk A: a vertical chain 0..4 from z=0 to z=0.4; node 4 is the target.
    # trunk B's seed (node 5) sits 0.1 m beside the target, at the same height.
    # Plain shortest paths give the target to B (0.1 m against 0.4 m); a path from B
    # would have to turn 90 degrees off its upward start, so direction paths give it to A.
    nodes = np.array([[0, 0, z] for z in (0.0, 0.1, 0.2, 0.3, 0.4)] + [[0.1, 0, 0.4]], float)
    g = _graph(nodes, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)])
    seeds, seed_trunk = np.array([0, 5]), np.array([0, 1])
    plain = shortest_paths(g, seeds).source
    assert plain[4] == 5
    trunk = direction_paths(g, nodes, seeds, seed_trunk, np.array([[0.0, 0.0], [0.1, 0.0]]), smoothing=smoothing)
    assert trunk.tolist() == [0, 0, 0, 0, 0, 1]


@pytest.mark.parametrize("smoothing", [None, 0.85])
def test_a_symmetric_bridge_splits_in_the_middle_and_unreached_nodes_stay_minus_one(smoothing):
    # two trunks at the ends of a horizontal bridge of 21 nodes, and one isolated node
    xs = np.arange(0.0, 2.01, 0.1)
    nodes = np.c_[xs, np.zeros_like(xs), np.full_like(xs, 1.0)]
    nodes = np.vstack([nodes, [[5.0, 5.0, 5.0]]])  # an isolated node
    n = len(xs)
    g = _graph(nodes, [(k, k + 1) for k in range(n - 1)])
    trunk = direction_paths(
        g, nodes, np.array([0, n - 1]), np.array([0, 1]), np.array([[0.0, 0.0], [2.0, 0.0]]), smoothing=smoothing
    )
    assert trunk[-1] == -1
    assert (trunk[: n // 2] == 0).all() and (trunk[n // 2 + 1 : n] == 1).all()


def test_midpoint_ratio_by_hand():
    # trunks at x=0 and x=4; tree 1's points at x=1 and x=3 lie at 1/4 and 3/4 of the way
    # to tree 2's trunk; a tree-2 point at x=2 is on the midpoint; a non-tree point is NaN
    xy = np.array([[1.0, 0.0], [3.0, 0.0], [2.0, 0.0], [9.0, 9.0]])
    r = midpoint_ratio(xy, np.array([1, 1, 2, 0]), np.array([[0.0, 0.0], [4.0, 0.0]]))
    assert r[:3] == pytest.approx([0.25, 0.75, 0.5])
    assert np.isnan(r[3])


def test_midpoint_ratio_nearest_other_trunk_and_single_tree():
    # the nearer of two other trunks counts; with one trunk every tree point is at 0
    xy = np.array([[0.0, 1.0]])
    r = midpoint_ratio(xy, np.array([1]), np.array([[0.0, 0.0], [0.0, 3.0], [0.0, -9.0]]))
    assert r == pytest.approx([1.0 / 3.0])
    assert midpoint_ratio(xy, np.array([1]), np.array([[5.0, 5.0]])).tolist() == [0.0]


def test_twig_visibility_separates_a_line_from_discs_and_not_from_itself():
    # a twig: points along a straight 1 m line; leaves: flat discs of 5 cm radius away
    # from it. Linearity tells them apart (AUC near 1); with the leaf points relabelled as
    # twig points of the same shape, the AUC is 0.5 (no separation).
    rng = np.random.default_rng(0)
    line = np.c_[np.linspace(0, 1, 200), np.zeros(200), np.zeros(200)] + rng.normal(0, 0.002, (200, 3))
    centres = np.c_[np.linspace(0, 1, 10), np.full(10, 0.5), np.zeros(10)]
    ang, rad = rng.uniform(0, 2 * np.pi, (10, 40)), 0.05 * np.sqrt(rng.uniform(0, 1, (10, 40)))
    discs = (centres[:, None, :] + np.stack([rad * np.cos(ang), rad * np.sin(ang), np.zeros_like(ang)], axis=2)).reshape(-1, 3)
    xyz = np.vstack([line, discs])
    twig = np.r_[np.ones(200, bool), np.zeros(400, bool)]
    assert twig_visibility(xyz, twig, ~twig) > 0.95
    half = np.arange(400) % 2 == 0
    leaf_a, leaf_b = np.r_[np.zeros(200, bool), half], np.r_[np.zeros(200, bool), ~half]
    assert abs(twig_visibility(xyz, leaf_a, leaf_b) - 0.5) < 0.1
    assert np.isnan(twig_visibility(xyz, twig, np.zeros(600, bool)))


def test_error_breakdown_by_hand():
    # true trees 1 and 2 with three points each; found tree 5 stands for true 1 and found
    # tree 7 for true 2. Point 2 (true 1) went to 7: wrong; point 5 went to no tree.
    true = np.array([1, 1, 1, 2, 2, 2])
    pred = np.array([5, 5, 7, 7, 7, 0])
    ratio = np.array([0.1, 0.2, 0.55, 0.1, 0.45, 0.2])
    e = error_breakdown(true, pred, ratio)
    assert e["wrong"] == pytest.approx(1 / 6) and e["unlabelled"] == pytest.approx(1 / 6)
    # with point 2 put right the only error left is the unlabelled point, and vice versa
    from simulator.scoring.scores import v_measure

    assert e["v-measure, wrong right"] == pytest.approx(v_measure(true, np.array([5, 5, 5, 7, 7, 0])))
    assert e["v-measure, unlabelled right"] == pytest.approx(v_measure(true, np.array([5, 5, 7, 7, 7, 7])))
    assert e["v-measure"] < min(e["v-measure, wrong right"], e["v-measure, unlabelled right"])
    # bands: 0-0.3 holds 4 points (none wrong), 0.4-0.5 one, 0.5-0.6 the wrong one
    assert e["band 0.0-0.3 points"] == 4 and e["band 0.0-0.3 wrong"] == 0
    assert e["band 0.4-0.5 points"] == 1 and e["band 0.5-0.6 wrong"] == 1.0
    assert e["band 0.6-1.0 points"] == 0


def test_error_breakdown_a_true_tree_no_found_tree_stands_for_gets_its_own_id():
    # found tree 3 holds most of both true trees' points: it stands for true 1; true 2's
    # points are wrong, and putting them right needs a new id, not tree 3
    true = np.array([1, 1, 1, 2, 2])
    pred = np.array([3, 3, 3, 3, 3])
    e = error_breakdown(true, pred, np.zeros(5))
    assert e["wrong"] == pytest.approx(2 / 5)
    assert e["v-measure, wrong right"] == pytest.approx(1.0)


def test_cross_edges_by_hand():
    # a chain 0-1-2-3-4 with a chord 0-4: nodes 0,1 are tree 1, nodes 2,3 tree 2, node 4
    # no tree. Only 1-2 joins two trees; edges touching node 4 never count.
    nodes = np.array([[x, 0.0, 0.0] for x in range(5)], float)
    g = _graph(nodes, [(0, 1), (1, 2), (2, 3), (3, 4), (0, 4)])
    i, j, cross = cross_edges(g, np.array([1, 1, 2, 2, 0]))
    edges = {(int(a), int(b)): bool(c) for a, b, c in zip(i, j, cross)}
    assert edges == {(0, 1): False, (1, 2): True, (2, 3): False, (3, 4): False, (0, 4): False}


def test_auc_by_hand():
    # 2 of the 4 pairs have x > y, one ties (half), one has x < y: (2 + 0.5) / 4
    assert auc(np.array([1.0, 3.0]), np.array([1.0, 2.0])) == pytest.approx(0.625)
    assert auc(np.array([5.0]), np.array([1.0, 2.0])) == 1.0
    assert np.isnan(auc(np.array([]), np.array([1.0])))


@pytest.mark.parametrize("target", [0.6, 0.75, 0.95])
def test_noisy_edge_scores_have_the_asked_auc(target):
    cross = np.arange(400_000) % 10 == 0
    p = noisy_edge_scores(cross, target, np.random.default_rng(1))
    assert ((p > 0) & (p < 1)).all()
    assert auc(p[cross], p[~cross]) == pytest.approx(target, abs=0.01)
