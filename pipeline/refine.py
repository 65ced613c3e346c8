"""Refinement of contested nodes: a random walk seeded by the trees' settled nodes.

Shortest paths from the trunks give a node to the trunk whose path is shortest. Where
crowns interlock, two trunks' paths to a twig differ by a few centimetres and the
shorter one often runs through a single contact between twigs of two trees. A random
walk from the node (Grady's random walker: the probability that a walk started at the
node reaches a tree's settled nodes first) weighs every route at once, so a twig that
hangs on its own branch by many edges and touches the neighbour's by a few stays with
its own branch.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.sparse.linalg import splu

from pipeline.graph import MIN_EDGE_WEIGHT
from pipeline.rowpasses import kept_entries

#: at most this many trees' probabilities are solved for at once (columns of one dense
#: right-hand side; memory is contested nodes × this × 8 bytes)
SOLVE_COLUMNS = 64


def rival_distance(graph: sparse.csr_matrix, node_tree: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shortest path length from any *other* tree's trunk to each node, and that tree.

    A path from another trunk to a node of tree t last enters t's territory over an edge
    (a, b), a outside, b inside, after ``dist[a]``; so one search inside the territories,
    started at every such b with the offset ``dist[a] + w(a, b)``, gives every node the
    shortest path from a rival trunk (exact when ``dist`` are the shortest-path lengths
    that gave ``node_tree``).

    Parameters
    ----------
    graph : (m, m) csr_matrix — the graph the paths ran on
    node_tree : (m,) int64 — 0 = no tree
    dist : (m,) float64 — path length from the node's own trunk [m]

    Returns
    -------
    rival_dist : (m,) float64 [m] — inf where no other tree's path reaches the node
    rival : (m,) int64 — that tree (1-based), 0 where none
    """
    m = node_tree.shape[0]
    g = graph.tocoo()
    a, b, w = g.row, g.col, g.data
    ta, tb = node_tree[a], node_tree[b]  # each edge's trees, gathered once
    labelled = (ta > 0) & (tb > 0) & np.isfinite(dist[a])
    same = ta == tb
    cross = labelled & ~same
    inside = labelled & same
    del labelled, same, tb  # every edge's arrays go as soon as they are done with
    rival_dist = np.full(m, np.inf)
    rival = np.zeros(m, np.int64)
    if not cross.any():
        return rival_dist, rival
    # the best entry of each entered node
    off = dist[a[cross]] + w[cross]
    order = np.lexsort((off, b[cross]))
    ent, first = np.unique(b[cross][order], return_index=True)
    ent_off, ent_tree = off[order][first], ta[cross][order][first]
    del ta, cross, off, order
    # one virtual source per entered node, joined to it by its offset; indices in the
    # type scipy would convert them to (int32 below 2**31 nodes), not int64 first
    e = ent.size
    index = np.int32 if m + e < np.iinfo(np.int32).max else np.int64
    rows = np.r_[a[inside].astype(index, copy=False), np.arange(m, m + e, dtype=index)]
    cols = np.r_[b[inside].astype(index, copy=False), ent.astype(index, copy=False)]
    data = np.r_[w[inside], np.maximum(ent_off, MIN_EDGE_WEIGHT)]
    del g, a, b, w, inside
    aug = sparse.csr_matrix((data, (rows, cols)), shape=(m + e, m + e))
    del rows, cols, data
    d, _, src = csgraph.dijkstra(aug, directed=True, indices=m + np.arange(e), min_only=True, return_predecessors=True)
    d = d[:m]
    src = src[:m]
    hit = np.isfinite(d) & (src >= m)
    rival_dist[hit] = d[hit]
    rival[hit] = ent_tree[src[hit] - m]
    return rival_dist, rival


def contested_nodes(node_tree: np.ndarray, dist: np.ndarray, rival_dist: np.ndarray, *, margin: float) -> np.ndarray:
    """Nodes whose rival tree's path is at most ``margin`` [m] longer than their own, (m,) bool.

    A node no other tree's path reaches is never contested.
    """
    out = (node_tree > 0) & np.isfinite(rival_dist) & np.isfinite(dist)
    out[out] = rival_dist[out] - dist[out] <= margin
    return out


def random_walk(graph: sparse.csr_matrix, node_tree: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Relabel the ``free`` nodes by a random walk seeded by every other labelled node.

    Each free node takes the tree whose seeds a walk from it reaches first with the
    highest probability (edge conductance 1 / length). Free nodes in a part of the graph
    with no seed keep their label.

    Parameters
    ----------
    graph : (m, m) csr_matrix — edge lengths [m]
    node_tree : (m,) int64 — 0 = no tree (not a seed, not walked through)
    free : (m,) bool — nodes to relabel (labelled ones only)

    Returns
    -------
    (m,) int64 — ``node_tree`` with the free nodes relabelled
    """
    out = node_tree.copy()
    free = free & (node_tree > 0)
    u = np.flatnonzero(free)
    if u.size == 0:
        return out
    # the walk runs over tree nodes only: the rest is neither seed nor path
    tree = node_tree > 0
    g = _conductance_among(graph.tocsr(), tree)
    g = g.maximum(g.T)
    seeds = np.flatnonzero(tree & ~free)
    w_uu = g[u][:, u]
    w_us = g[u][:, seeds]
    deg = np.asarray(g[u].sum(axis=1)).ravel()
    # nodes cut off from every seed are left alone (their system would be singular)
    _, comp = csgraph.connected_components(w_uu, directed=False)
    touch = np.zeros(comp.max() + 1, bool)
    touch[comp[np.asarray(w_us.sum(axis=1)).ravel() > 0]] = True
    ok = touch[comp]
    if not ok.any():
        return out
    u, w_uu, w_us, deg = u[ok], w_uu[ok][:, ok], w_us[ok], deg[ok]
    lap = (sparse.diags(deg) - w_uu).tocsc()
    lu = splu(lap)
    labels = np.unique(node_tree[seeds])
    best_p = np.full(u.size, -1.0)
    best_t = node_tree[u].copy()
    seed_tree = node_tree[seeds]
    for i in range(0, labels.size, SOLVE_COLUMNS):
        chunk = labels[i : i + SOLVE_COLUMNS]
        col = np.searchsorted(chunk, seed_tree)
        inside = (col < chunk.size) & (chunk[np.minimum(col, chunk.size - 1)] == seed_tree)
        onehot = sparse.csr_matrix((np.ones(inside.sum()), (np.flatnonzero(inside), col[inside])),
                                   shape=(seeds.size, chunk.size))
        rhs = (w_us @ onehot).toarray()
        used = np.flatnonzero(rhs.any(axis=0))
        if used.size == 0:
            continue
        p = lu.solve(rhs[:, used])
        j = p.argmax(axis=1)
        pj = p[np.arange(u.size), j]
        better = pj > best_p
        best_p[better] = pj[better]
        best_t[better] = chunk[used][j[better]]
    out[u] = best_t
    return out


def _conductance_among(graph: sparse.csr_matrix, on: np.ndarray) -> sparse.csr_matrix:
    """``K @ C @ K`` for the conductances ``C`` (1 / length) of ``graph`` and ``K`` the
    diagonal of ``on`` (m,) bool: the edges between two ``on`` nodes, (m, m).

    On a canonical matrix (rows sorted, no duplicates) the edges are taken a block of rows
    at a time, in their order: the very arrays scipy's two products give (they keep each
    row's order, and drop the zero conductances of infinite lengths), without a copy of
    the graph and of its product with ``K`` first.
    """
    if not graph.has_canonical_format:  # the products sum duplicates and reorder rows
        g = graph.copy()
        g.data = 1.0 / np.maximum(g.data, MIN_EDGE_WEIGHT)
        keep = sparse.diags(on.astype(np.float64))
        return (keep @ g @ keep).tocsr()
    indices, length = graph.indices, graph.data
    return kept_entries(graph, lambda rows, lo, hi: on[rows] & on[indices[lo:hi]] & (length[lo:hi] != np.inf),
                        data=lambda keep: 1.0 / np.maximum(length[keep], MIN_EDGE_WEIGHT))


def refine_contested(graph: sparse.csr_matrix, node_tree: np.ndarray, dist: np.ndarray, *, margin: float) -> np.ndarray:
    """``node_tree`` with its contested nodes relabelled by :func:`random_walk`.

    Parameters
    ----------
    graph : (m, m) csr_matrix — the graph the shortest paths ran on (edge lengths [m])
    node_tree : (m,) int64 — tree of each node by shortest path, 0 = none
    dist : (m,) float64 — each node's shortest path length from its trunk [m]
    margin : float — contested: a rival trunk's path at most this much longer [m]

    Returns
    -------
    (m,) int64
    """
    rival_dist, _ = rival_distance(graph, node_tree, dist)
    return random_walk(graph, node_tree, contested_nodes(node_tree, dist, rival_dist, margin=margin))
