"""Circles through the cross-sections of stems and posts.

A RANSAC search over random point triples (:func:`fit_circle`), each circle scored by
the points within a band around it (:func:`circle_support`), then least squares on the
best one's points; :func:`trunk_circle` corrects the radius for the scan's noise. Used
for trunk diameters (:mod:`pipeline.metrics`), the trunks' feet and the trellis-post
test (:mod:`pipeline.posts`).
"""

from __future__ import annotations

import functools

import numpy as np

# Fixed tuning of the circle fits (lengths in metres).

#: points of one cross-section a circle fit uses at most (evenly spaced in input order)
MAX_FIT_POINTS = 100_000
_FIT_CHUNK = 1 << 16  # residuals computed per block of trials (elements; cache-sized)
#: ulps of a squared distance's largest term that bound its rounding in
#: :func:`circle_support`'s product and in the definition's own distance (4 terms, each
#: within a few ulps; the definition's sqrt and hypot within 3 ulps of each other)
_BAND_ROUNDING = 64
#: below this many points :func:`circle_support` lays its products out points x circles
#: (counts as column sums), from it circles x points (row sums): the faster on one core
_COLUMN_SUM_POINTS = 128
#: a circle whose rounding bound is this share of its band or more is counted point by point
_MAX_BAND_MARGIN = 1e-9
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
    if len(xy) < MIN_FIT_POINTS:
        return np.full(2, np.nan), float("nan")
    return _fit_tried(_circle_trials(xy, trials), inlier, solid=solid)


def _fit_tried(tried: tuple[np.ndarray, ...], inlier: float, *, solid: bool = False) -> tuple[np.ndarray, float]:
    """The circle of :func:`fit_circle` from the circles ``tried`` (:func:`_circle_trials`):
    the best supported within the band ``inlier`` [m] (``solid``: less the points more than
    SOLID_INSIDE_BANDS bands inside), refitted by least squares (:func:`_best_circle`)."""
    inside = SOLID_INSIDE_BANDS * inlier if solid else None
    return _best_circle(*tried, circle_support(*tried[:4], inlier, inside_depth=inside), inlier)


def _circle_trials(xy: np.ndarray, trials: int) -> tuple[np.ndarray, ...]:
    """The points a fit uses (at most MAX_FIT_POINTS of ``xy``) and the circles through
    ``trials`` random triples of them: (xy, ux, uy, r, ok), ``ok`` False where a triple
    is degenerate. The draw has a fixed seed: two fits to the same points try the same
    circles."""
    n = len(xy)
    if n > MAX_FIT_POINTS:  # a cross-section scanned at sub-millimetre spacing: every k-th point
        xy = xy[:: -(-n // MAX_FIT_POINTS)]
        n = len(xy)
    tri = _triples(n, trials)  # a triple repeating a point is degenerate: d = 0 below
    x, y = xy[:, 0], xy[:, 1]
    (ax, bx, cx), (ay, by, cy) = (x[k] for k in tri), (y[k] for k in tri)
    d = 2 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    ok = np.abs(d) > 1e-12
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    d = np.where(ok, d, 1)
    ux = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / d
    uy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / d
    r = np.hypot(ax - ux, ay - uy)
    return xy, ux, uy, r, ok


@functools.lru_cache(maxsize=256)
def _triples(n: int, trials: int) -> np.ndarray:
    """The point indices of :func:`_circle_trials`' triples among ``n`` points, (3, trials)
    int64 (row k the k-th point of each), read-only: the draw of a fixed seed, kept as
    a block's post sections and stems draw it again and again for the same few counts."""
    tri = np.ascontiguousarray(np.random.default_rng(0).integers(0, n, (trials, 3)).T)
    tri.flags.writeable = False
    return tri


def _best_circle(xy: np.ndarray, ux: np.ndarray, uy: np.ndarray, r: np.ndarray, ok: np.ndarray,
                 support: np.ndarray, inlier: float) -> tuple[np.ndarray, float]:
    """Least squares on the points within ``inlier`` of the best supported of the tried
    circles (the first of equals); NaN radius with fewer than MIN_FIT_POINTS of them."""
    best = int(np.argmax(np.where(ok, support, -(len(xy) + 1))))
    keep = np.abs(np.hypot(xy[:, 0] - ux[best], xy[:, 1] - uy[best]) - r[best]) < inlier
    if keep.sum() < MIN_FIT_POINTS:
        return np.full(2, np.nan), float("nan")
    return _least_squares_circle(xy[keep])


def _mean_rows(p: np.ndarray) -> np.ndarray:
    """``p.mean(axis=0)`` of (m, 2) points, bit for bit (the same sum, divided by m),
    without its generic machinery: a fit takes a few means of a few dozen points."""
    return np.add.reduce(p, axis=0) / p.shape[0]


def _least_squares_circle(p: np.ndarray) -> tuple[np.ndarray, float]:
    """The algebraic least-squares circle through points ``p`` (m, 2): centre, radius."""
    mu = _mean_rows(p)
    q = p - mu
    sol, *_ = np.linalg.lstsq(np.column_stack([2 * q, np.ones(len(q))]), (q**2).sum(1), rcond=None)
    centre = sol[:2] + mu
    return centre, float(np.sqrt(max(sol[2] + (sol[:2] ** 2).sum(), 0.0)))


def circle_support(xy: np.ndarray, ux: np.ndarray, uy: np.ndarray, r: np.ndarray, inlier: float, *,
                   inside_depth: float | None = None) -> np.ndarray:
    """Points of ``xy`` (n, 2) [m] supporting each circle (``ux``, ``uy``, ``r``), (t,) int:
    those with ``abs(hypot(x - ux, y - uy) - r) < inlier`` [m], counted exactly so. Given
    ``inside_depth`` [m], less those more than that inside the circle (by ``sqrt(dx² + dy²)``).

    Each circle's band is a band of squared distances, and the squared distances of all
    points to a few circles are one matrix product of the points' coordinates and squares
    with the circles' (scaled so that the band is ``|.| < 1``). Each circle's points are
    counted twice, with the band narrowed and widened by a bound on the rounding of that
    product and of the definition; a circle whose two counts differ (a point within that
    bound of an edge) is counted again point by point (:func:`_support_pointwise`).
    """
    # Strategy: a few circles at a time, small enough to stay in cache (a whole trials x n
    # matrix would take gigabytes on a densely scanned trunk); per block of circles one
    # product, one abs and two comparisons with two sums, instead of the dozen passes
    # of a point-by-point residual.
    n, t = xy.shape[0], ux.shape[0]
    if n == 0 or t == 0 or not np.isfinite(xy).all():
        return _support_pointwise(xy, ux, uy, r, inlier, inside_depth=inside_depth)
    mean = _mean_rows(xy)  # centred, the squares stay small and so does their rounding
    p = xy - mean
    vx, vy = ux - mean[0], uy - mean[1]
    points = np.empty((4, n))
    points[0], points[1] = p[:, 0], p[:, 1]
    points[2] = p[:, 0] ** 2 + p[:, 1] ** 2
    points[3] = 1.0
    reach = float(np.sqrt(points[2].max()))
    u2 = vx * vx + vy * vy
    bound = (reach + np.sqrt(u2)) ** 2  # of every term of a squared distance

    m2vx, m2vy = -2 * vx, -2 * vy

    def band(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # lo < d < hi as |d² - c| < w (for lo <= 0, d² < hi²), with the product divided by w
        wide = lo > 0
        hh, ll = hi * hi, lo * lo
        c = np.where(wide, (hh + ll) / 2, 0.0)
        w = np.where(wide, (hh - ll) / 2, hh)
        rows = np.empty((4, t))  # a circle a column: whole rows reduced at a time
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for j, col in enumerate((m2vx, m2vy, 1.0, u2 - c)):
                np.divide(col, w, out=rows[j])
            rel = _BAND_ROUNDING * np.finfo(np.float64).eps * (bound + hh + c) / w
        unsure = ~((rel < _MAX_BAND_MARGIN) & np.isfinite(rows).all(axis=0))
        if unsure.any():
            rows[:, unsure] = 0.0
        return rows, unsure

    rows, unsure = band(r - inlier, r + inlier)
    if inside_depth is not None:  # d - r < -depth: d < r - depth, never where that is 0 or less
        deep_rows, deep_unsure = band(np.full(t, -1.0), r - inside_depth)
        unsure |= deep_unsure & (r - inside_depth > 0)
        can_be_inside = r - inside_depth > 0
    out = np.zeros(t, np.int64)
    step = min(t, max(1, _FIT_CHUNK // n))
    e_all, hits_all = np.empty(step * n), np.empty(step * n, np.uint8)
    count = np.uint16 if n < 1 << 16 else np.int64  # row sums of bytes: a narrow sum is several times faster
    narrow, widened = 1.0 - _MAX_BAND_MARGIN, 1.0 + _MAX_BAND_MARGIN

    # few points: points x circles, the counts column sums adding whole rows at a time (row
    # sums of a few points per circle pay a loop per circle); many: circles x points
    by_column = n < _COLUMN_SUM_POINTS
    point_rows = np.ascontiguousarray(points.T) if by_column else None

    def in_band(block_rows: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        shape, axis = ((n, k), 0) if by_column else ((k, n), 1)
        e, hits = e_all[: n * k].reshape(shape), hits_all[: n * k].reshape(shape)
        if by_column:
            np.matmul(point_rows, block_rows, out=e)
        else:
            np.matmul(block_rows.T, points, out=e)
        np.abs(e, out=e)
        np.less(e, narrow, out=hits)
        surely = hits.sum(axis=axis, dtype=count).astype(np.int64)
        np.less_equal(e, widened, out=hits)
        return surely, hits.sum(axis=axis, dtype=count).astype(np.int64) != surely

    for s0 in range(0, t, step):
        s1 = min(t, s0 + step)
        if inside_depth is not None:
            deep, undecided = in_band(deep_rows[:, s0:s1], s1 - s0)
            out[s0:s1] = -np.where(can_be_inside[s0:s1], deep, 0)
            unsure[s0:s1] |= undecided & can_be_inside[s0:s1]
        got, undecided = in_band(rows[:, s0:s1], s1 - s0)
        out[s0:s1] += got
        unsure[s0:s1] |= undecided
    if unsure.any():
        again = np.flatnonzero(unsure)
        out[again] = _support_pointwise(xy, ux[again], uy[again], r[again], inlier, inside_depth=inside_depth)
    return out


def _support_pointwise(xy: np.ndarray, ux: np.ndarray, uy: np.ndarray, r: np.ndarray, inlier: float, *,
                       inside_depth: float | None = None) -> np.ndarray:
    """:func:`circle_support` point by point, for the circles it cannot decide from its
    bounds: each point's distance as ``sqrt(dx² + dy²)``, and ``np.hypot`` (several times
    its cost, and within a few ulps of it) for the points within a rounding margin of
    the band's edges (or not finite), as the definition decides them.
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
    if len(xy) < MIN_FIT_POINTS:
        return np.full(2, np.nan), float("nan")
    tried = _circle_trials(xy, trials)  # drawn once: a second search tries the same circles
    centre, r = _fit_tried(tried, inlier, solid=solid)
    if not np.isfinite(r):
        return centre, r
    res = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1]) - r
    res = res[np.abs(res) < NOISE_WINDOW]
    sigma = 1.4826 * _median(np.abs(res - _median(res)))  # a normal sigma per MAD
    band = max(inlier, NOISE_INLIER_SIGMAS * sigma)
    if solid:
        c2, r2 = _refit_in_band(xy, centre, r, band)
    else:  # the same band searches the same circles again: the same circle
        c2, r2 = (centre, r) if band == inlier else _fit_tried(tried, band)
    if not np.isfinite(r2):
        return centre, r
    return c2, float(np.sqrt(max(r2 * r2 - 2.0 * sigma * sigma, 0.25 * r2 * r2)))


def _median(a: np.ndarray) -> float:
    """``np.median`` of the finite (m,) float64 values ``a`` (NaN when empty), without its
    generic machinery: the middle value, or the mean of the two middle ones."""
    m = a.size
    if m == 0:
        return float("nan")
    k = m // 2
    if m % 2:
        return float(np.partition(a, k)[k])
    part = np.partition(a, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2)


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
