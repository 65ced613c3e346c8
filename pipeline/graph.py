"""The voxel graph and the shortest-path operations on it.

Nodes are voxel centroids; edges join nodes closer than a radius, weighted by their
distance (optionally scaled by enrichment features). Shortest paths from many sources
run as one multi-source Dijkstra; path counts are subtree sizes of the shortest-path
forest, computed level by level from the predecessor array.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from pipeline.passes import CACHE_POINTS
from pipeline.rowpasses import block_rows, row_blocks

INT32_MAX = np.iinfo(np.int32).max
#: shortest edge weight [m]: csgraph treats explicit zeros as missing edges
MIN_EDGE_WEIGHT = 1e-6
#: a floating component with no ground in reach looks for a lower fragment among this
#: many nearest floating nodes
BRIDGE_CANDIDATES = 16


def check_graph_size(n_nodes: int, n_edges: int) -> None:
    """csgraph stores indices as int32: refuse graphs it cannot index."""
    if n_nodes >= INT32_MAX or 2 * n_edges >= INT32_MAX:
        raise ValueError(
            f"graph of {n_nodes} nodes and {n_edges} edges exceeds scipy.sparse.csgraph's int32 "
            "index limit; use smaller tiles"
        )


@dataclass(frozen=True)
class NodePairs:
    """Node pairs within a radius, in the order that lets a symmetric matrix be built
    with one stable counting pass.

    Attributes
    ----------
    pairs : (p, 2) int32 (int64 from :func:`voxel_pairs`, or for 2**31 nodes or more),
        ``pairs[:, 0] < pairs[:, 1]``
    length : (p,) float64 — distance between the two nodes [m]
    groups : (g + 1,) int64 or None
        ``pairs[groups[k]:groups[k + 1]]`` is group k, sorted by (first, second). A
        node's partners of larger index ascend with the group, those of smaller index
        descend (the voxel column offsets of :func:`voxel_pairs`, in ascending key
        order). None: no order (any pairs, as a k-d tree gives them).
    """

    pairs: np.ndarray
    length: np.ndarray
    groups: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.pairs.shape[0])

    def within(self, radius: float) -> "NodePairs":
        """The pairs at most ``radius`` [m] long, in the same order and groups."""
        near = self.length <= radius
        if near.all():  # the same pairs: no copy
            return self
        groups = None
        if self.groups is not None:
            groups = np.r_[0, np.cumsum(near)][self.groups]
        return NodePairs(self.pairs[near], self.length[near], groups)


def node_pairs(
    nodes: np.ndarray,
    radius: float,
    *,
    keys: np.ndarray | None = None,
    voxel_size: float | None = None,
) -> NodePairs:
    """Every pair of nodes at most ``radius`` [m] apart, and its length.

    Parameters
    ----------
    nodes : (m, 3) float64 [m]
    radius : float [m]
    keys : (m, 3) int64, optional
        Voxel keys of the nodes when they are voxel centroids (:class:`pipeline.voxels.Voxels`,
        one node per voxel, ordered by key); with ``voxel_size`` [m] the pairs are found
        from the voxel grid's integer offsets (:func:`voxel_pairs`), else by a k-d tree.

    Returns
    -------
    NodePairs
    """
    if keys is not None and voxel_size is not None:
        return voxel_pairs(keys, nodes, radius=radius, voxel_size=voxel_size)
    if nodes.shape[0] == 0:
        return NodePairs(np.zeros((0, 2), np.int64), np.zeros(0))
    # any tree finds the same pairs (only their order differs, and symmetric_csr sorts
    # it away): the unbalanced, uncompacted one builds in half the time, queries as fast
    tree = cKDTree(nodes, balanced_tree=False, compact_nodes=False)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    if nodes.shape[0] < INT32_MAX:  # half the bytes: the pairs are held while the graphs are built
        pairs = pairs.astype(np.int32)
    return NodePairs(pairs, pair_lengths(nodes, pairs))


def pair_lengths(points: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(p,) float64 distance [m] between the two points of each pair, (p, 2) int."""
    # one coordinate at a time: gathering whole (p, 3) rows and summing across them is
    # 2-3 times slower on the hundreds of thousands of pairs of a block (same values);
    # a cache-sized pass of pairs at a time in two reused buffers: whole-array
    # temporaries of millions of pairs each cost fresh pages the kernel must zero
    n = pairs.shape[0]
    total = np.empty(n)
    cols = [np.ascontiguousarray(points[:, d]) for d in range(points.shape[1])]
    step, other = np.empty(min(n, CACHE_POINTS)), np.empty(min(n, CACHE_POINTS))
    for s in range(0, n, CACHE_POINTS):
        e = min(n, s + CACHE_POINTS)
        a, b, t = pairs[s:e, 0], pairs[s:e, 1], total[s:e]
        one, two = step[: e - s], other[: e - s]
        t[:] = 0.0
        for col in cols:
            np.take(col, a, out=one)
            np.take(col, b, out=two)
            one -= two
            one *= one
            t += one
    return np.sqrt(total, out=total)


def stencil(radius: float, voxel_size: float) -> np.ndarray:
    """(s, 3) int64 voxel offsets whose voxels can hold a node within ``radius`` [m] of
    a node in voxel (0, 0, 0): the lexicographically positive half, in ascending order."""
    # two voxels d apart along an axis hold points at least (|d| - 1) voxel sizes apart
    # there; the margin keeps borderline offsets for the exact distance test (a
    # centroid may lie an ulp outside its voxel)
    reach = int(math.floor(radius / voxel_size * (1 + 1e-9))) + 1
    g = np.arange(-reach, reach + 1)
    off = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    gap = np.maximum(np.abs(off) - 1, 0).astype(np.float64) * voxel_size
    near = (gap * gap).sum(1) <= (radius * (1 + 1e-9)) ** 2
    x, y, z = off[:, 0], off[:, 1], off[:, 2]
    positive = (x > 0) | ((x == 0) & ((y > 0) | ((y == 0) & (z > 0))))
    return off[near & positive]


def voxel_pairs(keys: np.ndarray, nodes: np.ndarray, *, radius: float, voxel_size: float) -> NodePairs:
    """:func:`node_pairs` of voxel centroids, from the voxel grid's integer offsets.

    Parameters
    ----------
    keys : (m, 3) int64 — voxel keys, unique, sorted by (x, y, z) (as :func:`pipeline.voxels.voxelize` gives them)
    nodes : (m, 3) float64 — centroids, each inside its voxel [m]
    radius, voxel_size : float [m]

    Returns
    -------
    NodePairs, one group per (dx, dy) of :func:`stencil`, each sorted by node, then partner.
    """
    # Strategy: a node per voxel, and nodes sorted by key form (x, y) columns of
    # ascending z. For each (dx, dy) of the half stencil, one np.searchsorted on the
    # column keys finds every column's neighbour column; the partners of a node there
    # are the run of that column's nodes within the stencil's dz range, read from a
    # table counting each column's nodes below every z (padded, so no lookup leaves
    # its column). The exact distance test ends it.
    m = keys.shape[0]
    off = stencil(radius, voxel_size)
    columns, inverse = np.unique(off[:, :2], axis=0, return_inverse=True)
    if m < 2 or off.shape[0] == 0:
        return NodePairs(np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(columns.shape[0] + 1, np.int64))
    check_graph_size(m, 0)  # the search counts in int32
    table = _ColumnTable.build(keys, int(np.abs(off).max()))
    x, y, z = (np.ascontiguousarray(nodes[:, d]) for d in range(3))
    r2 = radius * radius
    firsts, seconds, lengths = [], [], []
    for c, (dx, dy) in enumerate(columns):
        dz = off[inverse.reshape(-1) == c, 2]  # one run of dz, ascending
        a, b = table.candidates(dx, dy, dz)
        # the distance as pair_lengths computes it, so lengths equal the k-d tree path's
        d2 = x[a] - x[b]
        d2 *= d2
        step = y[a] - y[b]
        step *= step
        d2 += step
        step = z[a] - z[b]
        step *= step
        d2 += step
        near = d2 <= r2
        firsts.append(a[near])
        seconds.append(b[near])
        lengths.append(np.sqrt(d2[near]))
    pairs = np.empty((sum(f.shape[0] for f in firsts), 2), np.int64)
    pairs[:, 0] = np.concatenate(firsts)
    pairs[:, 1] = np.concatenate(seconds)
    return NodePairs(pairs, np.concatenate(lengths), np.r_[0, np.cumsum([f.shape[0] for f in firsts])])


@dataclass(frozen=True)
class _ColumnTable:
    """:func:`voxel_pairs`' voxels as (x, y) columns of ascending z, and a table of slots
    (each column's z range padded by ``2 * reach + 1`` on both sides, so that no lookup
    leaves its column) counting the nodes below each slot.

    Attributes
    ----------
    ucol : (c,) int64 — each column's key ``x * ny + y``, ascending
    col : (m,) int64 — each node's column
    kz : (m,) int64 — each node's z key
    zlo, zspan : (c,) int64 — each column's lowest z key, and the z keys it spans
    tstart : (c,) int64 — the slot of each column's lowest voxel
    below : (t + 1,) int64 — the nodes in the slots before each slot
    ny : int — the stride of x in a column key
    reach : int — the stencil's largest offset [voxels]
    """

    ucol: np.ndarray
    col: np.ndarray
    kz: np.ndarray
    zlo: np.ndarray
    zspan: np.ndarray
    tstart: np.ndarray
    below: np.ndarray
    ny: int
    reach: int

    @classmethod
    def build(cls, keys: np.ndarray, reach: int) -> _ColumnTable:
        """The table of voxel ``keys`` (unique, sorted by (x, y, z)) for a stencil of ``reach``."""
        m = keys.shape[0]
        pad = 2 * reach + 1
        kx = keys[:, 0] - keys[:, 0].min()
        ky = keys[:, 1] - keys[:, 1].min() + reach
        kz = keys[:, 2]
        ny = int(ky.max()) + reach + 1
        colkey = kx * ny + ky  # (x, y) of a column and its neighbours, without wrapping
        start = np.flatnonzero(np.r_[True, colkey[1:] != colkey[:-1]])
        size = np.diff(np.r_[start, m])
        ucol, ncol = colkey[start], start.shape[0]
        col = np.repeat(np.arange(ncol), size)
        zlo = kz[start]
        zspan = kz[start + size - 1] - zlo + 1
        width = zspan + 2 * pad
        tstart = np.cumsum(width) - width + pad  # slot of each column's lowest voxel
        occupied = np.zeros(int(width.sum()), np.int64)
        occupied[tstart[col] + (kz - zlo[col])] = 1
        below = np.zeros(occupied.shape[0] + 1, np.int64)  # nodes in the slots before each slot
        np.cumsum(occupied, out=below[1:])
        return cls(ucol, col, kz, zlo, zspan, tstart, below, ny, reach)

    def candidates(self, dx, dy, dz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q,) int32 first and second nodes of the candidate pairs at column offset
        (``dx``, ``dy``): each node and the nodes of that neighbour column within the run
        ``dz`` (ascending) of z offsets, by node, then partner."""
        ucol, col = self.ucol, self.col
        if dx == 0 and dy == 0:
            sel, other = np.arange(col.shape[0]), col
        else:
            target = ucol + dx * self.ny + dy
            pos = np.minimum(np.searchsorted(ucol, target), ucol.shape[0] - 1)
            nb = np.where(ucol[pos] == target, pos, -1)[col]
            sel = np.flatnonzero(nb >= 0)
            other = nb[sel]
        # z of each node in the other column's frame, clamped where no dz can reach
        base = self.tstart[other] + np.clip(self.kz[sel] - self.zlo[other], -self.reach - 1, self.zspan[other] + self.reach)
        lo = self.below[base + dz[0]]
        count = self.below[base + dz[-1] + 1] - lo
        ends = np.cumsum(count)
        # int32 while candidates are many (csgraph indexes nodes with int32 anyway)
        a = np.repeat(sel.astype(np.int32), count)
        b = np.arange(int(ends[-1]) if ends.size else 0, dtype=np.int32) + np.repeat((lo - (ends - count)).astype(np.int32), count)
        return a, b


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
    candidates : NodePairs, optional
        ``node_pairs(nodes, r)`` with ``r >= radius``, to reuse one neighbour search
        for several radii (and to search voxel centroids by their keys)

    Returns
    -------
    (m, m) csr_matrix, symmetric, float64 weights [m] (> 0).
    """
    m = nodes.shape[0]
    if m == 0:
        return sparse.csr_matrix((0, 0))
    found = node_pairs(nodes, radius) if candidates is None else candidates.within(radius)
    check_graph_size(m, len(found))
    a, b, w = found.pairs[:, 0], found.pairs[:, 1], found.length
    if edge_scale is not None:
        f = edge_scale / (np.linalg.norm(edge_scale, axis=1, keepdims=True) + 1e-12)
        cos = (f[a] * f[b]).sum(1)
        w = w * (1.0 + (1.0 - np.clip(cos, -1.0, 1.0)))
    w = np.maximum(w, MIN_EDGE_WEIGHT)
    return symmetric_csr(found, w, m)


def symmetric_csr(
    pairs: "NodePairs | np.ndarray", weight: np.ndarray, m: int, *, diagonal: np.ndarray | None = None
) -> sparse.csr_matrix:
    """(m, m) symmetric csr_matrix with ``weight`` at (i, j) and (j, i) of each pair, sorted
    indices (canonical), and ``diagonal`` (m,) on the diagonal when given.

    ``pairs``: :class:`NodePairs`, or (p, 2) int in any order; each unordered pair once
    and no (i, i).
    """
    # Strategy: without duplicates nothing needs summing, and scipy's COO -> CSR is a
    # stable counting pass by row. Grouped pairs are laid out so that it leaves every
    # row sorted (partners below the node by group from last to first, the diagonal,
    # partners above it by group); pairs in no order take a second pass (the transpose,
    # built row by row).
    groups = pairs.groups if isinstance(pairs, NodePairs) else None
    p = pairs.pairs if isinstance(pairs, NodePairs) else pairs
    # scipy would copy int64 indices into its int32 index type; hand it int32 at once
    # (columns of int32 pairs as they are: the concatenations below copy them anyway)
    index = np.int32 if m < INT32_MAX else np.int64
    a, b = p[:, 0].astype(index, copy=False), p[:, 1].astype(index, copy=False)
    if groups is None:
        rows, cols, data = [a, b], [b, a], [weight, weight]
    else:
        def backwards(v: np.ndarray) -> np.ndarray:
            return np.concatenate([v[groups[k] : groups[k + 1]] for k in range(len(groups) - 2, -1, -1)] + [v[:0]])

        rows, cols, data = [backwards(b), a], [backwards(a), b], [backwards(weight), weight]
    if diagonal is not None:
        rows.insert(1, np.arange(m, dtype=index))
        cols.insert(1, np.arange(m, dtype=index))
        data.insert(1, diagonal)
    g = sparse.coo_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(m, m))
    del a, b, rows, cols, data  # each conversion below allocates a matrix's worth: free what is done with
    g.has_canonical_format = True  # no duplicates: tocsr need not sum (and sort) them
    out = g.tocsr()
    del g
    if groups is None:
        return out.T.tocsr()
    out.has_sorted_indices = True
    return out


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
    # a block of rows at a time: every edge's row, costs and sum would be fresh temporaries
    indptr, indices = graph.indptr, graph.indices
    w = np.empty(graph.data.shape[0])
    for start, stop in row_blocks(indptr):
        lo, hi = indptr[start], indptr[stop]
        row = block_rows(indptr, start, stop)
        t = w[lo:hi]
        np.multiply(graph.data[lo:hi], 0.5, out=t)
        t *= node_cost[row] + node_cost[indices[lo:hi]]
    return sparse.csr_matrix((w, indices.copy(), indptr.copy()), shape=graph.shape)


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
    standing on the ground (posts, vehicles) are never bridged. One round only:
    repeated rounds can chain fragments of neighbouring crowns together.

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
    # no ground component within reach: the nearest lower fragment among the nearest nodes
    rest = np.flatnonzero(~np.isfinite(best_d))
    aloft = np.flatnonzero(~grounded[comp])
    if rest.size and aloft.size > 1:
        k = min(BRIDGE_CANDIDATES, aloft.size)
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
    src, dst, w = src[first], dst[first], np.maximum(w[first], MIN_EDGE_WEIGHT)
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
