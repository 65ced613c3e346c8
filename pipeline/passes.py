"""Whole-array steps a cache-sized pass at a time.

A chain of numpy steps over every point of a block (compare, combine, select) passes
each step's temporary through main memory; over CACHE_POINTS points at a time the
temporaries stay in the CPU's cache and come from the allocator's free list, not from
fresh pages the kernel must zero. The same values, two to three times faster on a
few million points (docs/performance.md).

A sparse matrix's products and row reductions go a block of rows at a time for the
same reason (:mod:`pipeline.rowpasses`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: points per pass: a float64 temporary is 128 KiB
CACHE_POINTS = 1 << 14


def indices_where(n: int, test: Callable[[slice], np.ndarray]) -> np.ndarray:
    """``np.flatnonzero(test(slice(0, n)))``, computed CACHE_POINTS points at a time.

    ``test`` maps a slice of the points to their (len,) bool array; it must look at
    those points only (elementwise), so that the passes join into the whole's answer.
    """
    found = [np.zeros(0, np.int64)]
    for a in range(0, n, CACHE_POINTS):
        found.append(a + np.flatnonzero(test(slice(a, min(n, a + CACHE_POINTS)))))
    return np.concatenate(found)
