"""pipeline.rowpasses: a sparse product or a row reduction computed a block of rows at a time is scipy's whole-matrix one."""

from __future__ import annotations

from unittest.mock import patch

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import sparse

from pipeline import rowpasses


def _matrix(rng, rows: int, cols: int, density: float, dtype) -> sparse.csr_matrix:
    """A random CSR matrix with empty rows, duplicate-free, of ``dtype`` values."""
    m = sparse.random(rows, cols, density=density, format="csr", random_state=rng)
    if np.dtype(dtype).kind == "f":
        m.data = rng.normal(size=m.data.shape[0]).astype(dtype)
    else:
        m.data = rng.integers(1, 5, m.data.shape[0]).astype(dtype)
    return m


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(0, 300), cols=st.integers(1, 60), density=st.floats(0.0, 0.5),
       entries=st.integers(1, 40), seed=st.integers(0, 2**31 - 1),
       dtype=st.sampled_from([np.int8, np.int64, np.float32, np.float64]), width=st.sampled_from([0, 1, 4]))
def test_row_passes_equal_scipys_whole_matrix_results(rows, cols, density, entries, seed, dtype, width):
    # tiny passes, so that rows fall in many blocks (and long rows in blocks of their own)
    rng = np.random.default_rng(seed)
    a = _matrix(rng, rows, cols, density, dtype)
    x = rng.normal(size=(cols,) if width == 0 else (cols, width))
    values = np.abs(rng.normal(size=cols))
    with patch.object(rowpasses, "CACHE_ENTRIES", entries), patch.object(rowpasses.row_blocks, "__defaults__", (entries,)):
        blocks = list(rowpasses.row_blocks(a.indptr))
        got = rowpasses.sparse_product(a, x)
        sums = rowpasses.row_sums(a)
        peak = rowpasses.row_max(a, values)
    covered = [r for start, stop in blocks for r in range(start, stop)]
    assert covered == list(range(rows)) and all(stop > start for start, stop in blocks)
    want = a @ x
    assert got.dtype == want.dtype and np.array_equal(got, want)  # bit for bit
    want_sums = np.asarray(a.sum(axis=1)).ravel()
    assert sums.dtype == want_sums.dtype and np.array_equal(sums, want_sums)
    want_peak = np.array([values[a.indices[a.indptr[i] : a.indptr[i + 1]]].max(initial=0.0) for i in range(rows)])
    assert np.array_equal(peak, want_peak)


def test_sparse_product_of_int8_ones_gives_floats_and_other_layouts_go_to_scipy():
    a = sparse.csr_matrix(np.array([[1, 0, 1], [0, 0, 0], [1, 1, 1]], np.int8))
    x = np.array([0.5, 2.0, 4.0])
    got = rowpasses.sparse_product(a, x)
    assert got.dtype == np.float64 and got.tolist() == [4.5, 0.0, 6.5]
    assert rowpasses.row_sums(a).tolist() == [2, 0, 3]
    assert rowpasses.sparse_product(a.tocsc(), x).tolist() == [4.5, 0.0, 6.5]
    assert rowpasses.row_sums(a.tocsc()).tolist() == [2, 0, 3]


def test_kept_entries_is_scipys_matrix_of_the_kept_coordinates():
    rng = np.random.default_rng(3)
    a = _matrix(rng, 200, 200, 0.05, np.float64)
    on = rng.random(200) < 0.5
    with patch.object(rowpasses.row_blocks, "__defaults__", (7,)):  # many blocks
        got = rowpasses.kept_entries(a, lambda rows, lo, hi: on[rows] | on[a.indices[lo:hi]])
    c = a.tocoo()
    k = on[c.row] | on[c.col]
    want = sparse.csr_matrix((c.data[k], (c.row[k], c.col[k])), shape=a.shape)
    assert got.indices.dtype == np.int32 and got.nnz == int(k.sum())
    assert np.array_equal(got.indptr, want.indptr) and np.array_equal(got.indices, want.indices)
    assert np.array_equal(got.data, want.data)
