"""Orchard rows from tree positions: row lines, tree addresses, empty slots, replants.

Growers address trees as "row 12, tree 37". This module turns the merged trunk
positions of a block into that address book. It works on trunk positions (and tree
heights) only, after the tiles are merged, so a tiled run and an untiled run that find
the same trunks get the same addresses.

Numbering rule (documented in docs/rows.md):

- A block may hold several *sections* of different row direction; each section's rows
  run along one direction ``u``. Rows that run closer to north–south than to east–west
  are numbered from west to east, their positions from south to north; rows closer to
  east–west are numbered from south to north, their positions from west to east.
  Sections are numbered in the same order as their rows' centres, so a file with two
  blocks numbers the rows of the first section, then those of the second.
- ``position`` counts planting slots along the row from its first tree (position 1):
  an empty slot between two trees keeps its number, and the tree after it keeps its
  own. An empty slot at a row's end cannot be told from the row's end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pipeline.canopy import canopy_rows
from pipeline.params import RowParams
from pipeline.rowlinks import (
    band_count,
    banded_direction,
    chain_spacing,
    chains_of,
    link_trees,
    linked_directions,
    local_directions,
    measured_row_spacing,
    nearest_along,
    row_sections,
    section_direction,
)
from pipeline.rowslots import row_slots, row_steps, slot_centres

#: neighbours whose smoothed direction defines a tree's local row direction: enough to
#: outvote the few trees whose nearest neighbour lies across the row
_DIRECTION_NEIGHBOURS = 12
#: an off-row trunk this many row spacings beyond an outer row is no row of its own yet
_OUTER_REACH = 0.5
#: ... and stands between rows only where the off-row limit lies this many standard
#: deviations of the trees' scatter about their row lines out (the usual outlier rule);
#: the scatter's standard deviation from the median absolute offset
_OUTLIER_SIGMAS = 3.0
_MAD_SIGMA = 1.4826
#: rounds of reading the row directions off the links found (:func:`_along_links`)
_LINK_ROUNDS = 2
#: a row's trees lie within a band this fraction of the typical distance to a tree's
#: nearest tree wide (:func:`_straight_rows`) ...
_BAND_WIDTH = 0.2
#: ... and the rows are read again along the fewest such bands unless at least this share
#: of a section's trees have their nearest tree along the rows read (a block whose rows
#: keep most of their trees: the nearest tree decides)
_NEAREST_ALONG = 0.8
#: steps between a row's trees are whole numbers of its planting distance within this
#: fraction of it (a tree hand-planted off its slot)...
_WHOLE_SLOTS = 0.25
#: the median step is the planting distance where this share of the steps are whole numbers of it ...
_MEDIAN_WHOLE_SHARE = 0.5
#: ... and it is at most this many times the typical distance to a tree's nearest tree (one
#: slot, within _WHOLE_SLOTS) ...
_MEDIAN_NEAREST = 1.25
#: ... else the largest step of which this share are
_WHOLE_SHARE = 0.9
#: the planting distance is looked for among this many quantiles of the steps (and their halves and thirds)
_SPACING_CANDIDATES = 41


@dataclass(frozen=True)
class RowLayout:
    """Rows of a block and every tree's address.

    Attributes
    ----------
    row, position : (k,) int32
        1-based row number and planting-slot position of each tree.
    young : (k,) bool
        A replant: much lower than its row neighbours.
    rows : dict of str → ndarray
        One entry per row: ``row`` (int32), ``n_trees``, ``n_gaps`` (int32),
        ``spacing_m``, ``length_m``, ``azimuth_deg`` (float64; azimuth of increasing
        positions, clockwise from grid north, [0, 360)).
    lines : list of (m, 2) float64
        Each row's line through its trees' positions, in position order [m].
    gaps : dict of str → ndarray
        One entry per empty slot between two trees of a row: ``row``, ``position``
        (int32), ``x``, ``y`` (float64, the slot's centre, :func:`pipeline.rowslots.slot_centres`) [m].
    off_row : (k,) bool
        Trees off every row line, or a second tree in an occupied slot; each is a row of
        its own, numbered after the rows.
    between_rows : (k,) bool
        Those off-row trees that stand between two rows, or less than half a row spacing
        beyond an outer row, within the rows' extent: more likely a false trunk (foliage
        or a weed touching down) than a tree.
    """

    row: np.ndarray
    position: np.ndarray
    young: np.ndarray
    rows: dict
    lines: list
    gaps: dict
    off_row: np.ndarray
    between_rows: np.ndarray


def _section_rows(local, direction, members, u, v, spacing, params, canopy=None, links=None):
    """Rows of one section of the block.

    Strategy: trees linked into chains (:func:`pipeline.rowlinks.link_trees`) give the rows' course; the
    curvature common to the section's rows (across offset quadratic in the along
    coordinate, fitted to every chain of three or more trees at once) is taken off, so
    that each row is one across offset. Chains of three or more trees, and shorter ones
    half a row spacing from all of those, are rows; those whose offsets lie within half
    the lateral tolerance of each other are one row (fragments on both sides of a run of
    empty slots). A tree off its row stands between rows only where the rows are
    evident: the off-row limit is an outlier of the trees' scatter about their lines. Strips of ``canopy`` (cell centres, local frame) half a row spacing
    from all of those are rows whose trunks are hidden (:mod:`pipeline.canopy`). Every
    tree goes to its nearest row, unless it lies farther from it than
    ``params.max_offset`` times the distance between rows.

    Returns
    -------
    rows : list of (offset, (n,) int64 tree indices in order along the row, line): the
        line (local frame) only for a canopy row without trees, else None
    off : (o,) int64 — trees off every row
    between : (b,) int64 — those of them between two rows, within the rows' extent
    spacing : float — the typical step between neighbours in a row [m]
    """
    p = local[members]
    succ, pred, across, tol = links or _links(local, direction, members, u, spacing, params)
    chains = chains_of(succ, pred)
    steps = [row_steps(p[c], direction[members][c]) for c in chains if len(c) > 1]
    if steps:
        spacing = _planting_distance(np.concatenate(steps), spacing)
    a, c = p @ u, p @ v
    long = [ch for ch in chains if len(ch) >= 3]
    bow = _Bow.fit(a, c, long)
    flat = bow.flatten(a, c)
    centres = _row_centres(flat, chains, long, across, tol)
    shown = []
    if canopy is not None and len(canopy) and np.isfinite(across):
        shown = canopy_rows(bow.flatten(canopy @ u, canopy @ v), canopy @ u, centres,
                            row_spacing=across, spacing=spacing, extent=(float(a.min()), float(a.max())))
        centres = np.sort(np.r_[centres, [off for off, _, _ in shown]])
    nearest = np.abs(flat[:, None] - centres[None, :]).argmin(axis=1)
    dist = np.abs(flat - centres[nearest])
    on = dist <= params.max_offset * across if np.isfinite(across) else np.ones(len(p), dtype=bool)
    rows = _assigned_rows(centres, nearest, on, a, members, shown, bow, u, v)
    inside = _between_rows(flat, centres, dist, on, a, across, spacing, params)
    return rows, members[~on], members[~on & inside], spacing


def _planting_distance(steps: np.ndarray, nearest: float = float("inf")) -> float:
    """The planting distance [m] of rows whose steps between neighbouring trees are
    ``steps`` [m]: their median, unless most steps are not whole numbers of it
    (:func:`_whole`) or it is far longer than ``nearest``, the typical distance from a
    tree to its nearest tree [m]; then the largest step of which nearly all are (a step,
    a half or a third of one), read again as the median of the steps divided by their
    slots.

    A row that keeps four trees of six steps one and two slots in about equal
    numbers, and the median of such steps is no slot at all (7.5 m in 5 m rows). A
    median most steps are whole numbers of stands: false trunks half a slot from a
    tree (a trellis post) must not halve the planting distance. In rows half replanted
    most steps can be two slots (5 m rows keeping trees 10 m apart, and a tree 6 m
    across): a median :data:`_MEDIAN_NEAREST` times the nearest tree's distance is no
    planting distance."""
    spacing = float(np.median(steps))
    if _whole(steps, spacing).mean() >= _MEDIAN_WHOLE_SHARE and spacing <= _MEDIAN_NEAREST * nearest:
        return spacing
    quantiles = np.quantile(steps, np.linspace(0.0, 1.0, _SPACING_CANDIDATES))
    for cand in np.sort(np.concatenate([quantiles / n for n in (1, 2, 3)]))[::-1]:
        whole = _whole(steps, cand)
        if whole.mean() >= _WHOLE_SHARE:
            return float(np.median(steps[whole] / np.maximum(1.0, np.rint(steps[whole] / cand))))
    return spacing


def _whole(steps: np.ndarray, spacing: float) -> np.ndarray:
    """(n,) bool: which ``steps`` [m] are a whole number (one or more) of ``spacing`` [m],
    within :data:`_WHOLE_SLOTS` of it."""
    ratio = steps / spacing
    return np.abs(ratio - np.maximum(1.0, np.rint(ratio))) <= _WHOLE_SLOTS


def _links(local, direction, members, u, spacing, params, across=None) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Each member's successor and predecessor along its row (:func:`pipeline.rowlinks.link_trees`),
    the distance between rows [m] (NaN: one row; measured unless given) and the lateral
    tolerance of a link [m]."""
    p = local[members]
    if across is None or not np.isfinite(across):
        across = measured_row_spacing(p, direction[members], cKDTree(p))
    tol = params.lateral_tolerance * across if np.isfinite(across) else max(spacing, 0.5)
    succ, pred = link_trees(local, direction, u, members, spacing, tol, params.max_gap_slots)
    if not np.isfinite(across):
        # no tree has a tree straight across the row (a row half replanted keeps its trees in
        # other slots than the next row): the distance between the lines of the chains found
        across = chain_spacing(p, chains_of(succ, pred), u, _BAND_WIDTH * spacing)
        if np.isfinite(across):
            tol = params.lateral_tolerance * across
            succ, pred = link_trees(local, direction, u, members, spacing, tol, params.max_gap_slots)
    return succ, pred, across, tol


def _along_links(local, direction, near, members, spacing, params) -> tuple[np.ndarray, tuple]:
    """``direction`` with the section's row directions read off the links they give
    (:func:`pipeline.rowlinks.linked_directions`) while that links more of its trees,
    and its links (:func:`_links`, along the section's direction).

    A row with empty slots has its nearest trees across the row at the gaps, and the
    directions lean across (a vase block whose rows keep four trees of six, 6 m apart
    across and 10 m along: 9-10 degrees), so far that a link over a gap falls outside the
    lateral tolerance; the links found lie along the rows. The reading that links more
    trees is the one that explains more of the block: more trees per row."""
    links = _links(local, direction, members, section_direction(direction[members]), spacing, params)
    for _ in range(_LINK_ROUNDS):
        again = linked_directions(local, near, members, links[0], direction)
        more = _links(local, again, members, section_direction(again[members]), spacing, params)
        if (more[0] >= 0).sum() <= (links[0] >= 0).sum():
            break
        direction, links = again, more
    return direction, links


def _straight_rows(local, direction, members, spacing, params, links) -> tuple[np.ndarray, tuple]:
    """``direction`` and ``links`` (:func:`_along_links`), or the section read along the
    direction in which its trees stand in the fewest straight lines
    (:func:`pipeline.rowlinks.banded_direction`) where that gives fewer lines and the
    nearest trees do not decide.

    On a block half replanted the grown trees stand one to three slots apart in their
    rows, and a tree's nearest tree lies as often across the rows as along them: the
    directions read off them (and off the links they give) can point anywhere (a vase
    block of two rows of six slots, three grown trees left in each). Rows are straight
    lines of trees: the fewest lines ``_BAND_WIDTH`` of ``spacing`` (the typical
    distance to a tree's nearest tree) wide that hold all trees run along the rows
    where the rows hold more trees than any line across them. Where most trees'
    nearest tree lies along the rows read (:data:`_NEAREST_ALONG`), those are the rows
    (a block of more rows than trees in a row has more trees in a line across).
    """
    p = local[members]
    now = section_direction(direction[members])
    if nearest_along(p, now) >= _NEAREST_ALONG:
        return direction, links
    width = _BAND_WIDTH * spacing
    u, n, across = banded_direction(p, width)
    if n >= band_count(p, now, width):
        return direction, links
    along = direction.copy()
    along[members] = u
    return along, _links(local, along, members, section_direction(along[members]), spacing, params, across)


@dataclass(frozen=True)
class _Bow:
    """The curvature common to a section's rows: the across offset (local frame) a
    quadratic in ``t``, the along coordinate centred on ``mean`` and divided by ``scale``."""

    mean: float
    scale: float
    curve: np.ndarray  # (2,) coefficients of t and t**2 [m]

    @classmethod
    def fit(cls, a: np.ndarray, c: np.ndarray, long: list[np.ndarray]) -> _Bow:
        """Fitted to every chain of ``long`` at once (each about its own mean): none
        without six trees in such chains. ``a``, ``c`` are the trees' along and across
        coordinates [m]."""
        mean, scale = a.mean(), max(float(np.ptp(a)), 1.0)
        t = (a - mean) / scale
        curve = np.zeros(2)
        if sum(len(ch) for ch in long) >= 6:
            x = np.concatenate([np.c_[t[ch] - t[ch].mean(), t[ch] ** 2 - (t[ch] ** 2).mean()] for ch in long])
            y = np.concatenate([c[ch] - c[ch].mean() for ch in long])
            curve = np.linalg.lstsq(x, y, rcond=None)[0]
        return cls(mean, scale, curve)

    def flatten(self, along: np.ndarray, across: np.ndarray) -> np.ndarray:
        """Across offsets with the curvature taken off [m]."""
        t = (along - self.mean) / self.scale
        return across - self.curve[0] * t - self.curve[1] * t**2

    def line(self, along: np.ndarray, offset: float) -> np.ndarray:
        """Across coordinates [m] of the row of flattened ``offset`` at ``along``."""
        t = (along - self.mean) / self.scale
        return offset + self.curve[0] * t + self.curve[1] * t**2


def _row_centres(flat: np.ndarray, chains: list[np.ndarray], long: list[np.ndarray], across: float,
                 tol: float) -> np.ndarray:
    """Flattened across offsets [m] of the section's rows, ascending: chains of three or
    more trees and shorter ones of their own, merged within half ``tol``."""
    seeds = list(long)
    if long and np.isfinite(across):  # a short row of its own lies half a row spacing from every long one
        known = np.array([np.median(flat[ch]) for ch in long])
        seeds += [ch for ch in chains if len(ch) < 3 and np.abs(known - np.median(flat[ch])).min() > 0.5 * across]
    elif not long:
        seeds = chains
    offs = np.array([np.median(flat[ch]) for ch in seeds])
    weight = np.array([len(ch) for ch in seeds], dtype=np.float64)
    order = np.argsort(offs)
    offs, weight = offs[order], weight[order]
    merge = 0.5 * tol if np.isfinite(across) else np.inf
    cut = np.r_[0, np.flatnonzero(np.diff(offs) > merge) + 1, len(offs)]
    return np.array([np.average(offs[i:j], weights=weight[i:j]) for i, j in zip(cut[:-1], cut[1:])])


def _assigned_rows(centres, nearest, on, a, members, shown, bow: _Bow, u, v) -> list:
    """:func:`_section_rows`' rows: each row's trees in order along it, or a line along its
    strip for a canopy row without trees."""
    rows = []
    strips = {off: (start, end) for off, start, end in shown}
    for r, centre in enumerate(centres):
        sel = np.flatnonzero(on & (nearest == r))
        if len(sel):
            rows.append((float(centre), members[sel[np.argsort(a[sel], kind="stable")]], None))
        elif centre in strips:  # the canopy's row, its trunks all hidden: a line along its strip
            along = np.linspace(*strips[centre], 5)
            across_c = bow.line(along, centre)
            rows.append((float(centre), np.zeros(0, np.int64), along[:, None] * u + across_c[:, None] * v))
    return rows


def _between_rows(flat, centres, dist, on, a, across: float, spacing: float, params) -> np.ndarray:
    """(n,) bool: whether each tree lies between the rows (or beside an outer one) and
    within their extent, where the rows are evident enough for a tree off them to be
    an outlier."""
    # between two rows, or beside an outer row nearer than an unseen next row could stand
    reach = _OUTER_REACH * across if np.isfinite(across) and len(centres) > 1 else 0.0
    inside = (flat > centres.min() - reach) & (flat < centres.max() + reach)
    if len(dist) >= 3 and np.isfinite(across):
        # a block has rows where a tree off its row line is an outlier of the trees' scatter
        # about their lines (a robust scatter: the few false trunks in the alleys do not
        # move it): in a stand planted loosely, or not in rows, it is a tree
        scatter = _MAD_SIGMA * float(np.median(dist))
        inside &= params.max_offset * across >= _OUTLIER_SIGMAS * scatter
    if on.any():
        inside &= (a >= a[on].min() - spacing) & (a <= a[on].max() + spacing)
    return inside


def _young(height: np.ndarray, chains: list[np.ndarray], ratio: float) -> np.ndarray:
    young = np.zeros(len(height), dtype=bool)
    for chain in chains:
        if len(chain) < 3:
            continue
        h = height[chain]
        for a in range(len(chain)):
            nb = np.r_[h[max(0, a - 2):a], h[a + 1:a + 3]]
            if len(nb) and h[a] < ratio * np.median(nb):
                young[chain[a]] = True
    return young


def _azimuth(v: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(v[0], v[1])) % 360.0)


def find_rows(xy: np.ndarray, height: np.ndarray | None = None, *, params: RowParams | None = None,
              canopy: np.ndarray | None = None) -> RowLayout:
    """Find the rows of a block and give every tree its address.

    Parameters
    ----------
    xy : (k, 2) float64
        Trunk positions [m] in a projected CRS (x east, y north).
    height : (k,) float64, optional
        Tree heights [m], for telling replants (``young``); without, no tree is young.
    params : RowParams, optional
    canopy : (c, 2) float64, optional
        Canopy cell centres [m] in the frame of ``xy`` (:func:`pipeline.canopy.canopy_cells`):
        a strip of canopy between or beside the rows the trunks give is a row whose
        trunks are hidden, numbered with the others (``n_trees`` 0).

    Returns
    -------
    RowLayout
        Addresses are unique: no two trees share a (row, position).
    """
    # Strategy: each tree's local row direction groups the trees into sections of one
    # direction; each section's trees are linked into rows and slots; then every row is
    # numbered across the block and its empty slots listed.
    params = params or RowParams()
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    k = len(xy)
    height = np.zeros(k) if height is None else np.asarray(height, dtype=np.float64)
    if k < 2:
        return _few_trees(xy)
    found, off_row, between_rows = _found_rows(xy, params, canopy)
    return _numbered(xy, height, found, off_row, between_rows, params)


def _empty_rows() -> dict:
    return {"row": np.zeros(0, np.int32), "n_trees": np.zeros(0, np.int32), "n_gaps": np.zeros(0, np.int32),
            "spacing_m": np.zeros(0), "length_m": np.zeros(0), "azimuth_deg": np.zeros(0)}


def _empty_gaps() -> dict:
    return {"row": np.zeros(0, np.int32), "position": np.zeros(0, np.int32), "x": np.zeros(0), "y": np.zeros(0)}


def _few_trees(xy: np.ndarray) -> RowLayout:
    """The layout of a block of no tree or one (a row of its own)."""
    k = len(xy)
    if k == 0:
        return RowLayout(np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, bool), _empty_rows(), [], _empty_gaps(),
                         np.zeros(0, bool), np.zeros(0, bool))
    rows = dict(_empty_rows(), row=np.array([1], np.int32), n_trees=np.array([1], np.int32),
                n_gaps=np.array([0], np.int32), spacing_m=np.array([np.nan]), length_m=np.array([0.0]),
                azimuth_deg=np.array([np.nan]))
    return RowLayout(np.ones(1, np.int32), np.ones(1, np.int32), np.zeros(1, bool), rows, [xy.copy()], _empty_gaps(),
                     np.zeros(1, bool), np.zeros(1, bool))


def _found_rows(xy: np.ndarray, params: RowParams, canopy: np.ndarray | None) -> tuple[list, np.ndarray, np.ndarray]:
    """The rows of every section of the block (at least two trees), unnumbered.

    Returns
    -------
    found : list of (section key, across offset, (n,) int64 trees in order along the
        row, (n,) int64 their slots, the row's spacing [m], the canopy's line (m, 2) [m]
        for a row whose trunks are all hidden, else None); trees off every row last, one
        row each
    off_row, between_rows : (k,) bool — as in :class:`RowLayout`
    """
    k = len(xy)
    centre = xy.mean(axis=0)
    local = xy - centre
    m = min(k, _DIRECTION_NEIGHBOURS)
    tree = cKDTree(local)
    dist, near = tree.query(local, k=m)
    direction = local_directions(local, near.reshape(k, m))
    section = row_sections(local, direction, params.max_section_angle)
    nn_dist = dist.reshape(k, m)[:, 1]
    if canopy is not None and len(canopy):  # each canopy cell goes with its nearest tree's section
        can_local = np.asarray(canopy, dtype=np.float64).reshape(-1, 2) - centre
        can_section = section[tree.query(can_local)[1]]

    found = []  # per row: (section key, across offset, trees in order along the row, slots, spacing, line)
    off_row = np.zeros(k, dtype=bool)
    between_rows = np.zeros(k, dtype=bool)
    for sec in np.unique(section):
        members = np.flatnonzero(section == sec)
        sec_key = tuple(np.round(local[members].mean(axis=0), 3))
        links = None
        if len(members) > 2:
            direction, links = _along_links(local, direction, near.reshape(k, m), members,
                                            float(np.median(nn_dist[members])), params)
            direction, links = _straight_rows(local, direction, members, float(np.median(nn_dist[members])),
                                              params, links)
        u = section_direction(direction[members]) if len(members) > 1 else np.array([1.0, 0.0])
        v = np.array([u[1], -u[0]]) if abs(u[1]) > abs(u[0]) else np.array([-u[1], u[0]])  # numbering: east or north
        sec_canopy = can_local[can_section == sec] if canopy is not None and len(canopy) else None
        rows_here, off, between, spacing = _section_rows(local, direction, members, u, v, float(np.median(nn_dist[members])),
                                                         params, sec_canopy, links)
        off_row[off] = True
        between_rows[between] = True
        for offset, g, line in rows_here:
            if line is not None:  # trunks hidden: the canopy's line
                found.append((sec_key, offset, g, np.zeros(0, np.int64), float("nan"), line + centre))
                continue
            slots, s, keep = row_slots(local[g], direction[g], spacing)
            off_row[g[~keep]] = True  # a second tree in an occupied slot
            found.append((sec_key, offset, g[keep], slots[keep], s, None))
    for i in np.flatnonzero(off_row):  # off every row line: one row each, after the rows
        found.append(((np.inf,), float(xy[i, 0]), np.array([i]), np.zeros(1, np.int64), float("nan"), None))
    return found, off_row, between_rows


def _numbered(xy: np.ndarray, height: np.ndarray, found: list, off_row: np.ndarray, between_rows: np.ndarray,
              params: RowParams) -> RowLayout:
    """The layout of the rows ``found`` (:func:`_found_rows`): rows numbered sections
    west to east (then south to north) and across each section, every tree's address,
    each row's line and measures, and the empty slots between its trees."""
    k = len(xy)
    row = np.zeros(k, dtype=np.int32)
    position = np.zeros(k, dtype=np.int32)
    empty_rows, empty_gaps = _empty_rows(), _empty_gaps()
    order = sorted(range(len(found)), key=lambda a: (found[a][0], found[a][1]))
    chains = []
    rows_out = {key: [] for key in empty_rows}
    lines = []
    gaps = {key: [] for key in empty_gaps}
    for number, a in enumerate(order, start=1):
        _, _, g, slots, s, canopy_line = found[a]
        if canopy_line is not None:  # along the section's direction: the way positions run
            lines.append(canopy_line)
            rows_out["row"].append(number)
            rows_out["n_trees"].append(0)
            rows_out["n_gaps"].append(0)
            rows_out["spacing_m"].append(np.nan)
            rows_out["length_m"].append(float(np.hypot(*np.diff(canopy_line, axis=0).T).sum()))
            rows_out["azimuth_deg"].append(_azimuth(canopy_line[-1] - canopy_line[0]))
            continue
        slots = slots - slots[0]
        row[g] = number
        position[g] = slots + 1
        chains.append(g)
        line = xy[g]
        lines.append(line.copy())
        missing = np.setdiff1d(np.arange(slots[-1] + 1), slots)
        # a run of more empty slots than max_gap_slots is no planting (a road, a headland)
        nxt = np.searchsorted(slots, missing)
        missing = missing[slots[nxt] - slots[nxt - 1] <= params.max_gap_slots]
        if len(missing):
            gaps["row"].append(np.full(len(missing), number, np.int32))
            gaps["position"].append((missing + 1).astype(np.int32))
            centre = slot_centres(slots, line, missing, s)
            gaps["x"].append(centre[:, 0])
            gaps["y"].append(centre[:, 1])
        rows_out["row"].append(number)
        rows_out["n_trees"].append(len(g))
        rows_out["n_gaps"].append(len(missing))
        rows_out["spacing_m"].append(s if len(g) > 1 else np.nan)
        rows_out["length_m"].append(float(np.hypot(*np.diff(line, axis=0).T).sum()) if len(g) > 1 else 0.0)
        rows_out["azimuth_deg"].append(_azimuth(line[-1] - line[0]) if len(g) > 1 else np.nan)
    young = _young(height, chains, params.young_ratio)
    rows = {
        "row": np.asarray(rows_out["row"], np.int32),
        "n_trees": np.asarray(rows_out["n_trees"], np.int32),
        "n_gaps": np.asarray(rows_out["n_gaps"], np.int32),
        "spacing_m": np.asarray(rows_out["spacing_m"], np.float64),
        "length_m": np.asarray(rows_out["length_m"], np.float64),
        "azimuth_deg": np.asarray(rows_out["azimuth_deg"], np.float64),
    }
    gap_cols = {key: (np.concatenate(val) if val else empty_gaps[key]) for key, val in gaps.items()}
    return RowLayout(row, position, young, rows, lines, gap_cols, off_row, between_rows)
