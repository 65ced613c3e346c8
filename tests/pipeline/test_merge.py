"""Reconciling trunks across tiles: ownership, duplicates, deterministic ids, id maps."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.merge import TileTrunks, position_order, reconcile_trunks


def _tile(tid, trunks, support, owned, diameter=None):
    trunks = np.asarray(trunks, dtype=np.float64).reshape(-1, 3)
    k = len(trunks)
    return TileTrunks(
        tid,
        trunks,
        np.asarray(support, dtype=np.float64),
        np.asarray(diameter if diameter is not None else np.arange(k) / 10 + tid, dtype=np.float64),
        np.asarray(owned, dtype=bool),
    )


def test_duplicate_on_a_border_keeps_the_higher_support():
    # tile 0 owns a trunk at x=9.98, tile 1 the same trunk at x=10.03 with more support
    a = _tile(0, [[9.98, 5.0, 0.0], [3.0, 5.0, 0.0]], [100, 80], [True, True], diameter=[0.20, 0.30])
    b = _tile(1, [[10.03, 5.0, 0.1], [15.0, 5.0, 0.0]], [120, 90], [True, True], diameter=[0.25, 0.35])
    g = reconcile_trunks([a, b], cluster_radius=0.8, fallback_radius=3.5)
    assert g.n_trees == 3
    assert np.allclose(g.trunks[:, 0], [3.0, 10.03, 15.0])
    assert g.owner.tolist() == [0, 1, 1]
    assert np.allclose(g.diameter, [0.30, 0.25, 0.35])
    assert g.id_maps[0].tolist() == [0, 2, 1]
    assert g.id_maps[1].tolist() == [0, 2, 3]


def test_tie_goes_to_the_lower_tile_id():
    a = _tile(4, [[9.9, 0.0, 0.0]], [50], [True])
    b = _tile(2, [[10.1, 0.0, 0.0]], [50], [True])
    g = reconcile_trunks([a, b], cluster_radius=0.8, fallback_radius=3.5)
    assert g.owner.tolist() == [2] and np.allclose(g.trunks[0, 0], 10.1)


def test_trunks_of_one_tile_are_never_merged():
    a = _tile(0, [[1.0, 1.0, 0.0], [1.5, 1.0, 0.0]], [10, 20], [True, True])
    assert reconcile_trunks([a], cluster_radius=0.8, fallback_radius=3.5).n_trees == 2


def test_buffer_trunks_map_to_the_owner_or_fallback_or_nothing():
    owner = _tile(0, [[5.0, 5.0, 0.0]], [10], [True])
    other = _tile(1, [[5.3, 5.0, 0.0], [7.5, 5.0, 0.0], [30.0, 5.0, 0.0]], [9, 2, 3], [False, False, False])
    g = reconcile_trunks([owner, other], cluster_radius=0.8, match_distance=1.0, fallback_radius=3.5)
    assert g.n_trees == 1
    assert g.id_maps[1].tolist() == [0, 1, 1, 0]


def test_no_trunks():
    g = reconcile_trunks([_tile(0, np.zeros((0, 3)), [], [])], cluster_radius=0.8, fallback_radius=3.5)
    assert g.n_trees == 0 and g.id_maps[0].tolist() == [0]


def test_position_order_rounds_to_millimetres():
    xy = np.array([[1.0004, 2.0], [1.0, 1.0], [0.5, 9.0]])
    assert position_order(xy).tolist() == [2, 1, 0]


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 10_000), perm_seed=st.integers(0, 10_000))
def test_ids_do_not_depend_on_tile_order(seed, perm_seed):
    rng = np.random.default_rng(seed)
    tiles = []
    for tid in range(6):
        k = int(rng.integers(0, 5))
        trunks = np.column_stack([rng.uniform(0, 30, k), rng.uniform(0, 20, k), rng.uniform(0, 1, k)])
        tiles.append(_tile(tid, trunks, rng.integers(1, 5, k), rng.random(k) < 0.7))
    g1 = reconcile_trunks(tiles, cluster_radius=0.8, fallback_radius=3.5)
    order = np.random.default_rng(perm_seed).permutation(len(tiles))
    g2 = reconcile_trunks([tiles[i] for i in order], cluster_radius=0.8, fallback_radius=3.5)
    assert np.array_equal(g1.trunks, g2.trunks)
    assert all(np.array_equal(g1.id_maps[t], g2.id_maps[t]) for t in g1.id_maps)
    # kept trunks of different tiles are never within the cluster radius of each other
    for i in range(g1.n_trees):
        for j in range(i + 1, g1.n_trees):
            if g1.owner[i] != g1.owner[j]:
                assert np.hypot(*(g1.trunks[i, :2] - g1.trunks[j, :2])) > 0.8
    # ids follow position
    assert np.array_equal(position_order(g1.trunks), np.arange(g1.n_trees))


def test_buffer_trunks_in_a_failed_tile_map_to_nothing():
    # tile 1 (core x 10..20) failed: tile 0 saw its trunk at x=12 in its buffer. That tree
    # has no owner; its buffer points must not join tile 0's tree at x=8 (3.9 m away,
    # within the fallback radius), which would swell that tree's crown
    a = _tile(0, [[8.0, 5.0, 0.0], [11.9, 5.0, 0.0], [10.3, 5.0, 0.0]], [100, 90, 80], [True, False, False])
    dead = np.array([[10.0, 0.0, 20.0, 10.0]])
    g = reconcile_trunks([a], cluster_radius=0.8, fallback_radius=5.0, dead_zones=dead)
    assert g.n_trees == 1 and g.id_maps[0].tolist() == [0, 1, 0, 0]
    # without a failed tile the fallback joins them (a buffer trunk the owner dropped)
    g = reconcile_trunks([a], cluster_radius=0.8, fallback_radius=5.0)
    assert g.id_maps[0].tolist() == [0, 1, 1, 1]
    # a trunk in the dead zone still takes a global trunk within the match distance: one
    # that the neighbour owns through its ownership margin
    b = _tile(2, [[10.2, 5.0, 0.0]], [120], [True])
    g = reconcile_trunks([a, b], cluster_radius=0.8, fallback_radius=5.0, dead_zones=dead)
    assert g.n_trees == 2 and g.id_maps[0].tolist() == [0, 1, 0, 2]
