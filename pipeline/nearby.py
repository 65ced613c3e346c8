"""Points near given positions, found through square cells instead of a k-d tree.

Sorting or marking the points by cell costs a fraction of building a k-d tree over
them, and the few queries of a kernel (one per trunk or post) need no more than a
k-d tree's ball query gives.
"""

from __future__ import annotations

import numpy as np

from pipeline.passes import CACHE_POINTS, indices_where
from pipeline.voxels import column_max, column_min

#: most grid cells of :func:`near_centres` (centres spread wider take the bounding box)
MAX_NEAR_CELLS = 4_000_000


def near_centres(xy: np.ndarray, centres: np.ndarray, reach: float) -> np.ndarray:
    """Indices (sorted) of the points ``xy`` (n, 2) in the grid cells of side ``reach`` [m]
    at and around each of ``centres`` (c, 2): a superset of those within ``reach`` of a
    centre, found without the cost of a k-d tree over all the points."""
    reach = reach * (1 + 1e-6)  # a point within reach is never outside the box or two cells off by rounding
    lo = centres.min(axis=0) - reach
    hi = centres.max(axis=0) + reach
    shape = (np.floor((hi - lo) / reach).astype(np.int64) + 1)
    if shape[0] * shape[1] > MAX_NEAR_CELLS:  # candidates spread over a huge extent: the box alone
        return indices_where(xy.shape[0], lambda s: _box_mask(xy[s], lo, hi))
    grid = np.zeros(shape, bool)
    cell = np.floor((centres - lo) / reach).astype(np.int64)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            grid[np.clip(cell[:, 0] + dx, 0, shape[0] - 1), np.clip(cell[:, 1] + dy, 0, shape[1] - 1)] = True
    # CACHE_POINTS points at a time, whose temporaries stay in the CPU's cache
    found = [np.zeros(0, np.int64)]
    for a in range(0, xy.shape[0], CACHE_POINTS):
        part = xy[a : a + CACHE_POINTS]
        inside = np.flatnonzero(_box_mask(part, lo, hi))
        # (x - lo) / reach >= 0 inside the box: truncation is the floor, without a pass of its own
        ix, iy = (np.minimum(((part[inside, d] - lo[d]) / reach).astype(np.int64), shape[d] - 1) for d in (0, 1))
        found.append(a + inside[grid[ix, iy]])
    return np.concatenate(found)


def _box_mask(xy: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Whether each point of ``xy`` (n, 2) lies in the box from ``lo`` to ``hi`` (2,), edges included."""
    x, y = xy[:, 0], xy[:, 1]
    return (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])


class CellIndex:
    """Points ``xy`` (n, 2) [m] sorted into square cells of side ``reach`` [m], to find
    those within ``reach`` of a position among the 3 x 3 cells around it.

    One sort of cell keys costs a fraction of a k-d tree over the same points, and a
    column query needs no more than a k-d tree's ball query gives.
    """

    def __init__(self, xy: np.ndarray, reach: float) -> None:
        self.xy, self.reach = xy, reach
        self.cell = reach * (1 + 1e-6)  # a point within reach is never two cells off by rounding
        n = xy.shape[0]
        self.lo = column_min(xy) if n else np.zeros(2)
        # a cell's row and column grow with x and y: the highest row is the highest y's
        top = int(((column_max(xy)[1:] - self.lo[1:]) / self.cell).astype(np.int64)[0]) if n else 0
        self.ny = top + 3  # keys of a row of cells never reach the next row's
        key = np.empty(n, np.int64)
        for a in range(0, n, CACHE_POINTS):  # temporaries that stay in the CPU's cache
            # column by column (numpy's passes along rows of two are slow); >= 0: truncation is the floor
            i, j = (((xy[a : a + CACHE_POINTS, d] - self.lo[d]) / self.cell).astype(np.int64) for d in (0, 1))
            i += 1
            i *= self.ny
            i += j
            i += 1
            key[a : a + CACHE_POINTS] = i
        # the same stable order from 16-bit keys where they fit: numpy sorts those by radix
        small = key.size and int(key.max()) < 1 << 16
        self.order = np.argsort(key.astype(np.uint16) if small else key, kind="stable")
        self.key = key[self.order]

    def ball(self, c: np.ndarray) -> np.ndarray:
        """Indices (sorted) of the points within ``reach`` of ``c`` (2,) [m]: those whose
        squared distance, summed as ``scipy.spatial.cKDTree.query_ball_point`` sums it, is
        at most ``reach**2``."""
        i, j = np.floor((np.asarray(c, dtype=np.float64) - self.lo) / self.cell).astype(np.int64)
        # cells i-1..i+1 by j-1..j+1, whose keys are (i + 1 + di) * ny + (j + 1 + dj), dj in -1..1;
        # j clipped to the keys' columns 1..ny-2, so that a range never runs into the next row
        j0, j1 = max(j, 1), min(j + 2, self.ny - 2)
        if j0 > j1:
            return np.zeros(0, np.int64)
        rows = (i + np.arange(3)) * self.ny
        bounds = np.searchsorted(self.key, np.r_[rows + j0, rows + j1 + 1])
        idx = np.concatenate([self.order[a:b] for a, b in zip(bounds[:3], bounds[3:])])
        dx = c[0] - self.xy[idx, 0]
        dy = c[1] - self.xy[idx, 1]
        # nine runs each in order: a merge sort ("stable") takes them as runs
        return np.sort(idx[dx * dx + dy * dy <= self.reach * self.reach], kind="stable")
