"""Hand-checkable graph kernels: path lengths on a voxel block, subtree counts on small forests."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import sparse
from scipy.sparse import csgraph

from pipeline.enrichment import neighbourhood_matrix
from pipeline.graph import (
    bridge_floating,
    build_graph,
    check_graph_size,
    depths,
    node_pairs,
    pair_lengths,
    reweight,
    shortest_paths,
    stencil,
    subtree_sizes,
    symmetric_csr,
)
from pipeline.passes import CACHE_POINTS
from pipeline.voxels import voxelize


def test_3x3x3_block_path_lengths_are_1_sqrt2_sqrt3():
    # 27 voxels of 1 m, one point at each centre; edges reach the cube diagonal
    ii = np.stack(np.meshgrid(range(3), range(3), range(3), indexing="ij"), -1).reshape(-1, 3)
    xyz = ii + 0.5
    vox = voxelize(xyz, voxel_size=1.0)
    g = build_graph(vox.centroids, radius=1.75)
    corner = int(np.flatnonzero((vox.keys == 0).all(1))[0])
    sp = shortest_paths(g, np.array([corner]))
    d = dict(zip(map(tuple, vox.keys.tolist()), sp.dist))
    assert d[(0, 0, 0)] == 0
    assert d[(1, 0, 0)] == pytest.approx(1.0)
    assert d[(1, 1, 0)] == pytest.approx(np.sqrt(2))
    assert d[(1, 1, 1)] == pytest.approx(np.sqrt(3))
    assert d[(2, 2, 2)] == pytest.approx(2 * np.sqrt(3))
    assert d[(2, 1, 0)] == pytest.approx(1 + np.sqrt(2))
    assert (sp.source == corner).all()


def test_multi_source_assigns_nearest_source():
    # a path graph 0-1-2-3-4-5-6 with sources at both ends: middle goes to the nearer end
    xyz = np.column_stack([np.arange(7.0), np.zeros(7), np.zeros(7)])
    g = build_graph(xyz, radius=1.01)
    sp = shortest_paths(g, np.array([0, 6]))
    assert sp.source.tolist() == [0, 0, 0, 0, 6, 6, 6] or sp.source.tolist() == [0, 0, 0, 6, 6, 6, 6]
    assert sp.dist.tolist() == [0, 1, 2, 3, 2, 1, 0]
    assert sp.pred[0] == -1 and sp.pred[6] == -1


def test_subtree_counts_on_path_graph():
    # 0 <- 1 <- 2 <- 3 <- 4 : node i has 5 - i paths through it
    pred = np.array([-1, 0, 1, 2, 3])
    assert subtree_sizes(pred).tolist() == [5, 4, 3, 2, 1]
    assert depths(pred).tolist() == [0, 1, 2, 3, 4]


def test_subtree_counts_on_branching_forest():
    #       0            5
    #      / \           |
    #     1   4          6
    #    / \
    #   2   3
    pred = np.array([-1, 0, 1, 1, 0, -1, 5])
    assert subtree_sizes(pred).tolist() == [5, 3, 1, 1, 1, 2, 1]
    w = np.array([1, 1, 2, 3, 1, 1, 10.0])
    assert subtree_sizes(pred, w).tolist() == [8, 6, 2, 3, 1, 11, 10]


def test_subtree_counts_from_dijkstra_match_brute_force():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(0, 1, (300, 3))
    g = build_graph(xyz, radius=0.2)
    sp = shortest_paths(g, np.array([0, 1]))
    size = subtree_sizes(sp.pred)
    # brute force: walk every node to its root, counting visits
    brute = np.zeros(len(xyz))
    for i in range(len(xyz)):
        if sp.source[i] < 0:
            continue
        j = i
        while j >= 0:
            brute[j] += 1
            j = sp.pred[j]
    reached = sp.source >= 0
    assert np.array_equal(size[reached], brute[reached])


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(min_value=-1, max_value=30), min_size=1, max_size=40))
def test_subtree_sizes_sum_to_depths_plus_nodes(parents):
    # build a valid forest: parent index must be smaller than the child's
    pred = np.array([p if 0 <= p < i else -1 for i, p in enumerate(parents)])
    size = subtree_sizes(pred)
    # each node is counted once in its own subtree and once per ancestor
    assert size.sum() == pytest.approx(len(pred) + depths(pred).sum())
    assert (size >= 1).all()


def test_edges_are_symmetric_and_positive():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 1, (200, 3))
    g = build_graph(xyz, radius=0.25)
    assert (g != g.T).nnz == 0
    assert (g.data > 0).all()
    assert g.data.max() <= 0.25 + 1e-12


def test_enriched_weights_never_shorter_than_distance():
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 1, (200, 3))
    plain = build_graph(xyz, radius=0.25)
    feats = rng.uniform(0, 1, (200, 4))
    rich = build_graph(xyz, radius=0.25, edge_scale=feats)
    assert rich.nnz == plain.nnz
    assert (rich.data >= plain.data - 1e-12).all()


def test_int32_limit_is_checked_up_front():
    with pytest.raises(ValueError, match="int32"):
        check_graph_size(2**31, 10)


def test_floating_fragment_is_bridged_but_grounded_objects_are_not():
    # a trunk column 0..1 m, a crown fragment 1.4..2 m above it (gap 0.4 m), and a post
    # standing on the ground 0.5 m away from the trunk
    trunk = np.column_stack([np.zeros(11), np.zeros(11), np.linspace(0, 1, 11)])
    crown = np.column_stack([np.zeros(7), np.zeros(7), np.linspace(1.4, 2.0, 7)])
    post = np.column_stack([np.full(8, 0.5), np.zeros(8), np.linspace(0, 0.7, 8)])
    nodes = np.concatenate([trunk, crown, post])
    height = nodes[:, 2]
    g = build_graph(nodes, radius=0.15)
    assert csgraph.connected_components(g, directed=False)[0] == 3
    b = bridge_floating(g, nodes, height, floating_height=0.5, max_gap=1.0)
    n, comp = csgraph.connected_components(b, directed=False)
    assert n == 2
    assert comp[11] == comp[0]  # the crown joined the trunk (nearest), not the post
    assert comp[18] != comp[0]  # the grounded post stays separate
    assert b.nnz == g.nnz + 2  # one symmetric edge


def _trunk_and_two_fragments():
    # a trunk column 0..1 m; fragment A at 1.5 m (0.5 m above the trunk's top) and
    # fragment B 0.35 m above A: A and B are each other's nearest component
    trunk = np.column_stack([np.zeros(11), np.zeros(11), np.linspace(0, 1, 11)])
    a = np.column_stack([np.linspace(0, 0.3, 4), np.zeros(4), np.full(4, 1.5)])
    b = np.column_stack([np.linspace(0, 0.3, 4), np.zeros(4), np.full(4, 1.85)])
    nodes = np.concatenate([trunk, a, b])
    return nodes, build_graph(nodes, radius=0.15)


def test_two_fragments_hang_from_the_ground_not_from_each_other():
    # linking each fragment to its nearest component would pair A and B into an
    # island that never reaches the ground (a crown whose trunk is never found)
    nodes, g = _trunk_and_two_fragments()
    assert csgraph.connected_components(g, directed=False)[0] == 3
    b = bridge_floating(g, nodes, nodes[:, 2], floating_height=0.5, max_gap=1.0)
    assert csgraph.connected_components(b, directed=False)[0] == 1
    added = sparse.triu(b - g).tocoo()
    # each fragment has one edge, to the trunk's top node (index 10): 0.5 m and 0.85 m
    assert sorted(zip(added.row.tolist(), added.col.tolist())) == [(10, 11), (10, 15)]
    assert np.allclose(sorted(added.data), [0.5, 0.85])


def test_a_fragment_out_of_reach_of_the_ground_hangs_from_a_lower_fragment():
    # with a 0.6 m reach B cannot reach the trunk (0.85 m) but reaches A (0.35 m), which
    # is lower; A hangs from the trunk
    nodes, g = _trunk_and_two_fragments()
    b = bridge_floating(g, nodes, nodes[:, 2], floating_height=0.5, max_gap=0.6)
    assert csgraph.connected_components(b, directed=False)[0] == 1
    added = sparse.triu(b - g).tocoo()
    assert sorted(zip(added.row.tolist(), added.col.tolist())) == [(10, 11), (11, 15)]
    # a fragment never hangs from a higher one: without the trunk's reach, A stays
    # apart and B still hangs from A
    b = bridge_floating(g, nodes, nodes[:, 2], floating_height=0.5, max_gap=0.4)
    n, comp = csgraph.connected_components(b, directed=False)
    assert n == 2 and comp[11] == comp[15] != comp[0]
    added = sparse.triu(b - g).tocoo()
    assert list(zip(added.row.tolist(), added.col.tolist())) == [(11, 15)]


def test_one_neighbour_search_serves_both_radii():
    # the graph and the neighbourhood matrix built from one search at the larger
    # radius equal those built from their own searches
    rng = np.random.default_rng(5)
    nodes = rng.uniform(0, 1.0, (3000, 3))
    pairs = node_pairs(nodes, 0.25)
    own = build_graph(nodes, radius=0.15)
    shared = build_graph(nodes, radius=0.15, candidates=pairs)
    assert own.nnz == shared.nnz > 0
    assert abs(own - shared).max() == 0
    assert abs(neighbourhood_matrix(nodes, radius=0.25) - neighbourhood_matrix(nodes, radius=0.25, candidates=pairs)).max() == 0
    assert shared.max() <= 0.15


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 40), st.integers(0, 10_000), st.booleans())
def test_symmetric_csr_equals_scipys_canonical_matrix(m, seed, with_diagonal):
    rng = np.random.default_rng(seed)
    upper = np.argwhere(np.triu(rng.random((m, m)) < 0.3, k=1))
    pairs = upper[rng.permutation(len(upper))]  # any order, as the KD-tree gives them
    w = rng.random(len(pairs)) + 0.1
    diag = rng.random(m) if with_diagonal else None
    got = symmetric_csr(pairs, w, m, diagonal=diag)
    rows = [pairs[:, 0], pairs[:, 1]] + ([np.arange(m)] if with_diagonal else [])
    cols = [pairs[:, 1], pairs[:, 0]] + ([np.arange(m)] if with_diagonal else [])
    vals = [w, w] + ([diag] if with_diagonal else [])
    want = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(m, m))
    assert got.has_sorted_indices
    # the same arrays, element for element: sparse products sum in the same order
    np.testing.assert_array_equal(got.indptr, want.indptr)
    np.testing.assert_array_equal(got.indices, want.indices)
    np.testing.assert_array_equal(got.data, want.data)


def test_pair_lengths_by_hand():
    pts = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [1.0, 2.0, 2.0]])
    np.testing.assert_allclose(pair_lengths(pts, np.array([[0, 1], [0, 2], [1, 2], [2, 2]])), [5.0, 3.0, np.sqrt(12.0), 0.0])
    assert pair_lengths(pts, np.zeros((0, 2), np.int64)).shape == (0,)


@settings(max_examples=100, deadline=None)
@given(m=st.integers(1, 200), p=st.integers(0, 500), dims=st.sampled_from([2, 3]), seed=st.integers(0, 2**31 - 1))
def test_pair_lengths_equal_the_definition_bit_for_bit(m, p, dims, seed):
    """Pairs in any order, strided or not: the same floats as the square root of the
    summed squared steps, coordinate by coordinate (the graphs' weights depend on them)."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(m, dims)) * 10.0 ** rng.integers(-2, 4)
    pairs = rng.integers(0, m, (p, 2))
    step = (pts[pairs[:, 0]] - pts[pairs[:, 1]]) ** 2
    want = np.zeros(p)
    for d in range(dims):
        want += step[:, d]
    np.testing.assert_array_equal(pair_lengths(pts, pairs), np.sqrt(want))
    strided = np.repeat(pairs, 2, axis=1)[:, ::2]  # the same pairs, columns 16 bytes apart
    np.testing.assert_array_equal(pair_lengths(np.asfortranarray(pts), strided), np.sqrt(want))


def test_pair_lengths_across_passes_equal_the_definition_bit_for_bit():
    """More pairs than one cache-sized pass holds: each pass's lengths are the whole's."""
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(1000, 3)) * 30.0
    pairs = rng.integers(0, 1000, (2 * CACHE_POINTS + 7, 2)).astype(np.int32)
    step = (pts[pairs[:, 0]] - pts[pairs[:, 1]]) ** 2
    want = np.zeros(pairs.shape[0])
    for d in range(3):
        want += step[:, d]
    np.testing.assert_array_equal(pair_lengths(pts, pairs), np.sqrt(want))


def test_reweight_keeps_the_structure_and_scales_each_edge():
    g = build_graph(np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]]), radius=0.15)
    r = reweight(g, np.array([1.0, 3.0, 5.0]))
    np.testing.assert_allclose(r.toarray(), g.toarray() * np.array([[0, 2, 3], [2, 0, 4], [3, 4, 0]]))
    # a matrix whose rows are not sorted gives the same result as its sorted form
    messy = sparse.csr_matrix((g.data[::-1].copy(), g.indices[::-1].copy(), g.indptr.copy()), shape=g.shape)
    messy.has_sorted_indices = False
    assert (reweight(messy, np.array([1.0, 3.0, 5.0])) != reweight(messy.sorted_indices(), np.array([1.0, 3.0, 5.0]))).nnz == 0


def test_reweight_a_few_rows_at_a_time_equals_the_whole_formula_bit_for_bit():
    from unittest.mock import patch

    from pipeline import rowpasses

    rng = np.random.default_rng(8)
    g = build_graph(rng.uniform(0, 2, (400, 3)), radius=0.3)
    cost = 1.0 + rng.uniform(0, 3, 400)
    row = np.repeat(np.arange(400), np.diff(g.indptr))
    want = g.data * 0.5 * (cost[row] + cost[g.indices])
    with patch.object(rowpasses.row_blocks, "__defaults__", (7,)):  # passes of about 7 edges
        got = reweight(g, cost)
    assert np.array_equal(got.data, want) and np.array_equal(got.indices, g.indices) and np.array_equal(got.indptr, g.indptr)


def _blocks(seed: int, n: int = 4000) -> np.ndarray:
    """Points of a small generated stand: trunks (vertical lines), crowns (noisy balls),
    grass (a noisy plane) and scattered outliers, over 6 x 4 x 4 m."""
    rng = np.random.default_rng(seed)
    parts = [rng.uniform([0, 0, 0], [6, 4, 0.2], (n // 4, 3))]
    for cx in (1.5, 4.5):
        parts.append(np.column_stack([rng.normal(cx, 0.05, n // 8), rng.normal(2, 0.05, n // 8), rng.uniform(0, 2, n // 8)]))
        parts.append(rng.normal([cx, 2, 2.6], 0.6, (n // 4, 3)))
    parts.append(rng.uniform([0, 0, 0], [6, 4, 4], (n // 50, 3)))
    return np.concatenate(parts)


def _pair_set(found) -> dict:
    return {(int(a), int(b)): float(w) for (a, b), w in zip(found.pairs, found.length)}


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize("voxel, radius", [(0.1, 0.25), (0.1, 0.15), (0.1, 0.2), (0.1, 0.1), (0.05, 0.3), (0.2, 0.25)])
def test_voxel_offset_graph_equals_the_kd_tree_graph_edge_for_edge(seed, voxel, radius):
    # the voxel-offset search (keys) against the k-d tree reference (no keys): the same
    # pairs with the same lengths, and the same matrices array for array
    xyz = _blocks(seed)
    vox = voxelize(xyz, voxel_size=voxel, grid_origin=(-0.37, 0.11, -0.05))
    nodes = vox.centroids
    ref = node_pairs(nodes, radius)
    got = node_pairs(nodes, radius, keys=vox.keys, voxel_size=voxel)
    assert len(got) == len(ref) > 0
    assert _pair_set(got) == _pair_set(ref)
    assert (got.pairs[:, 0] < got.pairs[:, 1]).all()
    small = min(radius, 0.15)
    for mine, theirs in (
        (build_graph(nodes, radius=small, candidates=got), build_graph(nodes, radius=small)),
        (build_graph(nodes, radius=small, edge_scale=np.cos(nodes), candidates=got), build_graph(nodes, radius=small, edge_scale=np.cos(nodes))),
        (neighbourhood_matrix(nodes, radius=radius, candidates=got), neighbourhood_matrix(nodes, radius=radius)),
    ):
        assert mine.has_sorted_indices
        np.testing.assert_array_equal(mine.indptr, theirs.indptr)
        np.testing.assert_array_equal(mine.indices, theirs.indices)
        np.testing.assert_array_equal(mine.data, theirs.data)


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, 10_000),
    st.integers(0, 300),
    st.sampled_from([0.05, 0.1, 0.3]),
    st.floats(1.0, 6.0),
)
def test_voxel_offset_pairs_equal_the_kd_tree_pairs(seed, n, voxel, ratio):
    # any cloud (including empty, one point, and clouds one voxel thick), any radius the
    # parameters allow (voxel size to 6 voxel sizes)
    rng = np.random.default_rng(seed)
    extent = rng.choice([0.3, 1.0, 3.0], 3)
    xyz = rng.uniform(-extent, extent, (n, 3)) + rng.uniform(-1e3, 1e3, 3)
    vox = voxelize(xyz, voxel_size=voxel)
    got = node_pairs(vox.centroids, voxel * ratio, keys=vox.keys, voxel_size=voxel)
    assert _pair_set(got) == _pair_set(node_pairs(vox.centroids, voxel * ratio))
    radius = voxel * ratio
    m = vox.n
    mine = symmetric_csr(got, got.length, m, diagonal=np.ones(m))
    theirs = symmetric_csr(got.pairs[::-1], got.length[::-1], m, diagonal=np.ones(m))  # no groups: the general path
    np.testing.assert_array_equal(mine.indices, theirs.indices)
    np.testing.assert_array_equal(mine.data, theirs.data)
    assert got.within(radius / 2).groups[-1] == len(got.within(radius / 2))


def test_stencil_by_hand():
    # radius of one voxel: offsets up to 2 along at most one axis (two voxels apart the
    # nodes can still be 0+ apart; along two axes they are at least 0.1 x sqrt 2 apart):
    # 27 + 3 x 2 x 9 = 81 offsets, without (0, 0, 0) and halved: 40
    off = stencil(0.1, 0.1)
    assert off.shape == (40, 3)
    assert ((np.abs(off) == 2).sum(1) <= 1).all()
    assert (off == [0, 0, 1]).all(1).any() and not (off == [0, 0, -1]).all(1).any()
    # each offset or its negation, never both
    both = {tuple(o) for o in off} & {tuple(-o) for o in off}
    assert not both
    assert (np.diff(off[:, 0] * 100 + off[:, 1] * 10 + off[:, 2]) > 0).all()  # ascending
