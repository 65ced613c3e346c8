"""Trees linked along their rows: local row directions, sections, chains of trees.

The first steps of :func:`pipeline.rows.find_rows`: each tree's local row direction
from its nearest trees, the block's sections (trees whose directions agree), and each
section's trees linked one after another along the row into chains.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

#: first-pass links reach this many slots (one empty slot between two trees)
SHORT_LINK_SLOTS = 2.5


def _doubled(vec: np.ndarray) -> np.ndarray:
    """Unit vectors of twice each vector's angle: a direction and its opposite agree."""
    ang = 2.0 * np.arctan2(vec[:, 1], vec[:, 0])
    return np.c_[np.cos(ang), np.sin(ang)]


def local_directions(xy: np.ndarray, near: np.ndarray) -> np.ndarray:
    """(k, 2) unit row direction at each tree: its nearest-neighbour direction,
    averaged (as doubled angles) over its nearest trees, so that in a grid whose rows are
    only a little wider than the in-row spacing the majority decides. ``near`` (k, m)
    are each tree's nearest trees, itself first."""
    d2 = _doubled(xy[near[:, 1]] - xy)
    mean = d2[near].mean(axis=1)
    ang = 0.5 * np.arctan2(mean[:, 1], mean[:, 0])
    return np.c_[np.cos(ang), np.sin(ang)]


def row_sections(xy: np.ndarray, direction: np.ndarray, max_angle: float) -> np.ndarray:
    """(k,) section label of each tree: trees joined through neighbours (Delaunay edges)
    whose row directions agree within ``max_angle`` degrees."""
    k = len(xy)
    if k < 4:
        return np.zeros(k, dtype=np.int64)
    from scipy.spatial import Delaunay, QhullError

    try:
        simplices = Delaunay(xy).simplices
    except (QhullError, ValueError):  # all trees on one line: one section
        return np.zeros(k, dtype=np.int64)
    e = np.r_[simplices[:, [0, 1]], simplices[:, [1, 2]], simplices[:, [2, 0]]]
    cos = np.abs(np.einsum("ij,ij->i", direction[e[:, 0]], direction[e[:, 1]]))
    keep = cos >= np.cos(np.radians(max_angle))
    e = e[keep]
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(k, k))
    _, labels = connected_components(graph, directed=False)
    # small sections (a stray tree, a headland corner) join their nearest large one
    sizes = np.bincount(labels)
    big = sizes[labels] >= 3
    if big.any() and not big.all():
        tree = cKDTree(xy[big])
        _, j = tree.query(xy[~big])
        labels[~big] = labels[big][j]
    return np.unique(labels, return_inverse=True)[1]


def _oriented(u: np.ndarray) -> np.ndarray:
    """The row direction pointed the way positions increase: north for rows closer to
    north–south, east for rows closer to east–west."""
    u = u / np.hypot(*u)
    if abs(u[1]) > abs(u[0]):
        return u if u[1] > 0 else -u
    return u if u[0] > 0 else -u


def section_direction(direction: np.ndarray) -> np.ndarray:
    mean = _doubled(direction).mean(axis=0)
    ang = 0.5 * np.arctan2(mean[1], mean[0])
    return _oriented(np.array([np.cos(ang), np.sin(ang)]))


def link_trees(xy, direction, u, members, spacing, tol, max_gap_slots):
    """Successor of each member tree along its row (-1 at a row's end).

    Strategy: candidate links go forward along ``u`` and lie within ``tol`` of the
    line through both trees' local row directions; the shortest links are taken first,
    each tree keeping one successor and one predecessor. Short links (up to one empty
    slot) are matched before long ones, so a long link only bridges a run of empty
    slots between two row fragments.
    """
    n = len(members)
    succ = np.full(n, -1, dtype=np.int64)
    pred = np.full(n, -1, dtype=np.int64)
    p = xy[members]
    d_loc = direction[members]
    tree = cKDTree(p)

    def match(pairs: np.ndarray) -> None:
        if not len(pairs):
            return
        i, j = pairs[:, 0], pairs[:, 1]
        vec = p[j] - p[i]
        along = vec @ u
        flip = along < 0
        i, j = np.where(flip, j, i), np.where(flip, i, j)
        vec = np.where(flip[:, None], -vec, vec)
        mid = d_loc[i] * np.sign(np.einsum("ij,ij->i", d_loc[i], d_loc[j]))[:, None] + d_loc[j]
        norm = np.hypot(mid[:, 0], mid[:, 1])
        mid = mid / np.where(norm > 0, norm, 1.0)[:, None]
        lateral = np.abs(vec[:, 0] * mid[:, 1] - vec[:, 1] * mid[:, 0])
        dist = np.hypot(vec[:, 0], vec[:, 1])
        ok = (lateral <= tol) & (along != 0)
        order = np.lexsort((j[ok], i[ok], dist[ok]))
        for a, b in zip(i[ok][order], j[ok][order]):
            if succ[a] < 0 and pred[b] < 0:  # links go forward along u: no loops
                succ[a] = b
                pred[b] = a

    match(tree.query_pairs(SHORT_LINK_SLOTS * spacing, output_type="ndarray").astype(np.int64).reshape(-1, 2))
    ends = np.flatnonzero((succ < 0) | (pred < 0))
    if len(ends) > 1 and max_gap_slots > SHORT_LINK_SLOTS:
        sub = cKDTree(p[ends])
        far = sub.query_pairs(max_gap_slots * spacing, output_type="ndarray").astype(np.int64).reshape(-1, 2)
        if len(far):
            far = ends[far]
            a, b = far[:, 0], far[:, 1]
            fwd = (p[b] - p[a]) @ u > 0
            start, stop = np.where(fwd, a, b), np.where(fwd, b, a)
            usable = (succ[start] < 0) & (pred[stop] < 0)
            match(np.c_[start[usable], stop[usable]])
    return succ, pred


def linked_directions(xy: np.ndarray, near: np.ndarray, members: np.ndarray, succ: np.ndarray,
                      direction: np.ndarray) -> np.ndarray:
    """(k, 2) ``direction`` with each member's row direction read off the links found
    (:func:`link_trees`' ``succ`` of the ``members``): the mean, as doubled angles, of
    the links of its nearest trees ``near`` (k, m), itself first. Where empty slots put
    a tree's nearest tree across the row, :func:`local_directions` leans across it; the
    links, which bridge such slots, lie along the row. A member with no link among its
    nearest trees keeps its direction."""
    k = len(xy)
    linked = succ >= 0
    a, b = members[linked], members[succ[linked]]
    d2 = _doubled(xy[b] - xy[a])
    total = np.zeros((k, 2))
    count = np.zeros(k)
    for end in (a, b):  # a link counts at both its trees
        np.add.at(total, end, d2)
        np.add.at(count, end, 1.0)
    mean = total[near[members]].sum(axis=1)
    ok = (count[near[members]].sum(axis=1) > 0) & (np.hypot(mean[:, 0], mean[:, 1]) > 0)
    ang = 0.5 * np.arctan2(mean[ok, 1], mean[ok, 0])
    out = direction.copy()
    out[members[ok]] = np.c_[np.cos(ang), np.sin(ang)]
    return out


def chains_of(succ: np.ndarray, pred: np.ndarray) -> list[np.ndarray]:
    chains = []
    for start in np.flatnonzero(pred < 0):
        chain = [start]
        while succ[chain[-1]] >= 0:
            chain.append(succ[chain[-1]])
        chains.append(np.asarray(chain, dtype=np.int64))
    return chains


def nearest_along(xy: np.ndarray, u: np.ndarray, max_angle: float = 30.0) -> float:
    """Share of the trees ``xy`` (k, 2) [m] whose nearest tree lies within ``max_angle``
    degrees of the direction ``u``."""
    if len(xy) < 2:
        return 1.0
    near = cKDTree(xy).query(xy, k=2)[1][:, 1]
    vec = xy[near] - xy
    cos = np.abs(vec @ u) / np.maximum(np.hypot(vec[:, 0], vec[:, 1]), 1e-12)
    return float((cos >= np.cos(np.radians(max_angle))).mean())


def chain_spacing(xy: np.ndarray, chains: list[np.ndarray], u: np.ndarray, min_gap: float) -> float:
    """Median distance [m] across ``u`` between neighbouring lines of the ``chains`` of two
    or more trees (member indices into ``xy``), counting only lines more than ``min_gap``
    [m] apart (fragments of one row are one line); NaN without two such lines."""
    v = np.array([-u[1], u[0]])
    offs = np.sort([float(np.median(xy[ch] @ v)) for ch in chains if len(ch) >= 2])
    gaps = np.diff(offs)
    gaps = gaps[gaps > min_gap]
    return float(np.median(gaps)) if len(gaps) else float("nan")


def measured_row_spacing(xy: np.ndarray, direction: np.ndarray, tree: cKDTree) -> float:
    """Median distance [m] from a tree to the nearest tree of a neighbouring row (one
    lying more than 60° off its row direction), or NaN for a block of one row."""
    k = len(xy)
    m = min(k, 40)
    dist, near = tree.query(xy, k=m)
    vec = xy[near.reshape(k, m)] - xy[:, None, :]
    along = np.abs(np.einsum("ijk,ik->ij", vec, direction))
    across = np.abs(vec[..., 0] * direction[:, None, 1] - vec[..., 1] * direction[:, None, 0])
    off = across > np.tan(np.radians(60.0)) * along
    off[:, 0] = False
    lateral = np.where(off, across, np.inf).min(axis=1)
    lateral = lateral[np.isfinite(lateral)]
    return float(np.median(lateral)) if len(lateral) >= max(3, 0.2 * k) else float("nan")


def bands(across: np.ndarray, width: float) -> np.ndarray:
    """(n,) int64 band of each across offset [m]: the fewest bands ``width`` [m] wide
    that hold them all (greedy from the lowest offset, which is optimal on a line)."""
    order = np.argsort(across, kind="stable")
    c = across[order]
    label = np.zeros(len(c), dtype=np.int64)
    i, band = 0, 0
    while i < len(c):  # one step per band
        j = int(np.searchsorted(c, c[i] + width, side="right"))
        label[i:j] = band
        i, band = j, band + 1
    out = np.empty(len(c), dtype=np.int64)
    out[order] = label
    return out


def band_count(xy: np.ndarray, u: np.ndarray, width: float) -> int:
    """Lines ``width`` [m] wide along ``u`` needed to hold all trees ``xy`` (:func:`bands`)."""
    return _band_fit(xy, u, width)[0]


def _band_fit(xy: np.ndarray, u: np.ndarray, width: float) -> tuple[int, float, np.ndarray]:
    """Bands (:func:`bands`) of the trees ``xy`` across direction ``u``: their number, the
    trees' squared offsets from their bands' means [m²], and each tree's band."""
    c = xy @ np.array([-u[1], u[0]])
    label = bands(c, width)
    mean = np.bincount(label, weights=c) / np.bincount(label)
    return int(label.max()) + 1, float(((c - mean[label]) ** 2).sum()), label


def banded_direction(xy: np.ndarray, width: float, neighbours: int = 12,
                     candidates: int = 64) -> tuple[np.ndarray, int, float]:
    """The direction along which the trees ``xy`` (k, 2) [m] stand in the fewest lines
    ``width`` [m] wide, that number of lines, and the median distance [m] between
    neighbouring lines of two or more trees (NaN without two).

    Strategy: the candidates are the directions (to 0.5 degrees) from each tree to its
    nearest ``neighbours`` trees (a row's trees lie one, two or three slots apart, so one
    of these runs along it), the ``candidates`` most frequent of them; each is scored by the bands its across offsets make
    (:func:`bands`): fewest, then tightest. The winner's angle is refined as the common
    direction of its bands of two or more trees (their pooled principal axis)."""
    k = len(xy)
    m = min(k, neighbours + 1)
    near = cKDTree(xy).query(xy, k=m)[1].reshape(k, m)
    vec = (xy[near[:, 1:]] - xy[:, None, :]).reshape(-1, 2)
    vec = vec[np.hypot(vec[:, 0], vec[:, 1]) > 0]
    ang, count = np.unique(np.round(2.0 * (np.degrees(np.arctan2(vec[:, 1], vec[:, 0])) % 180.0)) / 2.0,
                           return_counts=True)
    ang = ang[np.sort(np.argsort(-count, kind="stable")[:candidates])]  # a lattice's directions recur
    best = None
    for a in ang:
        u = np.array([np.cos(np.radians(a)), np.sin(np.radians(a))])
        n, spread, label = _band_fit(xy, u, width)
        if best is None or (n, spread) < best[:2]:
            best = (n, spread, label, u)
    n, _, label, u = best
    sizes = np.bincount(label)
    lined = sizes[label] >= 2
    if lined.sum() >= 3:
        means = np.c_[np.bincount(label, weights=xy[:, 0]), np.bincount(label, weights=xy[:, 1])] / sizes[:, None]
        d = (xy - means[label])[lined]
        vecs = np.linalg.eigh(d.T @ d)[1]
        if _band_fit(xy, vecs[:, 1], width)[0] <= n:
            u = vecs[:, 1]
    u = u / np.hypot(*u)
    n, _, label = _band_fit(xy, u, width)
    c = xy @ np.array([-u[1], u[0]])
    sizes = np.bincount(label)
    lines = np.sort((np.bincount(label, weights=c) / sizes)[sizes >= 2])
    return u, n, float(np.median(np.diff(lines))) if len(lines) >= 2 else float("nan")
