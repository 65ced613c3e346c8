"""pipeline.passes: a test computed a pass at a time is the whole's."""

from __future__ import annotations

import numpy as np

from pipeline.passes import CACHE_POINTS, indices_where


def test_indices_where_equals_flatnonzero_across_passes():
    rng = np.random.default_rng(6)
    for n in (0, 1, CACHE_POINTS - 1, CACHE_POINTS, 3 * CACHE_POINTS + 7):
        h = rng.uniform(-1, 3, n)
        t = rng.integers(0, 4, n)
        got = indices_where(n, lambda s: (t[s] > 0) & (h[s] >= 0.2) & (h[s] < 0.5))
        want = np.flatnonzero((t > 0) & (h >= 0.2) & (h < 0.5))
        assert got.dtype == np.int64 and np.array_equal(got, want)
