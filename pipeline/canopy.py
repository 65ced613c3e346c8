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
from scipy.signal import find_peaks

#: side of a canopy cell [m]: fine enough to resolve a 1 m hedgerow wall
CELL = 0.25
#: material this high above the ground [m] is canopy (grass and weeds stay lower)
MIN_HEIGHT = 1.0
#: a canopy row is a strip at least this many planting distances long ...
MIN_ROW_SLOTS = 3.0
#: ... covered by canopy over at least this share of its length (a vehicle or a bin is short)
MIN_FILL = 0.6
#: ... and at least this dense across, relative to the rows the trunks give
MIN_PEAK_RATIO = 0.4


def canopy_cells(xy: np.ndarray, height: np.ndarray, *, cell: float = CELL, min_height: float = MIN_HEIGHT) -> np.ndarray:
    """The grid cells holding canopy.

    Parameters
    ----------
    xy : (n, 2) float64
        Point positions [m] (any frame whose origin is a multiple of ``cell``, so that
        cells of different tiles line up).
    height : (n,) float64
        Height of each point above the ground [m].

    Returns
    -------
    (c, 2) int64 unique cell indices, ``floor(xy / cell)``, sorted.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    keep = np.asarray(height) >= min_height
    if not keep.any():
        return np.zeros((0, 2), np.int64)
    return np.unique(np.floor(xy[keep] / cell).astype(np.int64), axis=0)


def cell_centres(cells: np.ndarray, *, cell: float = CELL, origin=(0.0, 0.0)) -> np.ndarray:
    """(c, 2) float64 centres [m] of ``cells`` in the frame ``origin`` was added to."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    return (cells + 0.5) * cell + np.asarray(origin, dtype=np.float64)[:2]


def canopy_rows(across: np.ndarray, along: np.ndarray, known: np.ndarray, *, row_spacing: float,
                spacing: float) -> list[tuple[float, float, float]]:
    """Rows the canopy shows beside those the trunks give.

    Parameters
    ----------
    across, along : (c,) float64
        Canopy cell centres in the section's frame: across the rows (curvature taken
        off) and along them [m].
    known : (r,) float64
        Across offsets of the rows the trunks give [m].
    row_spacing : float
        Distance between rows [m].
    spacing : float
        Planting distance in a row [m].

    Returns
    -------
    list of (offset, along_start, along_end) [m], one per canopy row at least half a
    row spacing from every known row, sorted by offset.
    """
    across = np.asarray(across, dtype=np.float64)
    along = np.asarray(along, dtype=np.float64)
    if len(across) == 0 or not len(known) or not (np.isfinite(row_spacing) and row_spacing > 0):
        return []
    step = row_spacing / 20.0
    lo, hi = across.min() - row_spacing, across.max() + row_spacing
    counts = np.bincount(((across - lo) / step).astype(np.int64), minlength=int((hi - lo) / step) + 1).astype(float)
    density = gaussian_filter1d(counts, sigma=2.0)
    at = lambda off: density[np.clip(((np.asarray(off) - lo) / step).astype(np.int64), 0, len(density) - 1)]  # noqa: E731
    floor = MIN_PEAK_RATIO * float(np.median(at(known)))
    peaks, _ = find_peaks(density, height=floor, distance=max(1, int(0.6 * row_spacing / step)))
    out = []
    for pk in peaks:
        off = lo + (pk + 0.5) * step
        if np.abs(np.asarray(known) - off).min() < 0.5 * row_spacing:
            continue
        strip = np.abs(across - off) <= 0.25 * row_spacing
        if not strip.any():
            continue
        a = np.sort(along[strip])
        length = a[-1] - a[0]
        if length < MIN_ROW_SLOTS * spacing:
            continue
        covered = np.unique(np.floor((a - a[0]) / CELL)).size * CELL
        if covered < MIN_FILL * length:
            continue
        out.append((float(off), float(a[0]), float(a[-1])))
    return out
