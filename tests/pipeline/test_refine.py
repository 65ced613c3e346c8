"""Refinement of contested nodes on hand-built graphs."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.graph import build_graph, shortest_paths
from pipeline.params import SegmentParams
from pipeline.refine import contested_nodes, random_walk, refine_contested, rival_distance
from pipeline.segment import segment_nodes


def _line(a, b, step=0.1):
    """Nodes every ``step`` from ``a`` to ``b`` (both included)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = int(round(np.linalg.norm(b - a) / step)) + 1
    return a + np.linspace(0, 1, n)[:, None] * (b - a)


def _touching_crowns():
    """Two trees whose crowns touch at one twig.

    Tree A (trunk at x = 0) holds a dense twig cluster at x 1.6-2.0 m, 1 m up; tree B
    (trunk at x = 3.8 m) reaches it with a single thin twig whose tip lies 0.12 m from
    the cluster's end node: one edge. B's path to that end node is shorter than A's by
    a few centimetres, so shortest paths give it to B; it hangs on A's cluster by eight
    edges.
    """
    trunk_a = _line([0, 0, 0], [0, 0, 0.9])
    branch_a = _line([0, 0, 1.0], [1.5, 0, 1.0])
    g = np.arange(3) * 0.1 - 0.1
    cluster = np.array([[x, y, z + 1.0] for x in np.arange(16, 21) * 0.1 for y in g for z in g])
    trunk_b = _line([3.8, 0.22, 0], [3.8, 0.22, 0.9])
    twig_b = _line([3.8, 0.22, 1.0], [2.0, 0.22, 1.0])
    parts = [trunk_a, branch_a, cluster, trunk_b, twig_b]
    nodes = np.vstack(parts)
    tree = np.repeat([1, 1, 1, 2, 2], [len(p) for p in parts])
    sources = np.array([0, len(trunk_a) + len(branch_a) + len(cluster)])
    return nodes, tree, sources


def _segment(nodes, sources, method):
    graph = build_graph(nodes, radius=0.15)
    params = SegmentParams(method=method, contest_margin=0.3, unreached_radius=0.6)
    seg = segment_nodes(nodes, graph, source_nodes=sources, source_trunk=np.array([0, 1]),
                        trunk_xy=nodes[sources, :2], node_height=nodes[:, 2], params=params)
    return seg.node_tree


def test_a_twig_that_touches_the_neighbour_stays_with_its_own_branch():
    nodes, tree, sources = _touching_crowns()
    paths = _segment(nodes, sources, "paths")
    wrong = np.flatnonzero(paths != tree)
    assert wrong.size >= 1  # the contact node goes to the neighbour by shortest path
    assert (tree[wrong] == 1).all()
    refined = _segment(nodes, sources, "refined")
    np.testing.assert_array_equal(refined, tree)


def test_rival_distance_is_the_other_trunks_shortest_path():
    nodes, tree, sources = _touching_crowns()
    graph = build_graph(nodes, radius=0.15)
    sp = shortest_paths(graph, sources)
    node_tree = np.where(sp.source == sources[0], 1, 2)
    rival_dist, rival = rival_distance(graph, node_tree, sp.dist)
    own = shortest_paths(graph, sources[:1]).dist, shortest_paths(graph, sources[1:]).dist
    expect = np.where(node_tree == 1, own[1], own[0])
    np.testing.assert_allclose(rival_dist, expect)
    np.testing.assert_array_equal(rival, 3 - node_tree)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), margin=st.floats(0.0, 2.0))
def test_nodes_only_one_trunk_reaches_never_move(seed, margin):
    """Three random clouds: two joined (both trunks reach them), one apart with its own
    trunk; neither the lone cloud nor any node no rival path reaches changes tree."""
    rng = np.random.default_rng(seed)
    a = rng.uniform([0, 0, 0], [2, 1, 1], (120, 3))
    b = rng.uniform([1.5, 0, 0], [3.5, 1, 1], (120, 3))
    c = rng.uniform([10, 0, 0], [11, 1, 1], (60, 3))
    nodes = np.vstack([a, b, c])
    graph = build_graph(nodes, radius=0.35)
    sources = np.array([0, 120, 240])
    sp = shortest_paths(graph, sources)
    node_tree = np.zeros(len(nodes), np.int64)
    reached = sp.source >= 0
    node_tree[reached] = np.searchsorted(sources, sp.source[reached]) + 1
    out = refine_contested(graph, node_tree, sp.dist, margin=margin)
    rival_dist, _ = rival_distance(graph, node_tree, sp.dist)
    alone = ~np.isfinite(rival_dist)
    np.testing.assert_array_equal(out[alone], node_tree[alone])
    assert (out[240:] == node_tree[240:]).all()
    assert ((out > 0) == (node_tree > 0)).all()  # nothing gained or lost, only moved
    moved = out != node_tree
    assert not moved[~contested_nodes(node_tree, sp.dist, rival_dist, margin=margin)].any()


def test_a_walk_with_no_seed_in_reach_keeps_the_labels():
    nodes = _line([0, 0, 0], [1, 0, 0])
    graph = build_graph(nodes, radius=0.15)
    tree = np.ones(len(nodes), np.int64)
    np.testing.assert_array_equal(random_walk(graph, tree, np.ones(len(nodes), bool)), tree)


def test_what_is_left_of_a_cut_out_object_does_not_join_a_crown():
    """A vehicle's sides are cut out of the graph; its roof floats above the grass and
    used to join the nearest tree as canopy the graph could not bridge (5 m away at a
    row's end). A floating fragment as far away that touched no cut-out node still joins."""
    trunk = _line([0, 0, 0], [0, 0, 1.5])
    # the crown reaches 1.5 m: both fragments start within twice that (a fragment farther
    # out is the fence wire's case, test_segment), so only the cut-out face tells them apart
    crown = _line([0, 0, 1.6], [1.5, 0, 1.6])
    side = _line([2.0, 0, 0.1], [2.0, 0, 1.4])  # a face, cut out
    roof = _line([2.1, 0, 1.5], [3.0, 0, 1.5])  # touches the face's top node only
    canopy = _line([2.1, 1.0, 1.5], [3.0, 1.0, 1.5])  # floating canopy, no face near
    parts = [trunk, crown, side, roof, canopy]
    nodes = np.vstack(parts)
    part = np.repeat(np.arange(5), [len(p) for p in parts])
    graph = build_graph(nodes, radius=0.15)
    tree = segment_nodes(nodes, graph, source_nodes=np.array([0]), source_trunk=np.array([0]),
                         trunk_xy=np.zeros((1, 2)), node_height=nodes[:, 2], params=SegmentParams(unreached_radius=0.6),
                         exclude=part == 2).node_tree
    assert (tree[part <= 1] == 1).all()
    assert (tree[part == 2] == 0).all() and (tree[part == 3] == 0).all()
    assert (tree[part == 4] == 1).all()


def test_conductance_among_equals_scipys_products_array_for_array():
    """The walk's graph, a block of rows at a time: the very arrays of ``K @ C @ K``
    (rows in order, infinite lengths' zero conductances dropped), canonical input or not."""
    from unittest.mock import patch

    from scipy import sparse

    from pipeline import rowpasses
    from pipeline.graph import MIN_EDGE_WEIGHT, build_graph
    from pipeline.refine import _conductance_among

    rng = np.random.default_rng(2)
    for case in range(40):
        n = int(rng.integers(1, 150))
        g = build_graph(rng.uniform(0, 2, (n, 3)), radius=float(rng.uniform(0.1, 0.6)))
        if case % 5 == 0 and g.nnz:
            g.data[rng.integers(0, g.nnz, 3)] = np.inf
        if case % 4 == 1:  # rows out of order: the products' own path
            g = sparse.csr_matrix((g.data[::-1].copy(), g.indices[::-1].copy(), g.indptr.copy()), shape=g.shape)
        on = rng.random(n) < rng.random()
        c = g.copy()
        c.data = 1.0 / np.maximum(c.data, MIN_EDGE_WEIGHT)
        keep = sparse.diags(on.astype(np.float64))
        want = (keep @ c @ keep).tocsr()
        with patch.object(rowpasses.row_blocks, "__defaults__", (int(rng.integers(1, 40)),)):
            got = _conductance_among(g, on)
        for f in ("indptr", "indices", "data"):
            a, b = getattr(got, f), getattr(want, f)
            assert a.dtype == b.dtype and np.array_equal(a, b), (case, f)
