"""bench.edges: its edge factors and the node inputs they read, on hand-made nodes."""

import numpy as np
import pytest
from scipy import sparse

from bench.edges import WEIGHTINGS, contact_auc, edge_factors, principal_axes, shared_neighbours


def _pair(**kw) -> dict:
    # two nodes 0.1 m apart along x; node 0's axis runs along x, node 1's along z
    nodes = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]])
    base = dict(nodes=nodes, axis=np.array([[1.0, 0, 0], [0, 0, 1.0]]), linearity=np.array([1.0, 0.5]),
                density=np.array([100.0, 100.0 * np.e]), scattering=np.array([0.1, 0.4]), shared=np.array([0.25]),
                features=np.array([[1.0, 0.0], [0.0, 1.0]]), pred=np.array([-1, -1]), truth=np.array([1, 2]))
    base.update(kw)
    return base


@pytest.mark.parametrize(
    "kind, want",
    [
        ("axis", 1 + 2 * 0.5 * (0 + 1)),  # along node 0's axis, across node 1's
        ("axis linear", 1 + 2 * 0.5 * (0 + 0.5 * 1)),
        ("density", 1 + 2 * 1.0),  # densities e times apart
        ("scattering", 1 + 2 * 0.3),
        ("shared", 1 + 2 * 0.75),
        ("enriched", 1 + 2 * 1.0),  # orthogonal features
        ("turn", 1.0),  # no path leads to either node: no turn
        ("oracle", 1 + 2),  # two true trees
    ],
)
def test_factor_of_a_hand_made_pair(kind, want):
    f = edge_factors(kind, np.array([0]), np.array([1]), alpha=2.0, **_pair())
    assert f == pytest.approx([want])
    # the same edge read from its other end costs the same
    assert edge_factors(kind, np.array([1]), np.array([0]), alpha=2.0, **_pair()) == pytest.approx(f)


@pytest.mark.parametrize("kind", WEIGHTINGS)
def test_alike_nodes_along_their_axis_cost_their_length(kind):
    same = _pair(axis=np.array([[1.0, 0, 0], [-1.0, 0, 0]]), linearity=np.ones(2), density=np.ones(2),
                 scattering=np.zeros(2), shared=np.ones(1), features=np.ones((2, 2)), truth=np.array([1, 1]))
    assert edge_factors(kind, np.array([0]), np.array([1]), alpha=3.0, **same) == pytest.approx([1.0])


def test_unknown_weighting_is_refused():
    with pytest.raises(ValueError, match="unknown weighting"):
        edge_factors("nope", np.array([0]), np.array([1]), alpha=1.0, **_pair())


def test_principal_axis_of_a_line_of_nodes():
    nodes = np.c_[np.zeros(5), np.zeros(5), np.arange(5) * 0.1] + np.r_[0, 0.01, 0, -0.01, 0][:, None] * [1, 0, 0]
    adj = sparse.csr_matrix(np.ones((5, 5)))
    axis = principal_axes(nodes, adj)
    assert np.abs(axis[:, 2]) == pytest.approx(np.ones(5), abs=1e-3)


def test_shared_neighbours_on_a_path():
    # path 0-1-2-3: {0,1} and {0,1,2} share 2 of 3; {1,2,3} and {2,3} share 2 of 3
    i = np.array([0, 1, 2])
    g = sparse.csr_matrix((np.ones(6), (np.r_[i, i + 1], np.r_[i + 1, i])), shape=(4, 4))
    assert shared_neighbours(g, np.array([0, 2]), np.array([1, 3])) == pytest.approx([2 / 3, 2 / 3])


def test_contact_auc_on_a_path_of_two_trees():
    # path 0-1-2-3, nodes 0, 1 of tree 1 and 2, 3 of tree 2: edge (1, 2) is the contact,
    # (0, 1) and (2, 3) the edges beside it; node 4 belongs to no tree
    a, b, truth = np.array([0, 1, 2, 3]), np.array([1, 2, 3, 4]), np.array([1, 1, 2, 2, 0])
    assert contact_auc(np.array([1.0, 2.0, 1.0, 9.0]), a, b, truth) == pytest.approx(1.0)
    assert contact_auc(np.array([2.0, 1.0, 2.0, 0.0]), a, b, truth) == pytest.approx(0.0)
    assert contact_auc(np.array([2.0, 2.0, 1.0, 0.0]), a, b, truth) == pytest.approx(0.75)
    assert np.isnan(contact_auc(np.ones(4), a, b, np.array([1, 1, 1, 1, 0])))


def test_turn_costs_a_path_that_turns_at_a_contact():
    # a path 0-1-2 along x; from node 2 the edge (2, 3) goes on along x, the edge (2, 4)
    # turns up a right angle, the edge (2, 5) turns back
    nodes = np.array([[0.0, 0, 1], [0.1, 0, 1], [0.2, 0, 1], [0.3, 0, 1], [0.2, 0, 1.1], [0.1, 0.01, 1]])
    pred = np.array([-1, 0, 1, -1, -1, -1])
    kw = _pair(nodes=nodes, pred=pred)
    a, b = np.array([2, 4, 2]), np.array([3, 2, 5])
    assert edge_factors("turn", a, b, alpha=2.0, **kw) == pytest.approx([1.0, 2.0, 1.0 + 2 * 0.5 * 1.995], abs=1e-3)
