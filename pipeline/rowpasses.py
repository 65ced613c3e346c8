"""A sparse matrix's products and row reductions a block of rows at a time.

scipy casts a whole matrix's values to the product's type first: an int8 0/1
neighbourhood matrix of ten million entries became 80 MB of float64 each time, fresh
pages the kernel must zero. A block of rows at a time keeps that temporary in the
CPU's cache, with the same values (docs/performance.md). Apart from
:mod:`pipeline.passes` so that what reads a block before the pipeline runs does not
import scipy.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np
from scipy import sparse

#: stored entries of a sparse matrix per pass: a float64 block of them is 512 KiB
CACHE_ENTRIES = 1 << 16


def row_blocks(indptr: np.ndarray, entries: int = CACHE_ENTRIES) -> Iterator[tuple[int, int]]:
    """Runs of rows (start, stop) of a CSR matrix's ``indptr`` (r + 1,) holding about
    ``entries`` stored entries each (at least one row), covering every row in order."""
    r = indptr.shape[0] - 1
    start = 0
    while start < r:
        # the first row past start whose entries end beyond the budget
        stop = int(np.searchsorted(indptr, indptr[start] + entries, side="right")) - 1
        stop = min(max(stop, start + 1), r)
        yield start, stop
        start = stop


def _block(a: sparse.csr_matrix, start: int, stop: int, dtype) -> sparse.csr_matrix:
    lo, hi = int(a.indptr[start]), int(a.indptr[stop])
    return sparse.csr_matrix((a.data[lo:hi].astype(dtype), a.indices[lo:hi], a.indptr[start : stop + 1] - lo),
                             shape=(stop - start, a.shape[1]))


def sparse_product(a: sparse.csr_matrix, x: np.ndarray) -> np.ndarray:
    """``a @ x`` for a sparse matrix ``a`` (r, c) and a dense ``x`` (c,) or (c, k), a block
    of rows at a time when ``a`` is CSR: the same values and type as scipy's product,
    (r,) or (r, k).

    Each row's sum runs over its entries in stored order whatever block it is in, and
    only a block's values are cast to the product's type.
    """
    if a.format != "csr":  # another layout sums in another order
        return a @ x
    x = np.asarray(x)
    dtype = np.result_type(a.dtype, x.dtype)
    x = np.ascontiguousarray(x, dtype=dtype)
    out = np.zeros((a.shape[0],) + x.shape[1:], dtype)
    for start, stop in row_blocks(a.indptr):
        out[start:stop] = _block(a, start, stop, dtype) @ x
    return out


def _sum_dtype(dtype: np.dtype) -> np.dtype:
    """The type scipy sums a matrix of ``dtype`` in: small integers widened, as numpy's sum does."""
    if dtype.kind == "u" and np.can_cast(dtype, np.uint):
        return np.dtype(np.uint)
    if np.can_cast(dtype, np.int_):
        return np.dtype(np.int_)
    return dtype


def row_sums(a: sparse.csr_matrix) -> np.ndarray:
    """``np.asarray(a.sum(axis=1)).ravel()`` for a sparse matrix ``a`` (r, c), a block of
    rows at a time when ``a`` is CSR: the same values and type, (r,)."""
    if a.format != "csr":
        return np.asarray(a.sum(axis=1)).ravel()
    out = np.zeros(a.shape[0], _sum_dtype(a.dtype))
    for start, stop in row_blocks(a.indptr):
        lo = a.indptr[start]
        rows = start + np.flatnonzero(np.diff(a.indptr[start : stop + 1]))
        if rows.size:  # scipy's reduction of each non-empty row's run
            out[rows] = np.add.reduceat(a.data[lo : a.indptr[stop]], a.indptr[rows] - lo)
    return out


def row_max(a: sparse.csr_matrix, values: np.ndarray) -> np.ndarray:
    """Maximum of ``values`` (c,) over each row's stored columns of a CSR matrix ``a``
    (r, c), 0 for a row without any, (r,) float64; a block of rows at a time."""
    a = a.tocsr()
    out = np.zeros(a.shape[0])
    for start, stop in row_blocks(a.indptr):
        lo = a.indptr[start]
        rows = start + np.flatnonzero(np.diff(a.indptr[start : stop + 1]))
        if rows.size:
            out[rows] = np.maximum.reduceat(values[a.indices[lo : a.indptr[stop]]], a.indptr[rows] - lo)
    return out


def block_rows(indptr: np.ndarray, start: int, stop: int) -> np.ndarray:
    """The row of each stored entry of rows ``start:stop`` of a CSR ``indptr``, in order."""
    return np.repeat(np.arange(start, stop), np.diff(indptr[start : stop + 1]))


def kept_entries(a: sparse.csr_matrix, test: Callable[[np.ndarray, int, int], np.ndarray],
                 data: Callable[[np.ndarray], np.ndarray] | None = None) -> sparse.csr_matrix:
    """The CSR matrix of the stored entries of ``a`` that ``test`` keeps, in their order:
    what scipy builds from their coordinates, without every entry's coordinates and tests
    as fresh temporaries. ``test(rows, lo, hi)`` maps entries ``lo:hi`` (a block of whole
    rows; ``rows`` their rows) to their (hi - lo,) bool; ``data(keep)`` gives the kept
    entries' values (default ``a.data[keep]``). Indices are int32 where they fit, as
    scipy's."""
    indptr = a.indptr
    keep = np.empty(a.indices.shape[0], bool)
    kept = np.zeros(indptr.shape[0], np.int64)  # entries kept before each row
    for start, stop in row_blocks(indptr):
        lo, hi = int(indptr[start]), int(indptr[stop])
        k = keep[lo:hi]
        k[:] = test(block_rows(indptr, start, stop), lo, hi)
        kept[start + 1 : stop + 1] = kept[start] + np.r_[0, np.cumsum(k)][indptr[start + 1 : stop + 1] - lo]
    index = np.int32 if max(int(kept[-1]), *a.shape) <= np.iinfo(np.int32).max else np.int64
    values = a.data[keep] if data is None else data(keep)
    return sparse.csr_matrix((values, a.indices[keep].astype(index, copy=False), kept.astype(index)), shape=a.shape)
