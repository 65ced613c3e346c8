"""Per-tree measurements.

Metrics are computed from *partials* that can be merged: a tile computes partials for
the points in its core, the merge maps tile-local tree ids to global ones and combines
them (counts add, maxima take the max, and the convex hull of a union is the hull of
the union of the hulls' vertices). A single-block run is the one-tile case, so both
paths share this code.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from pipeline.circles import fit_circle, trunk_circle
from pipeline.params import MetricsParams
from pipeline.passes import indices_where
from pipeline.stemslice import stem_points
from pipeline.voxels import rows_by_column

TREE_COLUMNS = (
    "tree_id",
    "trunk_x",
    "trunk_y",
    "trunk_z",
    "height_m",
    "crown_diameter_m",
    "crown_area_m2",
    "crown_volume_m3",
    "trunk_diameter_m",
    "n_points",
    "wood_fraction",
)


@dataclass(frozen=True)
class TreePartials:
    """Mergeable per-tree aggregates.

    Attributes
    ----------
    tree_id : (m,) int64, sorted, unique, >= 1
    n_points, n_wood : (m,) int64
    z_max : (m,) float64
        Highest point of the tree [m], in the frame of the points.
    crown_xy : list of (h, 2) float64
        Convex-hull vertices of the crown points in plan view (may be empty arrays).
    crown_xyz : list of (g, 3) float64
        Convex-hull vertices of the crown points in 3D (may be empty arrays).
    """

    tree_id: np.ndarray
    n_points: np.ndarray
    n_wood: np.ndarray
    z_max: np.ndarray
    crown_xy: list
    crown_xyz: list

    def shifted(self, offset: np.ndarray) -> "TreePartials":
        """The same partials with coordinates moved by ``offset`` (3,)."""
        off = np.asarray(offset, dtype=np.float64)
        return TreePartials(
            self.tree_id,
            self.n_points,
            self.n_wood,
            self.z_max + off[2],
            [v + off[:2] for v in self.crown_xy],
            [v + off for v in self.crown_xyz],
        )


def group_runs(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Group equal labels: a stable order that sorts ``labels`` (n,) int, and each
    label's value, first position and length in that order (like ``np.unique`` with
    ``return_index`` and ``return_counts`` on the sorted labels).

    Labels in 0..65535 (tree ids of any tile) are sorted as uint16, which numpy sorts by
    radix, three times faster than int64.
    """
    labels = np.asarray(labels)
    key = labels
    if labels.size and labels.min() >= 0 and labels.max() <= np.iinfo(np.uint16).max:
        key = labels.astype(np.uint16)
    order = np.argsort(key, kind="stable")
    s = labels[order]
    start = np.flatnonzero(np.r_[True, s[1:] != s[:-1]]) if s.size else np.zeros(0, np.int64)
    counts = np.diff(np.r_[start, s.size])
    return order, s[start], start, counts


def _hull_vertices(pts: np.ndarray) -> np.ndarray:
    """Vertices of the convex hull of ``pts`` (all points if degenerate or tiny)."""
    d = pts.shape[1]
    if pts.shape[0] <= d + 1:
        return pts.copy()
    try:
        return pts[ConvexHull(pts).vertices]
    except QhullError:
        pass
    # flat or collinear: the hull within their plane or line still matters when these
    # points are merged with another tile's (the per-axis extremes alone lost vertices);
    # joggled input gives it, the points themselves if even that fails
    try:
        return pts[ConvexHull(pts, qhull_options="QJ").vertices]
    except QhullError:
        return np.unique(pts, axis=0)


#: crowns of fewer points go to qhull whole: :func:`_hull_candidates` would cost more than it saves
CANDIDATES_MIN_POINTS = 2_000
#: points per column of :func:`_hull_candidates`' plan grid, on average
CANDIDATES_COLUMN_POINTS = 64
#: height bins of :func:`_hull_candidates`' columns
CANDIDATES_HEIGHT_BINS = 128
#: most (column, bin) cells of :func:`_hull_candidates` per point (a compact crown has about
#: two): their counts take 8 bytes a cell
CANDIDATES_CELLS_PER_POINT = 4
_AROUND = np.ones((3, 3), bool)
_AROUND[1, 1] = False


def _hull_candidates(pts: np.ndarray) -> np.ndarray:
    """The points of ``pts`` (n, 3) that may be vertices of their convex hull, in order.

    A point is dropped when each of the eight columns around its own (a plan grid of
    about CANDIDATES_COLUMN_POINTS points a column) holds a point in a higher height bin
    and one in a lower bin than its own. In any direction, the column diagonal to its
    own on that side (beside it, for a direction with no x or no y part) then holds a
    point farther along it, so the point is inside the others' hull and the hull is the
    same without it. On a crown at mobile-scan density 60–70 % of the points go, and
    qhull's time with them (docs/performance.md).
    """
    n = pts.shape[0]
    if n < CANDIDATES_MIN_POINTS:
        return pts
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    lo = np.array([x.min(), y.min(), z.min()])
    span = np.array([x.max(), y.max(), z.max()]) - lo
    if not (span > 0).all():
        return pts  # flat: no point is inside the others' hull
    k = 1.0 / np.sqrt(span[0] * span[1] * CANDIDATES_COLUMN_POINTS / n)  # columns per metre
    kz = (CANDIDATES_HEIGHT_BINS - 1) / span[2]
    # the largest coordinate gives the largest index: the same arithmetic sizes the grid
    nx, ny, nz = int(span[0] * k) + 1, int(span[1] * k) + 1, int(span[2] * kz) + 1
    if nx * ny * nz > CANDIDATES_CELLS_PER_POINT * n:
        return pts  # a crown this thin has few inner columns: not worth a grid this large
    cell = ((x - lo[0]) * k).astype(np.int32)
    cell *= ny
    cell += ((y - lo[1]) * k).astype(np.int32)
    level = ((z - lo[2]) * kz).astype(np.int32)
    held = (np.bincount(cell * nz + level, minlength=nx * ny * nz) > 0).reshape(nx * ny, nz)
    some = held.any(axis=1)
    top = np.where(some, nz - 1 - np.argmax(held[:, ::-1], axis=1), -1).reshape(nx, ny)
    bottom = np.where(some, np.argmax(held, axis=1), nz).reshape(nx, ny)
    # the lowest top and the highest bottom around each column (none beyond the grid)
    lowest_top = ndimage.minimum_filter(top, footprint=_AROUND, mode="constant", cval=-1).ravel()
    highest_bottom = ndimage.maximum_filter(bottom, footprint=_AROUND, mode="constant", cval=nz).ravel()
    return pts[(level >= lowest_top[cell]) | (level <= highest_bottom[cell])]


def _crown_hulls(crown: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plan-view and 3D hull vertices of a crown's points, (h, 2) and (g, 3).

    The plan-view hull's vertices are among the projected 3D hull's vertices, so when
    the 3D hull exists the plan-view hull is taken over its vertices only.
    """
    if crown.shape[0] <= 4:
        return crown[:, :2].copy(), crown.copy()
    crown = _hull_candidates(crown)  # the same hull, its vertices in the same order
    try:
        xyz = crown[ConvexHull(crown).vertices]
    except QhullError:  # flat or collinear
        return _hull_vertices(crown[:, :2]), _hull_vertices(crown)
    return _hull_vertices(xyz[:, :2]), xyz


def tree_partials(
    xyz: np.ndarray,
    tree_id: np.ndarray,
    is_wood: np.ndarray,
    trunk_z: np.ndarray,
    *,
    params: MetricsParams,
    among: np.ndarray | None = None,
) -> TreePartials:
    """Aggregate the points of every tree.

    Parameters
    ----------
    xyz : (n, 3) float64 [m]
    tree_id : (n,) int64, 0 = not a tree, k = tree whose trunk base height is ``trunk_z[k-1]``
    is_wood : (n,) bool
    trunk_z : (k,) float64
        Trunk base height of each tree [m], same frame as ``xyz``.
    params : MetricsParams
        ``crown_base`` decides which points are crown.
    among : (n,) bool, optional
        The points to aggregate (default all): the same partials as of
        ``xyz[among]``, ``tree_id[among]``, ``is_wood[among]``, without those copies.

    Returns
    -------
    TreePartials for the trees that have at least one point.
    """
    # Strategy: sort the tree points by id once, then reduce each contiguous run. Only
    # heights are gathered for every tree point; whole points only for the crowns.
    if among is None:
        idx = indices_where(tree_id.shape[0], lambda s: tree_id[s] > 0)
    else:  # the picked points in their order: the same runs and crowns as of the copies
        idx = indices_where(tree_id.shape[0], lambda s: (tree_id[s] > 0) & among[s])
    order, uniq, start, counts = group_runs(tree_id[idx])
    idx = idx[order]
    if uniq.size == 0:
        return TreePartials(uniq.astype(np.int64), counts.astype(np.int64), np.zeros(0, np.int64), np.zeros(0), [], [])
    z = xyz[idx, 2]
    n_wood = np.add.reduceat(is_wood[idx].astype(np.int64), start)
    z_max = np.maximum.reduceat(z, start)
    z -= np.repeat(trunk_z[uniq - 1], counts)  # the height above the tree's trunk base, as each tree's own subtraction gave it
    crown = z >= params.crown_base
    crown_end = np.cumsum(np.add.reduceat(crown.astype(np.int64), start))
    crowns = rows_by_column(xyz, idx[crown])  # the hull candidates' passes run down its columns
    crown_xy, crown_xyz = [], []
    for e, c in zip(crown_end.tolist(), np.diff(np.r_[0, crown_end]).tolist()):
        hull_xy, hull_xyz = _crown_hulls(crowns[e - c : e])
        crown_xy.append(hull_xy)
        crown_xyz.append(hull_xyz)
    return TreePartials(uniq.astype(np.int64), counts.astype(np.int64), n_wood.astype(np.int64), z_max, crown_xy, crown_xyz)


def combine_partials(parts: list[TreePartials], id_maps: list[np.ndarray]) -> TreePartials:
    """Merge partials from several tiles into partials over global tree ids.

    Parameters
    ----------
    parts : list of TreePartials, tile-local ids
    id_maps : list of (k_t + 1,) int64
        ``id_maps[t][local_id]`` is the global id (0 drops the tree's points).
    """
    rows = []
    for part, mp in zip(parts, id_maps):
        g = mp[part.tree_id]
        for i in np.flatnonzero(g > 0):
            rows.append((int(g[i]), part, i))
    rows.sort(key=lambda r: r[0])
    out_id, n, nw, zm, cxy, cxyz = [], [], [], [], [], []
    j = 0
    while j < len(rows):
        gid = rows[j][0]
        k = j
        while k < len(rows) and rows[k][0] == gid:
            k += 1
        group = rows[j:k]
        out_id.append(gid)
        n.append(sum(int(p.n_points[i]) for _, p, i in group))
        nw.append(sum(int(p.n_wood[i]) for _, p, i in group))
        zm.append(max(float(p.z_max[i]) for _, p, i in group))
        cxy.append(_hull_vertices(np.concatenate([p.crown_xy[i] for _, p, i in group])))
        cxyz.append(_hull_vertices(np.concatenate([p.crown_xyz[i] for _, p, i in group])))
        j = k
    return TreePartials(
        np.asarray(out_id, dtype=np.int64),
        np.asarray(n, dtype=np.int64),
        np.asarray(nw, dtype=np.int64),
        np.asarray(zm, dtype=np.float64),
        cxy,
        cxyz,
    )


def _area_and_diameter(v: np.ndarray) -> tuple[float, float]:
    """Area [m²] and average spread [m] of the plan-view crown hull with vertices ``v`` (h, 2).

    The average spread is the mean of the longest spread (the two vertices farthest
    apart) and the spread at right angles to it, as foresters and arborists measure a
    crown's diameter (the mean of the widest spread and the one across it): one twig
    reaching out moves it by half its reach, and a crown cut by its neighbours in a row
    reads as the mean of its width across the row and its share along it.
    """
    if len(v) < 2:
        return 0.0, 0.0
    diff = v[:, None, :] - v[None, :, :]
    dist = np.sqrt((diff**2).sum(-1))
    a, b = np.unravel_index(dist.argmax(), dist.shape)
    longest = float(dist[a, b])
    across = v @ np.array([v[a, 1] - v[b, 1], v[b, 0] - v[a, 0]]) / max(longest, 1e-300)
    diameter = 0.5 * (longest + float(across.max() - across.min()))
    if len(v) < 3:
        return 0.0, diameter
    try:
        return float(ConvexHull(v).volume), diameter  # in 2D, "volume" is the area
    except QhullError:
        return 0.0, diameter


def _volume(v: np.ndarray) -> float:
    if len(v) < 4:
        return 0.0
    try:
        return float(ConvexHull(v).volume)
    except QhullError:
        return 0.0


def finalize_metrics(
    partials: TreePartials,
    trunks: np.ndarray,
    trunk_diameter: np.ndarray,
) -> dict[str, np.ndarray]:
    """Per-tree table from merged partials.

    Parameters
    ----------
    partials : TreePartials over ids 1..k (ids with no points get zero counts)
    trunks : (k, 3) float64
        Trunk bases, in the same frame as the partials; tree k is ``trunks[k-1]``.
    trunk_diameter : (k,) float64 [m]

    Returns
    -------
    dict of column name → (k,) array, columns in ``TREE_COLUMNS`` order.
    """
    k = trunks.shape[0]
    ids = np.arange(1, k + 1, dtype=np.int64)
    n = np.zeros(k, np.int64)
    nw = np.zeros(k, np.int64)
    height = np.zeros(k)
    area = np.zeros(k)
    diam = np.zeros(k)
    vol = np.zeros(k)
    for j, t in enumerate(partials.tree_id):
        i = t - 1
        n[i] = partials.n_points[j]
        nw[i] = partials.n_wood[j]
        height[i] = max(0.0, partials.z_max[j] - trunks[i, 2])
        area[i], diam[i] = _area_and_diameter(partials.crown_xy[j])
        vol[i] = _volume(partials.crown_xyz[j])
    with np.errstate(invalid="ignore", divide="ignore"):
        wood_fraction = np.where(n > 0, nw / np.maximum(n, 1), 0.0)
    return {
        "tree_id": ids,
        "trunk_x": trunks[:, 0].astype(np.float64),
        "trunk_y": trunks[:, 1].astype(np.float64),
        "trunk_z": trunks[:, 2].astype(np.float64),
        "height_m": height,
        "crown_diameter_m": diam,
        "crown_area_m2": area,
        "crown_volume_m3": vol,
        "trunk_diameter_m": np.asarray(trunk_diameter, dtype=np.float64),
        "n_points": n,
        "wood_fraction": wood_fraction.astype(np.float64),
    }


# Fixed tuning of the stem slices (lengths in metres).

#: a stem circle of a smaller radius [m] is a fit to a few close points, not a trunk
MIN_TRUNK_RADIUS = 0.005
#: the slice is first picked by height above the ground, this much wider [m] than by
#: height above the trunk base (the two differ on sloping ground)
SLICE_PRESELECT_MARGIN = 0.1


def trunk_circles(
    xyz: np.ndarray,
    tree_id: np.ndarray,
    trunks: np.ndarray,
    *,
    params: MetricsParams,
    height: np.ndarray | None = None,
    solid: bool = True,
    stakes: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """The stem of each tree at ``params.trunk_height`` above its base: centre and diameter.

    Fits a circle (:func:`trunk_circle`, corrected for noise; ``solid``: see there) to
    the tree's points in a horizontal slice of thickness ``params.trunk_slice`` within
    ``params.max_trunk_radius`` of the trunk. ``height`` (n,), the points' height above
    ground [m], only speeds up the selection. ``stakes``: young trees, a stake touching
    each stem (:func:`pipeline.stemslice.stem_points`).

    Returns
    -------
    centres : (k, 2) float64 [m]
        Centre of each fitted circle (same frame as ``xyz``); NaN where not measurable.
    diameters : (k,) float64 [m]
        NaN where fewer than MIN_FIT_POINTS points or the fit is implausible.
    """
    max_radius = params.max_trunk_radius
    k = trunks.shape[0]
    out = np.full(k, np.nan)
    centres = np.full((k, 2), np.nan)
    if k == 0:
        return centres, out
    if height is not None:  # pre-select the slice by height above ground (cheap)
        reach = params.trunk_slice / 2 + SLICE_PRESELECT_MARGIN

        def near(s: slice) -> np.ndarray:
            return (np.abs(height[s] - params.trunk_height) <= reach) & (tree_id[s] > 0)
    else:
        def near(s: slice) -> np.ndarray:
            return tree_id[s] > 0
    pre = indices_where(tree_id.shape[0], near)
    pts, ids = xyz[pre], tree_id[pre]
    dz = pts[:, 2] - trunks[ids - 1, 2]
    in_slice = np.abs(dz - params.trunk_height) <= params.trunk_slice / 2
    d2 = ((pts[:, :2] - trunks[ids - 1, :2]) ** 2).sum(1)
    sel = np.flatnonzero(in_slice & (d2 <= max_radius**2))
    sel = sel[stem_points(pts[sel, :2], ids[sel], stakes=stakes)]  # no riser or stake beside the stem
    c, r = tree_circles(pts[sel, :2], ids[sel], k, fit=partial(trunk_circle, solid=solid))
    ok = np.isfinite(r) & (r > MIN_TRUNK_RADIUS) & (r <= max_radius)
    out[ok] = 2 * r[ok]
    centres[ok] = c[ok]
    return centres, out


def tree_circles(xy: np.ndarray, tree_id: np.ndarray, k: int, *, fit=fit_circle) -> tuple[np.ndarray, np.ndarray]:
    """A circle (``fit``: :func:`fit_circle` or :func:`trunk_circle`) through each tree's points.

    Parameters
    ----------
    xy : (n, 2) float64 [m]
    tree_id : (n,) int64 — tree of each point, 1..k
    k : int — number of trees

    Returns
    -------
    centres (k, 2) and radii (k,) [m]; NaN for trees with no fit (fewer than MIN_FIT_POINTS points).
    """
    centres = np.full((k, 2), np.nan)
    radii = np.full(k, np.nan)
    order, uniq, start, counts = group_runs(tree_id)
    xy = xy[order]
    for t, s, c in zip(uniq, start, counts):
        centres[t - 1], radii[t - 1] = fit(xy[s : s + c])
    return centres, radii
