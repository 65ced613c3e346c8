"""Bilinear interpolation of a raster at points, bit for bit as scipy's
``map_coordinates(order=1, mode="nearest")`` and without its per-point loop (the ground
model's heights; :mod:`pipeline.ground`)."""

from __future__ import annotations

import numpy as np

#: points interpolated at a time by :func:`bilinear` (its temporaries stay in cache)
BILINEAR_CHUNK = 1 << 14
#: :func:`bilinear` gathers a point's four values from a table of each cell's corners
#: when it has at least this many points per cell of the grid (fewer: the table would
#: cost more than the gathers it saves)
BILINEAR_TABLE_POINTS = 0.25


def bilinear(grid: np.ndarray, xy: np.ndarray, origin: np.ndarray, cell: float) -> np.ndarray:
    """Values of ``grid`` (nx, ny), whose cell (0, 0) has its corner at ``origin`` (2,)
    [m] and cells of side ``cell`` [m], at the points ``xy`` (n, 2) [m]: bilinear between
    cell centres, the edge cells' values beyond them, (n,) float64.

    Bit for bit ``scipy.ndimage.map_coordinates(grid, g, order=1, mode="nearest")`` at
    grid coordinates ``g = (xy - origin) / cell - 0.5``: its weights (1 - f and
    1 - (1 - f) for the fraction f), indices clipped to the grid, and sum
    ((v * wx) * wy, corner by corner, from 0.0), without its per-point loop over a
    generic filter.
    """
    # Strategy: with many points a cell, the grid padded by its edge values gives each
    # cell's four corners as one column of a table (a cell index clipped to one past
    # the edges picks the clipped corners), so a point's four values are one gather of
    # one index; with few, each corner is gathered from the grid by its clipped indices.
    nx, ny = grid.shape
    n = xy.shape[0]
    out = np.empty(n)
    table = None
    if n >= BILINEAR_TABLE_POINTS * grid.size:
        p = np.pad(grid, 1, mode="edge")  # p[i + 1, j + 1] = grid[clip(i), clip(j)]
        table = np.stack([p[:-1, :-1], p[:-1, 1:], p[1:, :-1], p[1:, 1:]]).reshape(4, -1)  # a corner a row
    flat = grid.ravel()
    with np.errstate(invalid="ignore"):  # NaN coordinates: any index, NaN weights and value
        for s in range(0, n, BILINEAR_CHUNK):
            e = min(n, s + BILINEAR_CHUNK)
            t = out[s:e]
            if table is not None:
                x0, wx0, wx1 = _axis_cell(xy[s:e, 0], origin[0], cell, nx)
                y0, wy0, wy1 = _axis_cell(xy[s:e, 1], origin[1], cell, ny)
                x0 *= ny + 1
                x0 += y0
                x0 += ny + 2  # the padded table's row of cell (-1, -1) is row 0
                v = table.take(x0, axis=1)  # (4, m): each corner's values contiguous
                corners = ((v[1], wx0, wy1), (v[2], wx1, wy0), (v[3], wx1, wy1))
                np.multiply(v[0], wx0, out=t)
            else:
                x0, x1, wx0, wx1 = _axis_weights(xy[s:e, 0], origin[0], cell, nx)
                y0, y1, wy0, wy1 = _axis_weights(xy[s:e, 1], origin[1], cell, ny)
                x0 *= ny
                x1 *= ny
                corners = ((flat[x0 + y1], wx0, wy1), (flat[x1 + y0], wx1, wy0), (flat[x1 + y1], wx1, wy1))
                np.multiply(flat[x0 + y0], wx0, out=t)
            t *= wy0
            t += 0.0
            for v, wx, wy in corners:
                v *= wx  # a gathered copy
                v *= wy
                t += v
    return out


def _axis_fraction(v: np.ndarray, origin: float, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along one axis of :func:`bilinear`: the grid coordinate's floor (m,) intp and the
    two cells' weights (m,) float64."""
    c = np.subtract(v, origin)
    np.divide(c, cell, out=c)
    np.subtract(c, 0.5, out=c)
    f = np.floor(c)
    w0 = np.subtract(c, f, out=c)
    np.subtract(1.0, w0, out=w0)
    w1 = 1.0 - w0
    return f.astype(np.intp), w0, w1


def _axis_weights(v: np.ndarray, origin: float, cell: float, size: int) -> tuple[np.ndarray, ...]:
    """Along one axis of :func:`bilinear`: the two cells' indices (m,) intp and weights (m,)."""
    i0, w0, w1 = _axis_fraction(v, origin, cell)
    i1 = i0 + 1
    np.clip(i1, 0, size - 1, out=i1)
    np.clip(i0, 0, size - 1, out=i0)
    return i0, i1, w0, w1


def _axis_cell(v: np.ndarray, origin: float, cell: float, size: int) -> tuple[np.ndarray, ...]:
    """Along one axis of :func:`bilinear`'s corner table: the first cell's index clipped to
    -1..size-1 (m,) intp (below and above the grid, both corners are the edge cell) and
    the weights (m,)."""
    i0, w0, w1 = _axis_fraction(v, origin, cell)
    np.clip(i0, -1, size - 1, out=i0)
    return i0, w0, w1
