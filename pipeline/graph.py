"""The voxel graph and the shortest-path operations on it.

Nodes are voxel centroids; edges join nodes closer than a radius, weighted by their
distance (optionally scaled by enrichment features). Shortest paths from many sources
run as one multi-source Dijkstra; path counts are subtree sizes of the shortest-path
forest, computed level by level from the predecessor array.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

INT32_MAX = np.iinfo(np.int32).max


def check_graph_size(n_nodes: int, n_edges: int) -> None:
    """csgraph stores indices as int32: refuse graphs it cannot index."""
    if n_nodes >= INT32_MAX or 2 * n_edges >= INT32_MAX:
        raise ValueError(
            f"graph of {n_nodes} nodes and {n_edges} edges exceeds scipy.sparse.csgraph's int32 "
            "index limit; use smaller tiles"
        )


def node_pairs(nodes: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Every pair of nodes at most ``radius`` [m] apart, and its length.

    Returns
    -------
    pairs : (p, 2) int64, i < j
    length : (p,) float64 [m]
    """
    if nodes.shape[0] == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    pairs = cKDTree(nodes).query_pairs(radius, output_type="ndarray")
    return pairs, pair_lengths(nodes, pairs)


def pair_lengths(points: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(p,) float64 distance [m] between the two points of each pair, (p, 2) int."""
    # one coordinate at a time: gathering whole (p, 3) rows and summing across them is
    # 2-3 times slower on the hundreds of thousands of pairs of a block (same values)
    a, b = pairs[:, 0], pairs[:, 1]
    total = np.zeros(pairs.shape[0])
    for d in range(points.shape[1]):
        col = points[:, d]
        step = col[a] - col[b]
        step *= step
        total += step
    return np.sqrt(total, out=total)


def pairs_within(candidates: tuple[np.ndarray, np.ndarray], radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of a :func:`node_pairs` result at most ``radius`` [m] long, and their lengths."""
    pairs, length = candidates
    near = length <= radius
    return pairs[near], length[near]


def build_graph(
    nodes: np.ndarray,
    *,
    radius: float,
    edge_scale: np.ndarray | None = None,
    candidates: tuple[np.ndarray, np.ndarray] | None = None,
) -> sparse.csr_matrix:
    """Undirected graph joining nodes closer than ``radius``.

    Parameters
    ----------
    nodes : (m, 3) float64 [m]
    radius : float [m]
    edge_scale : (m, f) float64, optional
        Per-node feature vectors; when given, each edge's length is multiplied by
        ``1 + (1 - cos_sim(f_a, f_b))`` (the paper's cosine-similarity enrichment).
    candidates : optional ``node_pairs(nodes, r)`` with ``r >= radius``, to reuse one
        neighbour search for several radii

    Returns
    -------
    (m, m) csr_matrix, symmetric, float64 weights [m] (> 0).
    """
    m = nodes.shape[0]
    if m == 0:
        return sparse.csr_matrix((0, 0))
    pairs, w = node_pairs(nodes, radius) if candidates is None else pairs_within(candidates, radius)
    check_graph_size(m, pairs.shape[0])
    a, b = pairs[:, 0], pairs[:, 1]
    if edge_scale is not None:
        f = edge_scale / (np.linalg.norm(edge_scale, axis=1, keepdims=True) + 1e-12)
        cos = (f[a] * f[b]).sum(1)
        w = w * (1.0 + (1.0 - np.clip(cos, -1.0, 1.0)))
    w = np.maximum(w, 1e-6)  # csgraph treats explicit zeros as missing edges
    return symmetric_csr(pairs, w, m)


def symmetric_csr(pairs: np.ndarray, weight: np.ndarray, m: int, *, diagonal: np.ndarray | None = None) -> sparse.csr_matrix:
    """(m, m) symmetric csr_matrix with ``weight`` at (i, j) and (j, i) of each pair, sorted
    indices (canonical), and ``diagonal`` (m,) on the diagonal when given.

    ``pairs`` (p, 2) int must hold each unordered pair once and no (i, i).
    """
    # Strategy: without duplicates nothing needs summing, so skip scipy's sort of every
    # row: building the transpose row by row (a counting pass) leaves each row sorted.
    a, b = pairs[:, 0], pairs[:, 1]
    rows, cols, data = [a, b], [b, a], [weight, weight]
    if diagonal is not None:
        rows.append(np.arange(m))
        cols.append(np.arange(m))
        data.append(diagonal)
    g = sparse.coo_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(m, m))
    g.has_canonical_format = True  # no duplicates: tocsr need not sum (and sort) them
    return g.tocsr().T.tocsr()


def reweight(graph: sparse.csr_matrix, node_cost: np.ndarray) -> sparse.csr_matrix:
    """The same edges with each length multiplied by the mean cost factor of its two nodes.

    Parameters
    ----------
    graph : (m, m) csr_matrix
    node_cost : (m,) float64, >= 1

    Returns
    -------
    (m, m) csr_matrix with the same sparsity structure.
    """
    if not graph.has_canonical_format:
        graph = graph.copy()
        graph.sum_duplicates()
    row = np.repeat(np.arange(graph.shape[0]), np.diff(graph.indptr))
    w = graph.data * 0.5 * (node_cost[row] + node_cost[graph.indices])
    return sparse.csr_matrix((w, graph.indices.copy(), graph.indptr.copy()), shape=graph.shape)


def bridge_floating(
    graph: sparse.csr_matrix,
    nodes: np.ndarray,
    node_height: np.ndarray,
    *,
    floating_height: float,
    max_gap: float,
    min_nodes: int = 1,
) -> sparse.csr_matrix:
    """Hang every floating component from something below it, by one edge.

    Sparse scans break a crown off its trunk: with edges of 0.15 m a gap of a few
    decimetres leaves the crown as a component that never touches the ground. Each
    component whose lowest node is above ``floating_height`` [m] gets one edge, of its
    length, to the nearest node within ``max_gap`` [m] of a component standing on the
    ground; failing that, to the nearest node of a floating component whose lowest node
    is lower than its own. Every edge leads down, so chains of fragments end on the
    ground or stop, and never pair two fragments into a floating island. Components
    standing on the ground (posts, vehicles) are never bridged. One round only (with
    the earlier nearest-component rule, repeated rounds chained fragments of
    neighbouring crowns together on the AdTree row; not measured with this rule).

    Parameters
    ----------
    graph : (m, m) csr_matrix
    nodes : (m, 3) float64 [m]
    node_height : (m,) float64 — height above ground [m]
    floating_height, max_gap : float [m]
    min_nodes : int — smaller floating components are noise (outliers) and stay apart

    Returns
    -------
    (m, m) csr_matrix with the bridging edges added (symmetric).
    """
    m = graph.shape[0]
    if m == 0:
        return graph
    n_comp, comp = csgraph.connected_components(graph, directed=False)
    if n_comp < 2:
        return graph
    low = np.full(n_comp, np.inf)
    np.minimum.at(low, comp, node_height)
    grounded = low <= floating_height
    floating = ~grounded & (np.bincount(comp, minlength=n_comp) >= min_nodes)
    cand = np.flatnonzero(floating[comp])
    if cand.size == 0:
        return graph
    best_d = np.full(cand.size, np.inf)
    best_j = np.zeros(cand.size, np.int64)
    on_ground = np.flatnonzero(grounded[comp])
    if on_ground.size:
        d, j = cKDTree(nodes[on_ground]).query(nodes[cand], distance_upper_bound=max_gap)
        hit = np.isfinite(d)
        best_d[hit], best_j[hit] = d[hit], on_ground[j[hit]]
    # no ground component within reach: the nearest lower fragment among the 16 nearest
    rest = np.flatnonzero(~np.isfinite(best_d))
    aloft = np.flatnonzero(~grounded[comp])
    if rest.size and aloft.size > 1:
        k = min(16, aloft.size)
        d, j = cKDTree(nodes[aloft]).query(nodes[cand[rest]], k=k, distance_upper_bound=max_gap)
        d, j = np.atleast_2d(d), np.atleast_2d(j)
        valid = np.isfinite(d)
        jj = aloft[np.where(valid, j, 0)]
        d = np.where(valid & (low[comp[jj]] < low[comp[cand[rest]]][:, None]), d, np.inf)
        bk = np.argmin(d, axis=1)
        r = np.arange(rest.size)
        best_d[rest], best_j[rest] = d[r, bk], jj[r, bk]
    ok = np.isfinite(best_d)
    if not ok.any():
        return graph
    # one edge per floating component: its shortest link
    src, dst, w, c = cand[ok], best_j[ok], best_d[ok], comp[cand[ok]]
    order = np.lexsort((w, c))
    first = order[np.r_[True, c[order][1:] != c[order][:-1]]]
    src, dst, w = src[first], dst[first], np.maximum(w[first], 1e-6)
    extra = sparse.coo_matrix((np.r_[w, w], (np.r_[src, dst], np.r_[dst, src])), shape=(m, m)).tocsr()
    return (graph + extra).tocsr()


@dataclass(frozen=True)
class ShortestPaths:
    """Result of a multi-source Dijkstra.

    Attributes
    ----------
    dist : (m,) float64 — path length to the nearest source [m]; inf if unreached.
    pred : (m,) int64 — predecessor on that path; -1 for sources and unreached nodes.
    source : (m,) int64 — the nearest source node; -1 if unreached.
    """

    dist: np.ndarray
    pred: np.ndarray
    source: np.ndarray


def shortest_paths(graph: sparse.csr_matrix, sources: np.ndarray) -> ShortestPaths:
    """Shortest paths from all ``sources`` at once (one multi-source Dijkstra).

    Parameters
    ----------
    graph : (m, m) csr_matrix
    sources : (s,) int64 node indices

    Returns
    -------
    ShortestPaths
    """
    m = graph.shape[0]
    sources = np.unique(np.asarray(sources, dtype=np.int64))
    if m == 0 or sources.size == 0:
        return ShortestPaths(np.full(m, np.inf), np.full(m, -1, np.int64), np.full(m, -1, np.int64))
    dist, pred, src = csgraph.dijkstra(
        graph, directed=False, indices=sources, min_only=True, return_predecessors=True
    )
    pred = pred.astype(np.int64)
    pred[pred < 0] = -1
    src = src.astype(np.int64)
    src[src < 0] = -1
    return ShortestPaths(dist, pred, src)


def depths(pred: np.ndarray) -> np.ndarray:
    """Number of edges from each node up to its root in a forest given by ``pred``.

    Pointer jumping: O(m log d) work in whole-array steps, d the deepest path.

    Parameters
    ----------
    pred : (m,) int64, -1 at roots (and unreached nodes)

    Returns
    -------
    (m,) int64
    """
    depth = (pred >= 0).astype(np.int64)
    anc = pred.copy()
    while True:
        live = anc >= 0
        if not live.any():
            return depth
        a = anc[live]
        new_depth = depth.copy()
        new_depth[live] = depth[live] + depth[a]
        new_anc = anc.copy()
        new_anc[live] = anc[a]
        depth, anc = new_depth, new_anc


def subtree_sizes(pred: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Path counts: how many shortest paths pass through each node.

    In a shortest-path forest every node's path to its root passes through all its
    ancestors, so the number of paths through a node is the size of its subtree
    (the node itself included). Accumulated deepest level first: each level is one
    ``np.bincount``; total work linear in the number of nodes per level sweep.

    Parameters
    ----------
    pred : (m,) int64, -1 at roots
    weights : (m,) float64, optional — count each node with this weight (default 1)

    Returns
    -------
    (m,) float64
    """
    m = pred.shape[0]
    size = np.ones(m) if weights is None else np.asarray(weights, dtype=np.float64).copy()
    if m == 0:
        return size
    depth = depths(pred)
    order = np.argsort(depth, kind="stable")
    bounds = np.searchsorted(depth[order], np.arange(depth.max() + 2))
    for d in range(int(depth.max()), 0, -1):
        nodes = order[bounds[d] : bounds[d + 1]]
        size += np.bincount(pred[nodes], weights=size[nodes], minlength=m)
    return size


def without_nodes(graph: sparse.csr_matrix, cut: np.ndarray) -> sparse.csr_matrix:
    """``graph`` (m, m) without the edges of the nodes in ``cut`` (m,) bool (no path passes them)."""
    keep = sparse.diags((~cut).astype(np.float64))
    out = (keep @ graph @ keep).tocsr()
    out.eliminate_zeros()
    return out
