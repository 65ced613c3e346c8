"""Voxel index maps round-trip and every point belongs to exactly one voxel."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.voxels import _group_keys, column_max, column_min, packed_keys, voxelize

coords = arrays(np.float64, st.tuples(st.integers(1, 300), st.just(3)), elements=st.floats(-50, 50, allow_nan=False))


@settings(max_examples=40, deadline=None)
@given(coords, st.sampled_from([0.05, 0.1, 0.5]))
def test_index_maps_round_trip(xyz, size):
    vox = voxelize(xyz, voxel_size=size, grid_origin=(0.3, -1.0, 2.0))
    # every point maps to the voxel whose key contains it
    keys = np.floor((xyz - np.array([0.3, -1.0, 2.0])) / size).astype(np.int64)
    assert np.array_equal(vox.keys[vox.point_voxel], keys)
    # counts and centroids agree with the map
    assert vox.counts.sum() == len(xyz)
    assert np.array_equal(np.bincount(vox.point_voxel, minlength=vox.n), vox.counts)
    for d in range(3):
        mean = np.bincount(vox.point_voxel, weights=xyz[:, d], minlength=vox.n) / vox.counts
        assert np.allclose(mean, vox.centroids[:, d])
    # keys are unique
    assert len({tuple(k) for k in vox.keys.tolist()}) == vox.n


@settings(max_examples=40, deadline=None)
@given(coords, st.sampled_from([0.05, 0.1, 0.5]))
def test_packed_keys_pack_each_points_key_relative_to_the_lowest(xyz, size):
    origin = (0.3, -1.0, 2.0)
    keys = np.floor((xyz - np.array(origin)) / size).astype(np.int64)
    packed, lo, span = packed_keys(xyz, size, origin)
    rel = keys - keys.min(axis=0)
    np.testing.assert_array_equal(lo, keys.min(axis=0))
    np.testing.assert_array_equal(span, rel.max(axis=0) + 1)
    np.testing.assert_array_equal(packed, (rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2])
    assert packed.dtype == np.int64


def test_shared_grid_origin_gives_same_voxels_for_subsets():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 10, (5000, 3))
    full = voxelize(xyz, voxel_size=0.1)
    part = voxelize(xyz[xyz[:, 0] < 5], voxel_size=0.1)
    assert np.array_equal(full.keys[full.point_voxel][xyz[:, 0] < 5], part.keys[part.point_voxel])


def test_empty_input():
    vox = voxelize(np.zeros((0, 3)), voxel_size=0.1)
    assert vox.n == 0 and vox.point_voxel.shape == (0,)


@settings(max_examples=50, deadline=None)
@given(arrays(np.int64, st.tuples(st.integers(1, 50), st.integers(1, 4)), elements=st.integers(-(2**40), 2**40)))
def test_column_min_and_max_equal_numpys_reductions(a):
    np.testing.assert_array_equal(column_min(a), a.min(axis=0))
    np.testing.assert_array_equal(column_max(a), a.max(axis=0))
    assert column_min(a).dtype == a.dtype


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 199), min_size=60, max_size=400), st.sampled_from([200, 10_000]))
def test_grouping_keys_equals_numpys_unique_on_dense_and_sparse_grids(keys, n_keys):
    # 200 cells for 60 to 400 keys are counted in a dense grid, 10,000 sorted
    packed = np.asarray(keys, dtype=np.int64)
    uniq, inverse, counts = _group_keys(packed, n_keys)
    u, i, c = np.unique(packed, return_inverse=True, return_counts=True)
    assert np.array_equal(uniq, u) and np.array_equal(inverse, i) and np.array_equal(counts, c)
    assert inverse.dtype == np.int64 and uniq.dtype == np.int64 and counts.dtype == np.int64


def test_packed_keys_and_column_extremes_across_cache_sized_passes():
    # more points than one pass of CACHE_POINTS: every pass packs its points alike
    from pipeline.passes import CACHE_POINTS

    rng = np.random.default_rng(3)
    xyz = rng.uniform(-20, 20, (2 * CACHE_POINTS + 17, 3))
    origin = (0.3, -1.0, 2.0)
    keys = np.floor((xyz - np.array(origin)) / 0.1).astype(np.int64)
    packed, lo, span = packed_keys(xyz, 0.1, origin)
    rel = keys - keys.min(axis=0)
    np.testing.assert_array_equal(lo, keys.min(axis=0))
    np.testing.assert_array_equal(packed, (rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2])
    np.testing.assert_array_equal(column_min(xyz), xyz.min(axis=0))
    np.testing.assert_array_equal(column_max(xyz), xyz.max(axis=0))
    xyz[CACHE_POINTS + 5, 1] = np.nan  # a NaN in a later pass comes through as numpy's does
    np.testing.assert_array_equal(column_min(xyz), xyz.min(axis=0))


def test_rows_by_column_are_the_rows_and_voxelize_alike():
    from pipeline.voxels import rows_by_column

    rng = np.random.default_rng(5)
    xyz = rng.uniform(-3, 3, (40_000, 3))
    rows = np.flatnonzero(xyz[:, 2] > 0)
    got = rows_by_column(xyz, rows)
    assert got.flags.f_contiguous and np.array_equal(got, xyz[rows])
    a, b = voxelize(got, voxel_size=0.1), voxelize(xyz[rows], voxel_size=0.1)
    for f in ("point_voxel", "keys", "centroids", "counts"):
        assert getattr(a, f).tobytes() == getattr(b, f).tobytes()


def test_cell_index_is_the_whole_column_formula():
    # reference: floor((v - origin) / cell) over the whole column, as cell_index was before
    # it went a cache-sized pass at a time
    from pipeline.passes import CACHE_POINTS
    from pipeline.voxels import cell_index

    rng = np.random.default_rng(3)
    n = 2 * CACHE_POINTS + 5
    v = rng.uniform(-40, 60, n)
    v[:100] = np.round(v[:100] / 0.25) * 0.25  # on cell edges
    for col, origin in ((v, np.float64(0.1)), (v, -3.0), (v.astype(np.float32), 0.1), (v[:7], 2.5)):
        t = np.subtract(col, origin)
        np.divide(t, 0.25, out=t)
        np.floor(t, out=t)
        got = cell_index(col, origin, 0.25)
        assert got.dtype == np.int64 and np.array_equal(got, t.astype(np.int64))
    assert cell_index(np.zeros(0), 0.0, 0.25).shape == (0,)
