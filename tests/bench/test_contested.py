"""bench.contested: its diagnosis and its two small models, on inputs small enough to check by hand."""

import numpy as np
import pytest
from scipy import sparse

from bench.contested import (
    FEATURES,
    Block,
    contested_features,
    diagnose,
    fit_logistic,
    fit_trees,
    logistic_p,
    subtree_vote,
    trees_p,
)
from pipeline.graph import shortest_paths
from simulator.orchard import LEAF, WOOD


def _line_block() -> Block:
    # ten nodes 0.1 m apart on a line, trunk 1 at node 0 and trunk 2 at node 9: shortest
    # paths give nodes 0-4 to tree 1 and 5-9 to tree 2. Truly nodes 3-9 are tree 2's, so
    # nodes 3 and 4 are wrong: one run of two nodes, entered once (at node 3) from tree
    # 1's forest; node 3's rival path is 0.3 m longer (0.6 against 0.3), node 4's 0.1 m.
    # One point per node; node 3's point is wood.
    n = 10
    nodes = np.c_[np.arange(n) * 0.1, np.zeros(n), np.full(n, 1.0)]
    i = np.arange(n - 1)
    g = sparse.coo_matrix((np.full(n - 1, 0.1), (i, i + 1)), shape=(n, n))
    graph = (g + g.T).tocsr()
    sp = shortest_paths(graph, np.array([0, n - 1]))
    node_tree = np.where(sp.source == 0, 1, 2)
    true = np.array([1, 1, 1, 2, 2, 2, 2, 2, 2, 2])
    kind = np.full(n, LEAF)
    kind[3] = WOOD
    return Block(nodes=nodes, graph=graph, node_tree=node_tree, dist=sp.dist, final=node_tree, pred=sp.pred,
                 source_nodes=np.array([0, n - 1]), trunk_xy=np.array([[0.0, 0.0], [0.9, 0.0]]),
                 node_height=np.full(n, 1.0), linearity=np.full(n, 0.5), scattering=np.full(n, 0.1),
                 point_node=np.arange(n), point_true=true, point_kind=kind,
                 node_true=np.eye(3)[true], tree_points=n)


def test_diagnosis_of_a_line_by_hand():
    b = _line_block()
    assert b.node_tree.tolist() == [1, 1, 1, 1, 1, 2, 2, 2, 2, 2]
    d = diagnose(b, margin=1.0)
    assert d["wrong"] == pytest.approx(0.2)
    assert d["in wrong nodes"] == pytest.approx(1.0)  # one point a node: no minority points
    assert (d["wood"], d["twig"], d["leaf"]) == pytest.approx((0.5, 0.0, 0.5))
    assert d["in runs"] == 0.0  # a run of 2 nodes is fringe
    assert d["in runs with wood"] == pytest.approx(1.0)
    # nodes 3 and 4 lie 0.6 and 0.5 m from their true trunk (x = 0.9), 0.3 and 0.4 m from
    # the one they were given: past the midpoint, at 0.67 and 0.56 (the median: the lower)
    assert d["between trunks"].tolist() == pytest.approx([0.5 / 0.9, 0.5 / 0.9, 0.6 / 0.9])
    assert d["contested shipped"] == pytest.approx(0.5)  # node 4 only
    assert d["contested margin"] == pytest.approx(1.0)
    assert d["entries per run"] == pytest.approx(1.0)
    # inside tree 2 (edges 3-4-...-9) trunk 2 reaches both, by 0.6 and 0.5 m against 0.3 and 0.4
    assert d["reached inside own tree"] == pytest.approx(1.0)
    assert d["detour"] == pytest.approx((2.0 + 1.25) / 2)
    assert d["v paths"] < 1.0 and d["v fixed"] == pytest.approx(1.0)  # one point a node: all put right


def test_contested_features_one_row_per_contested_node():
    b = _line_block()
    idx, rival, x, _ = contested_features(b, margin=0.2)
    # nodes 4 and 5: each trunk's path to them is 0.1 m from the other's
    assert idx.tolist() == [4, 5]
    assert rival.tolist() == [2, 1]
    assert x.shape == (2, len(FEATURES)) and np.isfinite(x).all()


def test_subtree_vote_moves_a_forest_subtree_as_a_whole():
    # nodes 3 and 4 of tree 1 hang one from the other in the forest (3 is the root):
    # the walk moving node 4 (3 points of 4) moves both, moving node 3 (1 of 4) moves none
    b = _line_block()
    idx, pts = np.array([3, 4]), np.array([1.0, 3.0])
    assert subtree_vote(b, idx, pts, np.array([False, True])).tolist() == [True, True]
    assert subtree_vote(b, idx, pts, np.array([True, False])).tolist() == [False, False]
    # node 5 hangs from tree 2's forest: a subtree of its own
    assert subtree_vote(b, np.array([4, 5]), np.ones(2), np.array([True, False])).tolist() == [True, False]


def test_logistic_regression_learns_a_threshold():
    x = np.linspace(-1, 1, 200)[:, None]
    y = (x[:, 0] > 0.2).astype(float)
    model = fit_logistic(x, y, np.ones(200))
    p = logistic_p(model, x)
    assert ((p > 0.5) == (y > 0.5)).mean() > 0.97


def test_boosted_trees_learn_an_interaction_a_line_cannot():
    # y = x0 xor x1 (by sign): no linear model beats chance, depth-2 trees get it
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (400, 2))
    y = ((x[:, 0] > 0) ^ (x[:, 1] > 0)).astype(float)
    w = np.ones(400)
    assert (((logistic_p(fit_logistic(x, y, w), x) > 0.5) == (y > 0.5)).mean()) < 0.7
    assert (((trees_p(fit_trees(x, y, w, rounds=40), x) > 0.5) == (y > 0.5)).mean()) > 0.95
