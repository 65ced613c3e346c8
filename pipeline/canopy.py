"""Rows from the canopy, where the trunks are hidden.

A row whose trunks are all hidden (foliage to the ground, a missed scan pass) still
shows as a strip of canopy across the block. Counting it keeps the rows after it at
their numbers: "row 12" stays row 12 whether or not any trunk of row 11 was found.
The canopy is kept as the occupied cells of a horizontal grid (the points above a
height), which tiles compute on their cores and a merge joins by union.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from pipeline.voxels import cell_index, keyed_cells

#: side of a canopy cell [m]: fine enough to resolve a 1 m hedgerow wall
CELL = 0.25
#: material this high above the ground [m] is canopy (grass and weeds stay lower)
MIN_HEIGHT = 1.0
#: a canopy row is a strip at least this many planting distances long ...
MIN_ROW_SLOTS = 3.0
#: ... covered by canopy over at least this share of its length (a vehicle or a bin is short)
MIN_FILL = 0.6
#: ... at least this dense across, relative to the rows the trunks give ...
MIN_PEAK_RATIO = 0.4
#: ... and at least this thick, relative to them (a fence's wire is one cell thick)
MIN_THICKNESS_RATIO = 0.5
#: the canopy's rows may stand this close, relative to the trunks' rows (two hidden rows
#: in a row); closer peaks are the two sides of one crown wall
MIN_SPACING_RATIO = 0.3


def canopy_cells(xy: np.ndarray, height: np.ndarray, *, cell: float = CELL, min_height: float = MIN_HEIGHT,
                 offset=None, among: np.ndarray | None = None) -> np.ndarray:
    """The grid cells holding canopy.

    Parameters
    ----------
    xy : (n, 2) float64
        Point positions [m] (any frame whose origin is a multiple of ``cell``, so that
        cells of different tiles line up; with ``offset``, once it is added).
    height : (n,) float64
        Height of each point above the ground [m].
    offset : (2,) float64, optional
        Added to the positions first [m] (a block's origin: local points in its frame).
    among : (n,) bool, optional
        The points to look at (default all).

    Returns
    -------
    (c, 2) int64 unique cell indices, ``floor((xy + offset) / cell)``, sorted.
    """
    # Strategy: the canopy points are picked first, and their cells computed column by
    # column: no (n, 2) copies (a boolean pick of rows is several times slower than a
    # gather of each column).
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    keep = np.asarray(height) >= min_height
    if among is not None:
        keep &= among
    idx = np.flatnonzero(keep)
    if not idx.size:
        return np.zeros((0, 2), np.int64)
    # x + off is x - (-off) to the bit: the cells of floor((xy + offset) / cell)
    shift = np.zeros(2) if offset is None else -np.asarray(offset, dtype=np.float64)[:2]
    return keyed_cells(*(cell_index(xy[idx, d], shift[d], cell) for d in (0, 1)))


def unique_cells(cells: np.ndarray) -> np.ndarray:
    """The distinct rows of ``cells`` (c, 2) int64, sorted by x then y: what
    ``np.unique(cells, axis=0)`` gives, from one int64 key per cell instead of a
    sort of row records (several times slower on millions of points).

    Returns
    -------
    (u, 2) int64
    """
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    if cells.shape[0] == 0:
        return cells.copy()
    return keyed_cells(cells[:, 0], cells[:, 1])


def cell_centres(cells: np.ndarray, *, cell: float = CELL, origin=(0.0, 0.0)) -> np.ndarray:
    """(c, 2) float64 centres [m] of ``cells`` in the frame ``origin`` was added to."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    return (cells + 0.5) * cell + np.asarray(origin, dtype=np.float64)[:2]


def canopy_rows(across: np.ndarray, along: np.ndarray, known: np.ndarray, *, row_spacing: float,
                spacing: float, extent: tuple[float, float] | None = None) -> list[tuple[float, float, float]]:
    """Rows the canopy shows beside those the trunks give.

    Parameters
    ----------
    across, along : (c,) float64
        Canopy cell centres in the section's frame: across the rows (curvature taken
        off) and along them [m].
    known : (r,) float64
        Across offsets of the rows the trunks give [m].
    row_spacing : float
        Distance between the rows the trunks give [m] (twice the true one where every
        other row is hidden: the canopy's own is measured here).
    spacing : float
        Planting distance in a row [m].
    extent : (start, end), optional
        Along range of the trees of the known rows [m]: a canopy row reaches at most
        half a row spacing and one planting distance past it at either end (a fence
        around the block runs on into the headlands).

    Returns
    -------
    list of (offset, along_start, along_end) [m], one per canopy row at least half a
    row spacing from every known row, sorted by offset.
    """
    across = np.asarray(across, dtype=np.float64)
    along = np.asarray(along, dtype=np.float64)
    known = np.asarray(known, dtype=np.float64)
    if len(across) == 0 or not len(known) or not (np.isfinite(row_spacing) and row_spacing > 0):
        return []
    step = CELL / 2
    lo = across.min() - 1.0
    counts = np.bincount(((across - lo) / step).astype(np.int64)).astype(float)
    density = gaussian_filter1d(np.r_[counts, np.zeros(int(2.0 / step))], sigma=2.0)
    floor = MIN_PEAK_RATIO * float(np.median(density[np.clip(((known - lo) / step).astype(np.int64), 0, len(density) - 1)]))
    # crowns of neighbouring rows stand at least a quarter of the trunks' row spacing apart
    peaks = _peaks(density, floor, max(1, int(0.25 * row_spacing / step)))
    offsets = lo + (peaks + 0.5) * step
    if len(offsets) > 1:  # the canopy's own row spacing, where every other row (or two) is hidden
        gap = float(np.median(np.diff(offsets)))
        if MIN_SPACING_RATIO * row_spacing <= gap < 0.9 * row_spacing:
            row_spacing = gap
    thick = MIN_THICKNESS_RATIO * float(np.median([_thickness(across, along, off, row_spacing) for off in known]))
    out = []
    for off in offsets:
        if np.abs(known - off).min() < 0.5 * row_spacing:
            continue
        strip = np.abs(across - off) <= 0.25 * row_spacing
        if not strip.any():
            continue
        off = float(np.median(across[strip]))  # the strip's middle, finer than the histogram
        a = _longest_run(_solid(along[strip]), max_gap=spacing)  # stray outliers do not lengthen it
        length = a[-1] - a[0]
        if length < MIN_ROW_SLOTS * spacing:
            continue
        covered = np.unique(np.floor((a - a[0]) / CELL)).size * CELL
        if covered < MIN_FILL * length or _thickness(across, along, off, row_spacing) < thick:
            continue
        overhang = 0.5 * row_spacing + spacing
        if extent is not None and (a[0] < extent[0] - overhang or a[-1] > extent[1] + overhang):
            continue
        out.append((off, float(a[0]), float(a[-1])))
    return out


def _peaks(y: np.ndarray, floor: float, distance: int) -> np.ndarray:
    """Indices of the local maxima of ``y`` at least ``floor`` high, highest first kept
    where two lie closer than ``distance`` samples; sorted."""
    inner = np.flatnonzero((y[1:-1] > y[:-2]) & (y[1:-1] >= y[2:]) & (y[1:-1] >= floor)) + 1
    kept: list[int] = []
    for i in inner[np.argsort(-y[inner], kind="stable")]:
        if all(abs(i - k) >= distance for k in kept):
            kept.append(int(i))
    return np.asarray(sorted(kept), dtype=np.int64)


def _per_step(along: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells across a strip at each of its along steps: (the step of each cell, the count
    of each step)."""
    _, inverse, counts = np.unique(np.floor(along / CELL), return_inverse=True, return_counts=True)
    return inverse, counts


def _solid(along: np.ndarray) -> np.ndarray:
    """Sorted along positions [m] of the strip's cells, less those where the strip is
    under half its median thickness (stray points beyond a crown wall's ends)."""
    inverse, counts = _per_step(along)
    return np.sort(along[counts[inverse] >= 0.5 * np.median(counts)])


def _longest_run(a: np.ndarray, *, max_gap: float) -> np.ndarray:
    """The longest stretch of sorted ``a`` without a gap wider than ``max_gap`` [m]."""
    cuts = np.r_[0, np.flatnonzero(np.diff(a) > max_gap) + 1, len(a)]
    i = int(np.argmax(a[cuts[1:] - 1] - a[cuts[:-1]]))
    return a[cuts[i]:cuts[i + 1]]


def _thickness(across: np.ndarray, along: np.ndarray, off: float, row_spacing: float) -> float:
    """Median thickness [m] across the strip of canopy at ``off``: cells per along step."""
    strip = np.abs(across - off) <= 0.25 * row_spacing
    if not strip.any():
        return 0.0
    return float(np.median(_per_step(along[strip])[1])) * CELL
