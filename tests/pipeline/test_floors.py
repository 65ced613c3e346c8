"""Per-group percentiles of the size floors (pipeline.floors)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.floors import group_percentile, group_percentiles


def _by_lexsort(values, group, n_groups, q):
    """The definition: values sorted by group, then value (one lexsort); the nearest rank in each group."""
    keep = group >= 0
    order = np.lexsort((values[keep], group[keep]))
    v, g = values[keep][order], group[keep][order]
    start = np.searchsorted(g, np.arange(n_groups))
    end = np.searchsorted(g, np.arange(n_groups), side="right")
    out = np.full(n_groups, -np.inf)
    has = end > start
    out[has] = v[(start + np.floor((end - start - 1) * q / 100.0).astype(np.int64))[has]]
    return out


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 300), n_groups=st.integers(1, 12),
       zeros=st.booleans(), nans=st.booleans(), many_groups=st.booleans())
def test_group_percentiles_are_the_lexsorted_nearest_ranks(seed, n, n_groups, zeros, nans, many_groups):
    rng = np.random.default_rng(seed)
    values = np.round(rng.normal(0, 1, n), 1)  # ties
    if zeros:  # signed zeros compare equal but differ in their bytes
        values[rng.random(n) < 0.3] = -0.0
        values[rng.random(n) < 0.3] = 0.0
    if nans:
        values[rng.random(n) < 0.1] = np.nan
    if many_groups:  # group ids past a 16-bit sort's reach
        n_groups = 70_000
    group = rng.integers(-1, n_groups, n)
    qs = (90.0, 10.0, 0.0, 100.0, 50.0)
    got = group_percentiles(values, group, n_groups, qs)
    for row, q in zip(got, qs):
        want = _by_lexsort(values, group, n_groups, q)
        assert row.tobytes() == want.tobytes()
        assert group_percentile(values, group, n_groups, q).tobytes() == want.tobytes()
