"""pipeline.woodleaf.neighbourhood_max: the maximum over each node's neighbours."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import sparse

from pipeline.woodleaf import neighbourhood_max


def _by_definition(values, adjacency):
    """The row maxima of the matrix holding each neighbour's value (scipy counts a row's
    implicit zeros in, which never exceed non-negative values)."""
    a = adjacency.tocsr(copy=True)
    a.data = values[a.indices].astype(np.float64)
    return np.asarray(a.max(axis=1).todense()).ravel()


def test_by_hand():
    # node 0: neighbours 1 and 2; node 1: none; node 2: itself; node 3: node 1 only
    adj = sparse.csr_matrix(np.array([[0, 1, 1, 0], [0, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0]], float))
    got = neighbourhood_max(np.array([5.0, 2.0, 7.0, 9.0]), adj)
    np.testing.assert_array_equal(got, [7.0, 0.0, 7.0, 2.0])
    assert got.dtype == np.float64


def test_no_nodes():
    assert neighbourhood_max(np.zeros(0), sparse.csr_matrix((0, 0))).shape == (0,)


@settings(max_examples=150, deadline=None)
@given(
    m=st.integers(1, 60),
    density=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**31 - 1),
    integer=st.booleans(),
)
def test_equals_the_row_maxima_of_the_value_matrix(m, density, seed, integer):
    rng = np.random.default_rng(seed)
    adj = sparse.random(m, m, density=density, format="csr", random_state=rng)
    values = rng.integers(0, 5, m) if integer else rng.random(m) * (rng.random(m) < 0.7)
    got = neighbourhood_max(values, adj)
    np.testing.assert_array_equal(got, _by_definition(values, adj))
    assert got.dtype == np.float64
