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
from scipy.spatial import ConvexHull, QhullError

from pipeline.params import MetricsParams

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


def _crown_hulls(crown: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plan-view and 3D hull vertices of a crown's points, (h, 2) and (g, 3).

    The plan-view hull's vertices are among the projected 3D hull's vertices, so when
    the 3D hull exists the plan-view hull is taken over its vertices only.
    """
    if crown.shape[0] <= 4:
        return crown[:, :2].copy(), crown.copy()
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

    Returns
    -------
    TreePartials for the trees that have at least one point.
    """
    # Strategy: sort the tree points by id once, then reduce each contiguous run.
    idx = np.flatnonzero(tree_id > 0)
    order, uniq, start, counts = group_runs(tree_id[idx])
    idx = idx[order]
    pts, wood = xyz[idx], is_wood[idx]
    n_wood = np.add.reduceat(wood.astype(np.int64), start) if uniq.size else np.zeros(0, np.int64)
    z_max = np.maximum.reduceat(pts[:, 2], start) if uniq.size else np.zeros(0)
    crown_xy, crown_xyz = [], []
    for t, s, c in zip(uniq, start, counts):
        p = pts[s : s + c]
        crown = p[p[:, 2] - trunk_z[t - 1] >= params.crown_base]
        xy, xyz = _crown_hulls(crown)
        crown_xy.append(xy)
        crown_xyz.append(xyz)
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
    if len(v) < 2:
        return 0.0, 0.0
    diff = v[:, None, :] - v[None, :, :]
    diameter = float(np.sqrt((diff**2).sum(-1)).max())
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


# Fixed tuning of the circle fits (lengths in metres).

#: points of one cross-section a circle fit uses at most (evenly spaced in input order)
MAX_FIT_POINTS = 100_000
_FIT_CHUNK = 1 << 16  # residuals computed per block of trials (elements; cache-sized)
#: fewest points (and inliers) a circle is fitted to
MIN_FIT_POINTS = 5
#: residual [m] under which a point supports a circle: bark roughness on a clean scan
FIT_INLIER = 0.02
#: RANSAC triples tried per circle
FIT_TRIALS = 256
#: radial residuals within this distance [m] of a first circle estimate the scan's noise
#: at the trunk (see :func:`trunk_circle`)
NOISE_WINDOW = 0.15
#: the refit's inlier band, in noise sigmas (a fixed 2 cm band keeps only part of a noisy trunk)
NOISE_INLIER_SIGMAS = 2.5
#: most least-squares rounds of a stem circle's refit in its noise band (on 706 slices of
#: generated trunks it settled within 4 rounds for all but 7, and within 7 for all)
REFIT_ROUNDS = 10
#: depth inside a stem's circle, in inlier bands, beyond which a point counts against it
#: (:func:`fit_circle`'s ``solid``). Chosen on blocks of seeds >= 1000 and a clean noisy
#: arc: at 1 band a 0.1 m trunk at sigma 0.05 m came out 5 mm small on average, at 2
#: more thin stems kept circles several times their size (docs/method.md)
SOLID_INSIDE_BANDS = 1.5
#: a stem circle of a smaller radius [m] is a fit to a few close points, not a trunk
MIN_TRUNK_RADIUS = 0.005
#: the slice is first picked by height above the ground, this much wider [m] than by
#: height above the trunk base (the two differ on sloping ground)
SLICE_PRESELECT_MARGIN = 0.1


def fit_circle(xy: np.ndarray, *, inlier: float = FIT_INLIER, trials: int = FIT_TRIALS,
               solid: bool = False) -> tuple[np.ndarray, float]:
    """Robust circle through 2D points: RANSAC over point triples, then least squares.

    Parameters
    ----------
    xy : (n, 2) float64 [m]
    inlier : float — residual [m] under which a point supports a circle
    trials : int — random triples tried (fixed seed: the result is deterministic)
    solid : bool — the section of something solid (a stem): a point more than
        ``SOLID_INSIDE_BANDS`` bands inside a circle counts against it, as no bark lies
        inside a stem. A stem thinner than the band fits whole within the band of any
        larger circle through it, and plain support then picks the larger circle the
        clutter around the stem (leaves, grass, shoots) adds points to.

    Returns
    -------
    centre (2,), radius [m]; radius NaN when fewer than MIN_FIT_POINTS points.
    """
    n = len(xy)
    if n < MIN_FIT_POINTS:
        return np.full(2, np.nan), float("nan")
    if n > MAX_FIT_POINTS:  # a cross-section scanned at sub-millimetre spacing: every k-th point
        xy = xy[:: -(-n // MAX_FIT_POINTS)]
        n = len(xy)
    rng = np.random.default_rng(0)
    tri = rng.integers(0, n, (trials, 3))  # a triple repeating a point is degenerate: d = 0 below
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    d = 2 * (a[:, 0] * (b[:, 1] - c[:, 1]) + b[:, 0] * (c[:, 1] - a[:, 1]) + c[:, 0] * (a[:, 1] - b[:, 1]))
    ok = np.abs(d) > 1e-12
    a2, b2, c2 = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / np.where(ok, d, 1)
    uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / np.where(ok, d, 1)
    r = np.hypot(a[:, 0] - ux, a[:, 1] - uy)
    inside = SOLID_INSIDE_BANDS * inlier if solid else None
    support = np.where(ok, circle_support(xy, ux, uy, r, inlier, inside_depth=inside), -(n + 1))
    best = int(np.argmax(support))
    keep = np.abs(np.hypot(xy[:, 0] - ux[best], xy[:, 1] - uy[best]) - r[best]) < inlier
    if keep.sum() < MIN_FIT_POINTS:
        return np.full(2, np.nan), float("nan")
    return _least_squares_circle(xy[keep])


def _least_squares_circle(p: np.ndarray) -> tuple[np.ndarray, float]:
    """The algebraic least-squares circle through points ``p`` (m, 2): centre, radius."""
    mu = p.mean(axis=0)
    q = p - mu
    sol, *_ = np.linalg.lstsq(np.column_stack([2 * q, np.ones(len(q))]), (q**2).sum(1), rcond=None)
    centre = sol[:2] + mu
    return centre, float(np.sqrt(max(sol[2] + (sol[:2] ** 2).sum(), 0.0)))


def circle_support(xy: np.ndarray, ux: np.ndarray, uy: np.ndarray, r: np.ndarray, inlier: float, *,
                   inside_depth: float | None = None) -> np.ndarray:
    """Points of ``xy`` (n, 2) [m] supporting each circle (``ux``, ``uy``, ``r``), (t,) int:
    those with ``abs(hypot(x - ux, y - uy) - r) < inlier`` [m], counted exactly so. Given
    ``inside_depth`` [m], less those more than that inside the circle (by ``sqrt(dx² + dy²)``).

    ``np.hypot`` costs several times ``sqrt(dx² + dy²)``, which is within a few ulps of
    it: the sum of squares decides every point but those within a rounding margin of the
    band's edges (or not finite), which ``np.hypot`` decides as the definition does.
    """
    # Strategy: a few trials at a time, small enough to stay in cache (a whole trials x n
    # matrix would take gigabytes on a densely scanned trunk).
    x, y = xy[None, :, 0], xy[None, :, 1]
    n, t = xy.shape[0], ux.shape[0]
    out = np.zeros(t, np.int64)
    step = min(t, max(1, _FIT_CHUNK // max(n, 1)))
    # buffers reused by every block of trials: fresh temporaries of this size cost page faults
    dx, dy, d, tmp = (np.empty((step, n)) for _ in range(4))
    inside, unsure = np.empty((step, n), bool), np.empty((step, n), bool)
    # sqrt of the rounded squares is within 3 ulps of hypot: 16 ulps of the largest
    # distance at the band's edge is a safe margin
    margin = 16 * np.finfo(np.float64).eps * (np.abs(r) + 2 * inlier)
    for s0 in range(0, t, step):
        s1 = min(t, s0 + step)
        k = s1 - s0
        dx_, dy_, d_, tmp_, in_, un_ = dx[:k], dy[:k], d[:k], tmp[:k], inside[:k], unsure[:k]
        rr = r[s0:s1, None]
        np.subtract(x, ux[s0:s1, None], out=dx_)
        np.subtract(y, uy[s0:s1, None], out=dy_)
        np.multiply(dx_, dx_, out=d_)
        np.multiply(dy_, dy_, out=tmp_)
        np.add(d_, tmp_, out=d_)
        np.sqrt(d_, out=d_)
        np.subtract(d_, rr, out=d_)
        if inside_depth is not None:
            np.less(d_, -inside_depth, out=un_)
            out[s0:s1] = -np.count_nonzero(un_, axis=1)
        np.abs(d_, out=d_)  # the residual
        np.less(d_, inlier, out=in_)
        np.subtract(d_, inlier, out=tmp_)
        np.abs(tmp_, out=tmp_)
        np.greater(tmp_, margin[s0:s1, None], out=un_)
        np.logical_not(un_, out=un_)  # near an edge, or not finite
        if un_.any():
            i, j = np.nonzero(un_)
            in_[i, j] = np.abs(np.hypot(dx_[i, j], dy_[i, j]) - rr[i, 0]) < inlier
        out[s0:s1] += np.count_nonzero(in_, axis=1)
    return out


def trunk_circle(xy: np.ndarray, *, inlier: float = FIT_INLIER, trials: int = FIT_TRIALS,
                 solid: bool = True) -> tuple[np.ndarray, float]:
    """A circle through a trunk's cross-section, corrected for the scan's noise.

    Range noise scatters the bark's points on both sides of the circle, and a circle fit
    to them comes out too large: with noise sigma per axis the mean squared distance
    from the centre is r² + 2 sigma². This fits :func:`fit_circle` (``solid``: see
    there), estimates sigma from the points' radial residuals (their median absolute
    deviation, within ``NOISE_WINDOW`` of that circle), refits with the inlier band
    widened to ``NOISE_INLIER_SIGMAS`` sigma and returns the radius sqrt(R² - 2 sigma²),
    at least R / 2 (the effect on diameters: docs/method.md).

    With ``solid`` the refit stays with that circle: least squares on the points within
    the widened band, repeated until those points stop changing (at most
    ``REFIT_ROUNDS``); a new search with the wide band could pick another circle that
    the band lets gather more of the clutter. Without, the search is run again with it.

    Returns
    -------
    centre (2,), radius [m]; as :func:`fit_circle`.
    """
    centre, r = fit_circle(xy, inlier=inlier, trials=trials, solid=solid)
    if not np.isfinite(r):
        return centre, r
    res = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1]) - r
    res = res[np.abs(res) < NOISE_WINDOW]
    sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))  # a normal sigma per MAD
    band = max(inlier, NOISE_INLIER_SIGMAS * sigma)
    c2, r2 = _refit_in_band(xy, centre, r, band) if solid else fit_circle(xy, inlier=band, trials=trials)
    if not np.isfinite(r2):
        return centre, r
    return c2, float(np.sqrt(max(r2 * r2 - 2.0 * sigma * sigma, 0.25 * r2 * r2)))


def _refit_in_band(xy: np.ndarray, centre: np.ndarray, r: float, band: float) -> tuple[np.ndarray, float]:
    """Least squares on the points within ``band`` [m] of the circle, repeated on the
    new circle's band until its points stop changing (at most ``REFIT_ROUNDS``); NaN
    radius with fewer than MIN_FIT_POINTS points in a band."""
    keep = None
    for _ in range(REFIT_ROUNDS):
        near = np.abs(np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1]) - r) < band
        if np.count_nonzero(near) < MIN_FIT_POINTS:
            return np.full(2, np.nan), float("nan")
        if keep is not None and np.array_equal(near, keep):
            break
        keep = near
        centre, r = _least_squares_circle(xy[keep])
    return centre, r


def trunk_circles(
    xyz: np.ndarray,
    tree_id: np.ndarray,
    trunks: np.ndarray,
    *,
    params: MetricsParams,
    height: np.ndarray | None = None,
    solid: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """The stem of each tree at ``params.trunk_height`` above its base: centre and diameter.

    Fits a circle (:func:`trunk_circle`, corrected for noise; ``solid``: see there) to
    the tree's points in a horizontal slice of thickness ``params.trunk_slice`` within
    ``params.max_trunk_radius`` of the trunk. ``height`` (n,), the points' height above
    ground [m], only speeds up the selection.

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
        mask = (np.abs(height - params.trunk_height) <= params.trunk_slice / 2 + SLICE_PRESELECT_MARGIN) & (tree_id > 0)
    else:
        mask = tree_id > 0
    pts, ids = xyz[mask], tree_id[mask]
    dz = pts[:, 2] - trunks[ids - 1, 2]
    in_slice = np.abs(dz - params.trunk_height) <= params.trunk_slice / 2
    d2 = ((pts[:, :2] - trunks[ids - 1, :2]) ** 2).sum(1)
    sel = in_slice & (d2 <= max_radius**2)
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
