"""Trellis posts: straight vertical poles standing in a tree row.

A trellised row (high-density apples, pears) has a post every few trees and at both
row ends, 2.5-4 m tall, with wires along the row. The foliage touches the posts all
the way up, so a post drains crown material to the ground like a trunk: it is taken
for a tree, or it drains more of a crown than the tree's own trunk, which is then
dropped as its satellite. A post differs from a trunk in its shape: a trunk tapers and
splits into scaffolds below about 1 m (a central leader goes on thinner and bends),
while a post keeps one thickness on one vertical axis from the ground to its top, and
ends there (a forest tree's bole goes on into its crown, far above any post). A trunk
whose straight central leader is about as thick as itself can look like a post too,
so by default the posts are kept only in wide rows (:mod:`pipeline.process`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.circles import trunk_circle
from pipeline.nearby import CellIndex, near_centres

# Fixed tuning of the post test (lengths in metres; the tallest post is
# TrunkParams.max_post_height).

#: heights above the ground [m] of the cross-sections that must all show the same circle
POST_HEIGHTS = (0.3, 0.7, 1.2, 1.7, 2.2)
#: above POST_HEIGHTS the column is followed in steps of this [m] to find the post's
#: top, then in steps of POST_FINE_STEP [m]
POST_STEP = 0.5
POST_FINE_STEP = 0.1
#: a column still going on at the tallest post's height is a tree's bole: it is followed
#: with an axis drifting up to POST_FOLLOW_SHIFT [m] per POST_STEP and a radius within
#: POST_FOLLOW_TOL of the post's (a bole leans, tapers and swells at whorls) ...
POST_FOLLOW_SHIFT = 0.08
POST_FOLLOW_TOL = 0.5
#: ... until this many sections in a row show no such circle (one may be sparsely scanned)
POST_FOLLOW_MISSES = 2
#: half the thickness of each cross-section [m]
POST_SLAB = 0.05
#: points at most this far out from the radius found at the lowest section count in the
#: sections above it [m] (the foliage touching the post stays out)
POST_MARGIN = 0.08
#: the circles' centres lie within this of their median [m] (a vertical axis)
POST_MAX_SHIFT = 0.05
#: the circles' radii lie within this share of their median, or POST_MIN_RADIUS_TOL [m]
POST_RADIUS_TOL = 0.3
POST_MIN_RADIUS_TOL = 0.015
#: fewest points in a cross-section
POST_MIN_POINTS = 8
#: RANSAC trials of each section's circle fit: foliage touching the post crowds its
#: sections, and with fewer trials a post could pass or fail by the draw
POST_TRIALS = 1024
#: the lowest section is looked for within this [m] of a candidate
POST_REACH = 0.25


@dataclass(frozen=True)
class Posts:
    """Posts found among candidate positions.

    Attributes
    ----------
    xy : (p, 2) float64 — post axis [m]
    radius : (p,) float64 [m]
    top : (p,) float64 — height above the ground up to which the post was followed [m]
    """

    xy: np.ndarray
    radius: np.ndarray
    top: np.ndarray


def find_posts(
    xyz: np.ndarray,
    height: np.ndarray,
    centres: np.ndarray,
    *,
    max_radius: float,
    max_height: float,
    reach: float = POST_REACH,
    among: np.ndarray | None = None,
) -> Posts:
    """The candidate positions that stand on a trellis post.

    At each candidate, circles (:func:`pipeline.circles.trunk_circle`) are fitted to
    the points in thin horizontal sections at ``POST_HEIGHTS`` above the ground: the
    lowest within ``reach`` of the candidate, the others within the lowest circle's
    radius plus ``POST_MARGIN`` of its centre. A post's circles all lie on one vertical
    axis (centres within ``POST_MAX_SHIFT`` of their median) with one radius (within
    ``POST_RADIUS_TOL`` of the median, at most ``max_radius``). The column is then
    followed upwards while the same circle is found (steps of ``POST_STEP``, then of
    ``POST_FINE_STEP``); a column still found at ``max_height``, on that axis or on
    one drifting as a leaning bole's does (``_Column.goes_on``), is a tree's bole, not a
    post.

    Parameters
    ----------
    xyz : (n, 3) float64 [m]
    height : (n,) float64 — height above the ground [m]
    centres : (c, 2) float64 — candidate positions (contact groups) [m]
    max_radius : float — thickest post [m]; 0 finds none
    max_height : float — tallest post [m]; a column going on to this height is a bole
    reach : float — radius of the lowest section around a candidate [m]
    among : (n,) bool, optional — the points to look at (default all): the same posts as
        the points ``xyz[among]`` would give, without a copy of them all

    Returns
    -------
    Posts (one per candidate that is a post; nearby candidates on one post give one)
    """
    # Strategy: most candidates fail on the sections at POST_HEIGHTS, which hold a few %
    # of a column's points: those points are picked first (slightly wider slabs, then
    # the sections' own test), a grid of them finds each candidate's, and the circles
    # are fitted to them. The whole columns are indexed only once a candidate's
    # sections show a post, to follow it up to its top.
    none = Posts(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    if max_radius <= 0 or centres.shape[0] == 0 or xyz.shape[0] == 0:
        return none
    column_reach = reach + max_radius + POST_MARGIN + POST_FOLLOW_SHIFT
    in_sections, section_of = _section_points(height, among, max_height=max_height)
    low_xy = xyz[in_sections, :2]
    near = near_centres(low_xy, centres, column_reach)  # in input order, as the fits need
    low_xy, low_height, section_of = low_xy[near], height[in_sections[near]], section_of[near]
    sections = CellIndex(low_xy, column_reach)
    columns = None
    found_xy, found_r, found_top = [], [], []
    for c in np.asarray(centres, dtype=np.float64):
        if found_xy and np.min(np.hypot(*(np.asarray(found_xy) - c).T)) <= 2 * max_radius:
            continue  # on a post already found
        # in input order: the circle fits draw their trials by position
        idx = sections.ball(c)
        if np.bincount(section_of[idx], minlength=len(POST_HEIGHTS)).min() < POST_MIN_POINTS:
            continue  # a section without the points of a circle: no post
        post = _axis_at(c, _Column(low_xy[idx], low_height[idx], max_height), max_radius=max_radius, reach=reach)
        if post is None:
            continue
        if columns is None:
            columns = _Columns(xyz, height, centres, column_reach, max_height=max_height, among=among)
        top = _top(columns.at(c), *post)
        if top is not None:
            found_xy.append(post[0])
            found_r.append(post[1])
            found_top.append(top)
    if not found_xy:
        return none
    return Posts(np.asarray(found_xy), np.asarray(found_r), np.asarray(found_top))


def _section_points(height: np.ndarray, among: np.ndarray | None, *, max_height: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (sorted) of the points (among ``among``, up to ``max_height`` [m] as
    :class:`_Columns` keeps them) that a section at one of POST_HEIGHTS takes by its
    height (:meth:`_Column.section`'s own test), and the index in POST_HEIGHTS of each,
    (m,) int64 and (m,) int64."""
    # a slab a micrometre wider each side first (two comparisons a point and section, a
    # superset whatever the rounding; NaN heights in none), then the sections' own test
    # on the few it lets through
    near = np.zeros(height.shape[0], bool)
    slab = np.empty(height.shape[0], bool)
    for at in POST_HEIGHTS:
        np.greater_equal(height, at - POST_SLAB - 1e-6, out=slab)
        slab &= height <= at + POST_SLAB + 1e-6
        near |= slab
    if among is not None:
        near &= among
    idx = np.flatnonzero(near)
    h = height[idx]
    which = np.full(idx.size, -1, np.int64)
    for k, at in enumerate(POST_HEIGHTS):
        which[np.abs(h - at) <= POST_SLAB] = k  # as the sections test them
    keep = (which >= 0) & (h >= POST_HEIGHTS[0] - POST_SLAB) & (h <= max_height + POST_SLAB)
    return idx[keep], which[keep]


class _Columns:
    """The points of every candidate's whole column (heights up to ``max_height``), indexed
    to find one candidate's in input order (:meth:`at`)."""

    def __init__(self, xyz: np.ndarray, height: np.ndarray, centres: np.ndarray, column_reach: float, *,
                 max_height: float, among: np.ndarray | None) -> None:
        near = near_centres(xyz[:, :2], centres, column_reach)
        keep = (height[near] >= POST_HEIGHTS[0] - POST_SLAB) & (height[near] <= max_height + POST_SLAB)
        near = near[keep if among is None else keep & among[near]]  # in input order, as the fits need
        self.xy, self.height, self.max_height = xyz[near, :2], height[near], max_height
        self.index = CellIndex(self.xy, column_reach)

    def at(self, c: np.ndarray) -> _Column:
        """The column around candidate ``c`` (2,) [m]."""
        idx = self.index.ball(c)
        return _Column(self.xy[idx], self.height[idx], self.max_height)


def _axis_at(c: np.ndarray, column: _Column, *, max_radius: float, reach: float) -> tuple[np.ndarray, float] | None:
    """The axis (2,) and radius [m] of the post that the sections at POST_HEIGHTS of the
    ``column`` of candidate ``c`` show (:func:`_one_axis`), or None."""
    c0, r0 = column.section(POST_HEIGHTS[0], c, reach)
    if not 0 < r0 <= max_radius:
        return None
    picks = [column.pick(at, c0, r0 + POST_MARGIN) for at in POST_HEIGHTS[1:]]
    if min(p.size for p in picks) < POST_MIN_POINTS:
        return None  # a section without the points of a circle
    # the highest first: a trunk splits and a leader tapers and branches above the lowest
    # section, so the highest are the likeliest to differ from it (on six generated blocks
    # of bench.rayextract's scenes 4-27 % fewer fits than the fewest points first, whose
    # fits cost about the same at these sizes). The sections that rule a post out do so
    # in any order (:func:`_ruled_out` and :func:`_one_axis` look at the set of circles)
    circles = [(c0, r0)]
    for sel in picks[::-1]:
        circles.append(column.fit(sel))
        if _ruled_out(circles, max_radius):
            break
    return _one_axis(circles, max_radius)


def _top(column: _Column, axis: np.ndarray, r_med: float) -> float | None:
    """The height above the ground [m] up to which the post on ``axis`` with radius
    ``r_med`` [m] stands in its whole ``column``, or None where the column goes on to the
    tallest post's height (a bole going on into a crown)."""
    top = POST_HEIGHTS[-1]
    for step in (POST_STEP, POST_FINE_STEP):  # the post's top: coarse steps up, then fine ones
        while top < column.max_height and _same(*column.section(top + step, axis, r_med + POST_MARGIN), axis, r_med):
            top += step
    if top >= column.max_height or column.goes_on(axis, r_med):
        return None
    return top + POST_FINE_STEP


def _one_axis(circles: list, max_radius: float) -> tuple[np.ndarray, float] | None:
    """The axis (centres' median) and radius (radii's median) of a post whose section
    circles at every one of POST_HEIGHTS are ``circles`` [(centre (2,), radius)], or None:
    a circle missing or not on that axis with that radius (:func:`_same`), or a radius
    over ``max_radius``."""
    if len(circles) < len(POST_HEIGHTS) or not all(np.isfinite(r) for _, r in circles):
        return None
    axis = np.median([cc for cc, _ in circles], axis=0)
    r_med = float(np.median([r for _, r in circles]))
    if r_med > max_radius or not all(_same(cc, r, axis, r_med) for cc, r in circles):
        return None
    return axis, r_med


def _ruled_out(circles: list, max_radius: float) -> bool:
    """Whether the first of a candidate's section circles already make :func:`_one_axis`
    None whatever the others are: one is missing; more than half of the POST_HEIGHTS
    sections' radii are over ``max_radius`` already (so is their median); no median
    radius of at most ``max_radius`` has them all within the tolerance :func:`_same`
    allows around it (:func:`_radius_medians`); or two centres are farther apart than
    twice the shift it allows around one axis. Once more than half of the circles are
    known, the medians lie between two of theirs (:func:`_median_bounds`): the median
    radius, and each coordinate of the axis, must then be one there that holds them all.
    A margin of 1e-9 m keeps rounding on the side of going on."""
    if not all(np.isfinite(r) for _, r in circles):
        return True
    radii = np.array([r for _, r in circles])
    if np.count_nonzero(radii > max_radius) > len(POST_HEIGHTS) // 2:
        return True
    least, most = _radius_medians(float(radii.min()), float(radii.max()))
    low, high = _median_bounds(radii)
    if max(least, low) > min(most, max_radius, high) + 1e-9:
        return True
    centres = np.array([cc for cc, _ in circles])
    apart = np.hypot(*(centres[:, None, :] - centres[None, :, :]).transpose(2, 0, 1))
    if apart.max() > 2 * POST_MAX_SHIFT + 1e-9:
        return True
    for v in centres.T:  # an axis within POST_MAX_SHIFT of each centre, along x and along y
        low, high = _median_bounds(v)
        if max(float(v.max()) - POST_MAX_SHIFT, low) > min(float(v.min()) + POST_MAX_SHIFT, high) + 1e-9:
            return True
    return False


def _median_bounds(known: np.ndarray) -> tuple[float, float]:
    """The least and the greatest value the median of all POST_HEIGHTS sections' values
    can take given the first ``known`` (k,) of them, whatever the others are (infinite
    where those could still set it)."""
    v = np.sort(known)
    mid, unknown = len(POST_HEIGHTS) // 2, len(POST_HEIGHTS) - len(v)
    low = float(v[mid - unknown]) if mid - unknown >= 0 else -np.inf
    high = float(v[mid]) if mid < len(v) else np.inf
    return low, high


def _radius_range_fits(low: float, high: float, max_radius: float) -> bool:
    """Whether some median radius m <= ``max_radius`` has radii ``low`` and ``high`` [m]
    both within ``max(POST_MIN_RADIUS_TOL, POST_RADIUS_TOL * m)`` of it (:func:`_same`)."""
    least, most = _radius_medians(low, high)
    return least <= min(most, max_radius) + 1e-9


def _radius_medians(low: float, high: float) -> tuple[float, float]:
    """The least and the greatest median radius m [m] that has radii ``low`` and ``high``
    [m] both within ``max(POST_MIN_RADIUS_TOL, POST_RADIUS_TOL * m)`` of it (none where
    the first is the greater).

    m + tol(m) and m - tol(m) both grow with m, so ``high`` sets the least such m and
    ``low`` the largest; each piece is linear on either side of the knee where the
    share takes over from the floor."""
    knee = POST_MIN_RADIUS_TOL / POST_RADIUS_TOL
    least = high - POST_MIN_RADIUS_TOL if high <= knee + POST_MIN_RADIUS_TOL else high / (1 + POST_RADIUS_TOL)
    most = low + POST_MIN_RADIUS_TOL if low <= knee - POST_MIN_RADIUS_TOL else low / (1 - POST_RADIUS_TOL)
    return least, most


def _same(centre: np.ndarray, radius: float, axis: np.ndarray, r_med: float) -> bool:
    """A circle on the post's axis (within POST_MAX_SHIFT) with its radius (within
    POST_RADIUS_TOL of ``r_med``, or POST_MIN_RADIUS_TOL)."""
    return bool(
        np.isfinite(radius)
        and np.hypot(*(centre - axis)) <= POST_MAX_SHIFT
        and abs(radius - r_med) <= max(POST_MIN_RADIUS_TOL, POST_RADIUS_TOL * r_med)
    )


class _Column:
    """The points around one candidate: xy (n, 2) [m] and height above the ground (n,) [m],
    followed up to ``max_height`` [m]."""

    def __init__(self, xy: np.ndarray, height: np.ndarray, max_height: float) -> None:
        self.xy, self.height, self.max_height = xy, height, max_height

    def section(self, at: float, centre: np.ndarray, within: float) -> tuple[np.ndarray, float]:
        """The circle through the points within POST_SLAB of height ``at`` and ``within``
        [m] of ``centre``; NaN with fewer than POST_MIN_POINTS points."""
        return self.fit(self.pick(at, centre, within))

    def pick(self, at: float, centre: np.ndarray, within: float) -> np.ndarray:
        """The points (indices, in input order) of :meth:`section`."""
        sel = np.flatnonzero(np.abs(self.height - at) <= POST_SLAB)  # the slab first: a few of the column's points
        return sel[((self.xy[sel] - centre) ** 2).sum(1) <= within**2]

    def fit(self, sel: np.ndarray) -> tuple[np.ndarray, float]:
        """The circle of :meth:`section` through the points ``sel`` (:meth:`pick`)."""
        if sel.size < POST_MIN_POINTS:
            return np.full(2, np.nan), float("nan")
        return trunk_circle(self.xy[sel], trials=POST_TRIALS, solid=False)  # the fit its thresholds were set on

    def goes_on(self, axis: np.ndarray, radius: float) -> bool:
        """The column above POST_HEIGHTS goes on to ``max_height``: a tree's bole.

        Followed in steps of POST_STEP, each section centred on the last circle found
        (a bole leans: its axis drifts up to POST_FOLLOW_SHIFT per step) with a radius
        within POST_FOLLOW_TOL of ``radius`` (a bole tapers and swells at whorls), until
        POST_FOLLOW_MISSES sections in a row show no such circle.
        """
        at, centre, missed = POST_HEIGHTS[-1], axis, 0
        while at < self.max_height:
            at += POST_STEP
            c, r = self.section(at, centre, radius + POST_MARGIN + POST_FOLLOW_SHIFT)
            if (np.isfinite(r) and abs(r - radius) <= POST_FOLLOW_TOL * radius
                    and np.hypot(*(c - centre)) <= POST_FOLLOW_SHIFT):
                centre, missed = c, 0
            else:
                missed += 1
                if missed == POST_FOLLOW_MISSES:
                    return False
        return True


def on_posts(xyz: np.ndarray, height: np.ndarray, posts: Posts, *, margin: float) -> np.ndarray:
    """Points (or graph nodes) on a post: within its radius plus ``margin`` [m] of its
    axis and at most its top above the ground, (n,) bool. With a node-sized margin the
    nodes to cut out of the graph; with a noise-sized one the points that are the post
    itself (the rest of a post's voxels is foliage touching it)."""
    out = np.zeros(xyz.shape[0], bool)
    for xy, r, top in zip(posts.xy, posts.radius, posts.top):
        out |= (((xyz[:, :2] - xy) ** 2).sum(1) <= (r + margin) ** 2) & (height <= top)
    return out
