"""The part of a block a capture saw: a coarse 2-D occupancy grid of its points.

A tree of an earlier capture that this one does not find is removed only where this
capture saw the ground around it; beyond the area it covered the tree is just unseen.
Each tile reports the 1 m cells its core points fall in (cells on the block's whole-metre
grid, so tiled and untiled runs agree); the block's coverage is their union, with gaps
narrower than a few metres closed (the strip the scanner's own vehicle hides) and then
eroded by the radius around a trunk that must have been seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from pipeline.voxels import cell_index, keyed_cells

#: Side of a coverage cell [m]; whole metres, so cells follow from the block's origin exactly.
CELL = 1


def occupied_cells(xy: np.ndarray, origin_xy) -> np.ndarray:
    """(c, 2) int64: the distinct 1 m cells (``floor`` of the input-CRS coordinates) that
    points fall in.

    Parameters
    ----------
    xy : (n, 2) float64
        Points in the block's local frame [m].
    origin_xy : (2,) float
        The block's local origin (whole metres) in the input CRS.
    """
    if len(xy) == 0:
        return np.zeros((0, 2), np.int64)
    xy = np.asarray(xy, np.float64)
    i, j = (np.floor(xy[:, d]).astype(np.int64) for d in (0, 1))  # column by column: no (n, 2) temporaries
    lo = np.array([i.min(), j.min()])
    span = np.array([i.max(), j.max()]) - lo + 1
    flat = (i - lo[0]) * span[1] + (j - lo[1])
    hit = np.flatnonzero(np.bincount(flat, minlength=int(span[0] * span[1])))
    i, j = np.divmod(hit, span[1])
    return np.c_[i + lo[0], j + lo[1]] + np.round(np.asarray(origin_xy[:2], np.float64)).astype(np.int64)


#: side of a stem cell [m], and the band above the ground that holds stems but neither grass nor most crowns [m]
STEM_CELL = 0.1
STEM_BAND = (0.3, 0.9)
#: points a stem cell needs (a stray outlier point is no stem)
STEM_MIN_POINTS = 3


def stem_cells(xy: np.ndarray, height: np.ndarray, among: np.ndarray, origin_xy) -> np.ndarray:
    """(c, 3) int64: the :data:`STEM_CELL` cells (input CRS) holding points in the
    :data:`STEM_BAND` above the ground, and how many: where a trunk stands. A tree of an
    earlier capture that this one found no trunk for, but whose stem is still there, was
    missed, not cut. Tiles' counts add up (:func:`stems_of`).

    Parameters
    ----------
    xy : (n, 2) float64 — points in the block's local frame [m]
    height : (n,) float64 — their height above the ground [m]
    among : (n,) bool — the points to look at (not ground)
    origin_xy : (2,) float — the block's local origin in the input CRS [m]
    """
    pick = np.flatnonzero(among & (height >= STEM_BAND[0]) & (height < STEM_BAND[1]))
    if not pick.size:
        return np.zeros((0, 3), np.int64)
    xy, origin = np.asarray(xy, np.float64), np.asarray(origin_xy[:2], np.float64)
    i, j = (cell_index(xy[pick, d], -origin[d], STEM_CELL) for d in (0, 1))  # x + o is x - (-o) to the bit
    cells, counts = keyed_cells(i, j, counts=True)
    return np.c_[cells, counts]


def stems_of(parts: list[np.ndarray]) -> np.ndarray:
    """(s, 2) float64: centres (input CRS) of the stem cells of a block, from its tiles'
    :func:`stem_cells` (a cell's counts added over the tiles), those with at least
    :data:`STEM_MIN_POINTS` points."""
    every = np.concatenate([np.asarray(p, np.int64).reshape(-1, 3) for p in parts]) if parts else np.zeros((0, 3), np.int64)
    cells, inv = np.unique(every[:, :2], axis=0, return_inverse=True)
    counts = np.bincount(inv.ravel(), weights=every[:, 2], minlength=len(cells))
    return (cells[counts >= STEM_MIN_POINTS] + 0.5) * STEM_CELL


@dataclass(frozen=True)
class Coverage:
    """Where a capture saw the block well enough to say a tree is gone.

    Attributes
    ----------
    lo : (2,) int64 — the grid's first cell (input CRS, metres)
    seen : (nx, ny) bool — cells whose whole neighbourhood of ``radius`` was seen
    """

    lo: np.ndarray
    seen: np.ndarray

    @classmethod
    def from_cells(cls, cells: np.ndarray, *, close: float = 2.0, radius: float = 1.5) -> Coverage:
        """The coverage of the occupied ``cells`` ((c, 2) int64): holes up to about
        ``2 close`` metres wide filled, then kept only where a disc of ``radius`` [m]
        around a cell is all seen."""
        cells = np.asarray(cells, np.int64).reshape(-1, 2)
        if len(cells) == 0:
            return cls(np.zeros(2, np.int64), np.zeros((0, 0), bool))
        pad = int(np.ceil(close)) + 1
        lo = cells.min(axis=0) - pad
        shape = tuple(cells.max(axis=0) - lo + 1 + pad)
        grid = np.zeros(shape, bool)
        grid[cells[:, 0] - lo[0], cells[:, 1] - lo[1]] = True
        grid = ndimage.binary_closing(grid, structure=_disc(close))
        grid = ndimage.binary_erosion(grid, structure=_disc(radius), border_value=0)
        return cls(lo, grid)

    def covered(self, xy: np.ndarray) -> np.ndarray:
        """(p,) bool: points (input CRS [m]) in the seen part of the block."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        ij = np.floor(xy).astype(np.int64) - self.lo
        inside = np.all((ij >= 0) & (ij < np.array(self.seen.shape)), axis=1)
        out = np.zeros(len(xy), bool)
        out[inside] = self.seen[ij[inside, 0], ij[inside, 1]]
        return out


def _disc(radius: float) -> np.ndarray:
    r = int(np.ceil(radius))
    i, j = np.mgrid[-r : r + 1, -r : r + 1]
    return (i * i + j * j) <= radius * radius + 1e-9
