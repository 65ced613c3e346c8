"""Ground removal by local z-minimum (paper: lateral radius R_g = 1 m) and height above ground."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from pipeline.params import GroundParams


@dataclass(frozen=True)
class GroundModel:
    """A gridded terrain model.

    Attributes
    ----------
    dtm : (nx, ny) float64
        Ground height of each cell [m]; every cell is filled (holes from the nearest ground cell).
    origin : (2,) float64
        XY of the corner of cell (0, 0) [m].
    cell_size : float [m]
    noise : float
        Robust estimate of the vertical spread of ground points around the surface [m].
    """

    dtm: np.ndarray
    origin: np.ndarray
    cell_size: float
    noise: float

    def tolerance(self, params: GroundParams) -> float:
        """Height [m] up to which points are ground: the parameter, widened to three
        times the estimated ground noise on noisy scans."""
        return max(params.tolerance, 3.0 * self.noise)

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Ground height [m] under each (x, y) (bilinear between cell centres), shape (n,)."""
        g = (np.asarray(xy, dtype=np.float64)[:, :2] - self.origin) / self.cell_size - 0.5
        return ndimage.map_coordinates(self.dtm, g.T, order=1, mode="nearest")


def _disk(radius_cells: float) -> np.ndarray:
    r = int(np.ceil(radius_cells))
    ii, jj = np.mgrid[-r : r + 1, -r : r + 1]
    return (ii**2 + jj**2) <= radius_cells**2 + 1e-9


def ground_model(
    xyz: np.ndarray,
    *,
    params: GroundParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> GroundModel:
    """Fit a terrain model from the lowest points.

    Parameters
    ----------
    xyz : (n, 3) float64 [m]
    params : GroundParams
    grid_origin : (3,) float
        The grid is aligned to this point so that tiles of one block share cells.

    Returns
    -------
    GroundModel
    """
    # Strategy: per-cell minimum z; drop cells far below their neighbourhood (isolated
    # points under the ground); the paper's local z-minimum over R_g picks ground cells
    # (a cell is ground if its minimum is near the local minimum, allowing for slope);
    # holes (cells under dense canopy with no ground return) take the nearest ground cell.
    xyz = np.asarray(xyz, dtype=np.float64)
    c = params.cell_size
    go = np.asarray(grid_origin[:2], dtype=np.float64)
    if xyz.shape[0] == 0:
        return GroundModel(np.zeros((1, 1)), go.copy(), c, 0.0)
    ij = np.floor((xyz[:, :2] - go) / c).astype(np.int64)
    lo = ij.min(axis=0)
    ij -= lo
    nx, ny = (ij.max(axis=0) + 1).tolist()
    origin = go + lo * c
    flat = ij[:, 0] * ny + ij[:, 1]
    zmin = np.full(nx * ny, np.inf)
    np.minimum.at(zmin, flat, xyz[:, 2])
    zmin = zmin.reshape(nx, ny)
    occupied = np.isfinite(zmin)

    # isolated low points: a cell minimum well below the median of its neighbourhood
    foot = _disk(max(params.search_radius / c, 1.0))
    med = ndimage.median_filter(_fill_nearest(zmin, occupied), size=5, mode="nearest")
    low = occupied & (zmin < med - params.outlier_depth)
    if low.any():
        # recompute those cells' minima without the low points
        pz = zmin.ravel()[flat]
        bad_pt = low.ravel()[flat] & (xyz[:, 2] <= pz + 1e-9)
        zmin2 = np.full(nx * ny, np.inf)
        keep = ~bad_pt
        np.minimum.at(zmin2, flat[keep], xyz[keep, 2])
        zmin = zmin2.reshape(nx, ny)
        occupied = np.isfinite(zmin)

    big = np.where(occupied, zmin, np.inf)
    local_min = ndimage.minimum_filter(big, footprint=foot, mode="nearest")
    # slope allowance: up to 30 % slope across the search radius counts as ground
    allowance = params.tolerance + 0.3 * params.search_radius
    with np.errstate(invalid="ignore"):  # empty cells: inf - inf
        is_ground_cell = occupied & (zmin - local_min <= allowance)
    # second pass: compare to the smoothed ground surface so that canopy cells next to
    # ground cells on a slope are not taken as ground
    dtm0 = _fill_nearest(np.where(is_ground_cell, zmin, np.nan), is_ground_cell)
    smooth = ndimage.median_filter(dtm0, footprint=foot, mode="nearest")
    is_ground_cell &= zmin - smooth <= params.tolerance + 0.15 * params.search_radius
    dtm = _fill_nearest(np.where(is_ground_cell, zmin, np.nan), is_ground_cell)
    dtm = ndimage.median_filter(dtm, size=3, mode="nearest")

    # Cell minima sit about two noise widths below the true surface: shift the model up
    # by the median residual of the near-ground points and take their spread as noise.
    model = GroundModel(dtm, origin, c, 0.0)
    sub = xyz[:: max(1, xyz.shape[0] // 200_000)]  # the statistics need no more points
    resid = sub[:, 2] - model.height_at(sub)
    band = resid[(resid >= -0.05) & (resid < 0.5)]
    noise = 0.0
    if band.size:
        shift = float(np.median(band))
        noise = float(1.4826 * np.median(np.abs(band - shift)))
        # only a shift the noise explains; a thick layer of grass must not lift the ground
        dtm = dtm + min(max(shift - noise, 0.0), 2.5 * noise)
    return GroundModel(dtm, origin, c, noise)


def _fill_nearest(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill invalid cells with the value of the nearest valid cell."""
    if valid.all():
        return values.astype(np.float64)
    if not valid.any():
        return np.zeros_like(values, dtype=np.float64)
    _, (ii, jj) = ndimage.distance_transform_edt(~valid, return_indices=True)
    return values[ii, jj].astype(np.float64)


def classify_ground(
    xyz: np.ndarray,
    model: GroundModel,
    *,
    params: GroundParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Height above ground and the ground mask.

    Parameters
    ----------
    xyz : (n, 3) float64 [m]
    model : GroundModel
    params : GroundParams

    Returns
    -------
    height : (n,) float64 [m], negative below the surface
    is_ground : (n,) bool — within the tolerance above (or a little below) the surface;
        the tolerance grows to three times the estimated ground noise on noisy scans.
    """
    height = xyz[:, 2] - model.height_at(xyz)
    tol = model.tolerance(params)
    is_ground = (height <= tol) & (height >= -max(params.outlier_depth, 3.0 * model.noise))
    return height, is_ground
