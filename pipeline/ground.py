"""Ground removal by local z-minimum (paper: lateral radius R_g = 1 m) and height above ground."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from pipeline.bilinear import bilinear
from pipeline.errors import InputError
from pipeline.params import GroundParams
from pipeline.passes import CACHE_POINTS
from pipeline.voxels import cell_index, column_max, column_min

# Fixed tuning of the ground model (lengths in metres, slopes in m/m, sizes in cells of
# GroundParams.cell_size).

#: a part of a block is modelled as one raster of at most this many cells (about 1.1 km
#: across at the default 0.25 m cell; the filters hold a few arrays of this size at once)
MAX_PART_CELLS = 20_000_000
#: a block whose footprint fits a raster of this many cells (500 m x 500 m at 0.25 m) is
#: modelled as one part, without looking for gaps
ONE_PART_CELLS = 4_000_000
#: in a wider block, points farther apart than this [m] (and than PART_GAP_RADII search
#: radii) with nothing between them belong to separate parts, each with its own raster
PART_GAP = 32.0
PART_GAP_RADII = 4.0
#: most squares of the grid that finds the parts (the grid itself must fit in memory)
MAX_PART_SQUARES = 50_000_000
#: the tile size suggested for a block too wide for one raster leaves this share of the
#: raster's width to the tile, the rest to its buffers
TILE_HINT_SHARE = 0.8

#: The ground noise is estimated from every k-th point of the block, k = n // STATS_SAMPLE
#: (at least 1): about this many points, enough for a median, in file order, so that the
#: tiles of a tiled job can take the same points (see :func:`stats_stride`).
STATS_SAMPLE = 200_000
#: residuals [m] above the raw model within this band are the near-ground points whose
#: median is the model's shift and whose spread is the noise
STATS_BAND = (-0.05, 0.5)
#: the model is lifted by at most this many noise widths (a thick layer of grass must not
#: lift the ground)
MAX_LIFT_NOISES = 2.5
#: on noisy scans the ground layer is this many noise widths thick, at least the tolerance
NOISE_WIDTHS = 3.0

#: the median a cell minimum is compared with, to find isolated low points, is over a
#: square of this many cells
OUTLIER_MEDIAN_CELLS = 5
#: rounds of :func:`_backed_minima`: a cell's lowest this many points can be unbacked
BACKED_ROUNDS = 8
#: points of a cell within the band above its minimum (the minimum included) that back
#: it: at least this many, and this share of the cell's points ...
BACKED_MIN = 3
BACKED_SHARE = 0.01
#: ... or the minima of this many neighbouring cells within the band
BACKED_NEIGHBOURS = 2

#: slope [m/m] that the ground test always allows across the search radius
SLOPE_ALLOWANCE = 0.3
#: steepest terrain slope [m/m] allowed for when ``max_slope`` is 0 (no limit)
MAX_TERRAIN_SLOPE = 2.0
#: the terrain's slope at a cell is the smallest within this many search radii (a step
#: onto a crown's bottom is steep over a cell or two, a hillside everywhere)
SLOPE_WINDOW_RADII = 3
#: the second pass allows this slope [m/m] above the smoothed ground surface
SMOOTH_SLOPE_ALLOWANCE = 0.15
#: the slope test compares cells with the lowest ground cell of each square of this size [m]
SLOPE_BLOCK = 1.0
#: and looks for lower ground up to this many squares away
SLOPE_STEPS = 40
#: the finished model is smoothed by a median over a square of this many cells
FINAL_MEDIAN_CELLS = 3


@dataclass(frozen=True)
class GroundModel:
    """A gridded terrain model: one raster per separate part of the block.

    Most blocks are one part (every block that fits ``ONE_PART_CELLS``). In a wider one,
    points far from the rest (stray returns kilometres away, or two orchard blocks in one
    file) get rasters of their own instead of one raster spanning the empty ground
    between them.

    Attributes
    ----------
    dtms : tuple of (nx, ny) float64
        Ground height of each cell of each part [m]; every cell is filled (holes from the
        nearest ground cell of the part).
    origins : (p, 2) float64
        XY of the corner of cell (0, 0) of each part [m].
    cell_size : float [m]
    noise : float
        Robust estimate of the vertical spread of ground points around the surface [m].
    part_xy : (b, 2) float64, optional
        Centres of the occupied ``PART_GAP`` squares, and ``part_of`` (b,) int64 the part of
        each: a point is modelled by the part of the nearest one (several parts only).
    """

    dtms: tuple
    origins: np.ndarray
    cell_size: float
    noise: float
    part_xy: np.ndarray | None = None
    part_of: np.ndarray | None = None

    def tolerance(self, params: GroundParams) -> float:
        """Height [m] up to which points are ground: the parameter, widened to
        NOISE_WIDTHS times the estimated ground noise on noisy scans."""
        return max(params.tolerance, NOISE_WIDTHS * self.noise)

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Ground height [m] under each (x, y) (bilinear between cell centres), shape (n,)."""
        xy = np.asarray(xy, dtype=np.float64)[:, :2]
        if len(self.dtms) == 1:
            return self._part_height(0, xy)
        _, near = cKDTree(self.part_xy).query(xy)
        part = self.part_of[near]
        out = np.empty(xy.shape[0])
        for k in np.unique(part):
            sel = part == k
            out[sel] = self._part_height(int(k), xy[sel])
        return out

    def _part_height(self, k: int, xy: np.ndarray) -> np.ndarray:
        return bilinear(self.dtms[k], xy, self.origins[k], self.cell_size)


def _disk(radius_cells: float) -> np.ndarray:
    r = int(np.ceil(radius_cells))
    ii, jj = np.mgrid[-r : r + 1, -r : r + 1]
    return (ii**2 + jj**2) <= radius_cells**2 + 1e-9


def stats_stride(n_points: int) -> int:
    """The k of "every k-th point" that :func:`ground_model` samples for the noise of a
    block of ``n_points``."""
    return max(1, int(n_points) // STATS_SAMPLE)


def ground_model(
    xyz: np.ndarray,
    *,
    params: GroundParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    stats: tuple[float, float] | None = None,
    raw: GroundModel | None = None,
) -> GroundModel:
    """Fit a terrain model from the lowest points.

    Parameters
    ----------
    xyz : (n, 3) float64 [m]
    params : GroundParams
    grid_origin : (3,) float
        The grid is aligned to this point so that tiles of one block share cells.
    stats : (shift, noise), optional
        :func:`ground_stats` of the whole block. A tile of a tiled job passes the block's,
        so that every tile lifts its surface alike; by default they are estimated from
        every :func:`stats_stride`-th point of ``xyz``.
    raw : GroundModel, optional
        :func:`raw_ground_model` of these very ``xyz``, ``params`` and ``grid_origin``,
        already fitted (a tiled job's ground pass fits each tile's): used instead of
        fitting it again.

    Returns
    -------
    GroundModel

    Raises
    ------
    InputError
        A connected part of the block is too wide to model in one piece (more than
        ``MAX_PART_CELLS`` cells): it has to be processed in tiles.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    model = raw_ground_model(xyz, params=params, grid_origin=grid_origin) if raw is None else raw
    if xyz.shape[0] == 0:
        return model
    if stats is None:
        stats = ground_stats(ground_residuals(model, xyz[:: stats_stride(xyz.shape[0])]))
    return lifted(model, stats)


def raw_ground_model(
    xyz: np.ndarray,
    *,
    params: GroundParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> GroundModel:
    """The terrain model of :func:`ground_model` before it is lifted by the noise (noise 0)."""
    # Strategy: split the block into parts separated by empty ground wider than the
    # filters reach, and fit one raster per part (:func:`_part_dtm`).
    xyz = np.asarray(xyz, dtype=np.float64)
    c = params.cell_size
    go = np.asarray(grid_origin[:2], dtype=np.float64)
    if xyz.shape[0] == 0:
        return GroundModel((np.zeros((1, 1)),), go[None].copy(), c, 0.0)
    ix, iy = (cell_index(xyz[:, d], go[d], c) for d in (0, 1))
    lo = np.array([ix.min(), iy.min()])
    span = np.array([ix.max(), iy.max()]) - lo + 1
    part = part_xy = part_of = None
    if float(span[0]) * float(span[1]) > ONE_PART_CELLS:
        ij = np.column_stack([ix, iy])
        part, part_xy, part_of = _parts(ij, c, go, max(PART_GAP, PART_GAP_RADII * params.search_radius))
    if part is None:  # one part (most blocks): the cells' flat index in place of ix
        np.subtract(ix, lo[0], out=ix)
        np.multiply(ix, span[1], out=ix)
        np.add(ix, iy, out=ix)
        np.subtract(ix, lo[1], out=ix)
        dtm = _part_dtm(np.ascontiguousarray(xyz[:, 2]), ix, tuple(span.tolist()), params, corner=lo)
        return GroundModel((dtm,), (go + lo * c)[None], c, 0.0, part_xy, part_of)
    order = np.argsort(part, kind="stable")
    dtms, origins = [], []
    for sel in np.split(order, np.cumsum(np.bincount(part))[:-1]):
        part_ij = ij[sel]
        lo = column_min(part_ij)
        part_ij -= lo
        nx, ny = (column_max(part_ij) + 1).tolist()
        dtms.append(_part_dtm(xyz[sel, 2], part_ij[:, 0] * ny + part_ij[:, 1], (nx, ny), params, corner=lo))
        origins.append(go + lo * c)
    return GroundModel(tuple(dtms), np.array(origins), c, 0.0, part_xy, part_of)


def ground_residuals(model: GroundModel, xyz: np.ndarray) -> np.ndarray:
    """(m,) height [m] of points (m, 3) above a (raw) terrain model."""
    return xyz[:, 2] - model.height_at(xyz)


def ground_stats(residuals: np.ndarray) -> tuple[float, float]:
    """(shift, noise) [m] from residuals above the raw model: cell minima sit about two
    noise widths below the true surface, so the median residual of the near-ground
    points is the shift and their robust spread the noise. (0, 0) without such points."""
    resid = np.asarray(residuals, dtype=np.float64)
    band = resid[(resid >= STATS_BAND[0]) & (resid < STATS_BAND[1])]
    if not band.size:
        return 0.0, 0.0
    shift = float(np.median(band))
    return shift, float(1.4826 * np.median(np.abs(band - shift)))  # a normal sigma per MAD


def lifted(model: GroundModel, stats: tuple[float, float]) -> GroundModel:
    """The raw model lifted by the part of the shift its noise explains (a thick layer of
    grass must not lift the ground), carrying that noise."""
    shift, noise = (float(v) for v in stats)
    lift = min(max(shift - noise, 0.0), MAX_LIFT_NOISES * noise)
    return GroundModel(tuple(d + lift for d in model.dtms), model.origins, model.cell_size, noise, model.part_xy, model.part_of)


def _parts(ij: np.ndarray, cell: float, grid_origin: np.ndarray, gap: float):
    """Separate parts of a block: connected sets of occupied ``gap``-wide squares.

    Points of two parts are at least ``gap`` [m] apart, so no filter of :func:`_part_dtm`
    reaches from one into the other.

    Returns
    -------
    part : (n,) int64 part of each point, or None when the block is one part
    part_xy : (b, 2) float64 centres of the occupied squares (None for one part)
    part_of : (b,) int64 part of each square (None for one part)
    """
    per = max(1, int(np.ceil(gap / cell)))  # cells per square
    sq = ij // per
    lo = column_min(sq)
    sq -= lo
    span = column_max(sq) + 1
    if float(span[0]) * float(span[1]) > MAX_PART_SQUARES:
        raise InputError(f"points spread over {span[0] * per * cell:.0f} x {span[1] * per * cell:.0f} m; split the file")
    occupied = np.zeros((int(span[0]), int(span[1])), bool)
    occupied[sq[:, 0], sq[:, 1]] = True
    label, n = ndimage.label(occupied, structure=np.ones((3, 3), bool))
    for box in ndimage.find_objects(label):  # each part's raster must fit
        _check_fits(np.array([b.stop - b.start for b in box]) * per, cell, cells=MAX_PART_CELLS)
    if n == 1:
        return None, None, None
    rows, cols = np.nonzero(occupied)
    part_xy = grid_origin + (np.column_stack([rows, cols]) + lo + 0.5) * per * cell
    return label[sq[:, 0], sq[:, 1]] - 1, part_xy, label[rows, cols] - 1


def _check_fits(cells_xy: np.ndarray, cell: float, *, cells: float) -> None:
    """Raise InputError when a raster of ``cells_xy`` cells has more than ``cells``."""
    if float(cells_xy[0]) * float(cells_xy[1]) > cells:
        tile = np.floor(TILE_HINT_SHARE * np.sqrt(cells) * cell / 100.0) * 100.0  # a tile and its buffers fit
        raise InputError(
            f"points spread over {cells_xy[0] * cell:.0f} x {cells_xy[1] * cell:.0f} m without a gap: too wide to "
            "model the ground in one piece; ",
            hint=f"process the block in tiles ({{tiling.tile_size}}) of at most {tile:.0f} m",
            param="tiling.tile_size", limit=float(tile),
        )


def _part_dtm(z: np.ndarray, flat: np.ndarray, shape: tuple[int, int], params: GroundParams, *,
              corner: np.ndarray) -> np.ndarray:
    """Ground height of each cell of one part [m], ``shape`` (nx, ny); ``z`` (n,) the
    points' heights, ``flat`` (n,) their cells' flat index ``i * ny + j`` relative to the
    part's corner cell, ``corner`` that cell's index on the block's grid."""
    # Strategy: per-cell minimum z; drop cells far below their neighbourhood (isolated
    # points under the ground); the paper's local z-minimum over R_g picks ground cells
    # (a cell is ground if its minimum is near the local minimum, allowing for slope);
    # holes (cells under dense canopy with no ground return) take the nearest ground cell.
    c = params.cell_size
    nx, ny = shape
    zmin = np.full(nx * ny, np.inf)
    np.minimum.at(zmin, flat, z)
    zmin = zmin.reshape(nx, ny)
    occupied = np.isfinite(zmin)

    # isolated low points: a cell minimum well below the median of its neighbourhood,
    # the neighbourhood seen through minima that other points back (multipath returns
    # under the ground can sit in most cells of a dense scan, several to a cell)
    foot = _disk(max(params.search_radius / c, 1.0))
    backed, own = _backed_minima(z, flat, zmin, params.outlier_depth)
    med = ndimage.median_filter(_fill_nearest(backed, np.isfinite(backed)), size=OUTLIER_MEDIAN_CELLS, mode="nearest")
    low = occupied & (zmin < med - params.outlier_depth)
    if low.any():
        # recompute those cells' minima without the lowest point, nor any other that
        # deep unless its cell's points back it (a cell can hold several stray returns;
        # a patch of ground that the neighbourhood misjudges keeps all but its lowest)
        in_low = np.flatnonzero(low.ravel()[flat])
        z_low, f_low = z[in_low], flat[in_low]
        stray = (z_low < (med.ravel() - params.outlier_depth)[f_low]) & (
            (z_low < backed.ravel()[f_low]) | ~own.ravel()[f_low]
        )
        keep = (z_low > zmin.ravel()[f_low] + 1e-9) & ~stray
        zmin2 = zmin.ravel().copy()
        zmin2[low.ravel()] = np.inf
        np.minimum.at(zmin2, flat[in_low[keep]], z_low[keep])
        zmin = zmin2.reshape(nx, ny)
        occupied = np.isfinite(zmin)

    big = np.where(occupied, zmin, np.inf)
    local_min = ndimage.minimum_filter(big, footprint=foot, mode="nearest")
    # slope allowance: SLOPE_ALLOWANCE across the search radius counts as ground, and on
    # steeper terrain its own slope (the local minimum lies a search radius downhill)
    allowance = params.tolerance + SLOPE_ALLOWANCE * params.search_radius
    slope = _terrain_slope(local_min, c, foot, cap=params.max_slope if params.max_slope > 0 else MAX_TERRAIN_SLOPE)
    cell_allowance = params.tolerance + np.maximum(slope, SLOPE_ALLOWANCE) * params.search_radius
    with np.errstate(invalid="ignore"):  # empty cells: inf - inf
        is_ground_cell = occupied & (zmin - local_min <= cell_allowance)
    if params.max_slope > 0:
        # crown bottoms with no ground return within R_g (a tree cut out of a scan with
        # only a patch of ground under its trunk) pass the local test: reject cells that
        # rise more steeply than max_slope from any lower ground cell
        is_ground_cell &= ~_too_steep(np.where(is_ground_cell, zmin, np.inf), c, params.max_slope, allowance, corner)
    # second pass: compare to the smoothed ground surface so that canopy cells next to
    # ground cells on a slope are not taken as ground
    dtm0 = _fill_nearest(np.where(is_ground_cell, zmin, np.nan), is_ground_cell)
    smooth = ndimage.median_filter(dtm0, footprint=foot, mode="nearest")
    is_ground_cell &= zmin - smooth <= params.tolerance + SMOOTH_SLOPE_ALLOWANCE * params.search_radius
    dtm = _fill_nearest(np.where(is_ground_cell, zmin, np.nan), is_ground_cell)
    return ndimage.median_filter(dtm, size=FINAL_MEDIAN_CELLS, mode="nearest")


def _backed_minima(z: np.ndarray, flat: np.ndarray, zmin: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray]:
    """Per cell the lowest point that other points back, (nx, ny) (inf where none), and
    whether its own cell's points back it, (nx, ny) bool.

    A point is backed when points of its cell lie at most ``band`` [m] above it (with it,
    ``BACKED_MIN`` and ``BACKED_SHARE`` of the cell's points), or the minima of
    ``BACKED_NEIGHBOURS`` neighbouring cells lie within ``band`` of it: ground points
    come in numbers and continue into the next cells, stray returns far under the
    ground (multipath) at scattered depths do neither, even where a dense cell holds a
    dozen of them. A cell's unbacked lowest points are
    passed over, up to ``BACKED_ROUNDS`` of them; after that the cell has no backed minimum.
    """
    nx, ny = zmin.shape
    cur = zmin.ravel().copy()
    zp, fp = z, flat  # the points of the cells still to check
    cells = np.flatnonzero(np.isfinite(cur))  # cells still to check
    need = np.maximum(BACKED_MIN, np.ceil(BACKED_SHARE * np.bincount(flat, minlength=nx * ny)))
    own = np.zeros(nx * ny, bool)
    for _ in range(BACKED_ROUNDS):
        if not cells.size:
            break
        ci, cj = np.divmod(cells, ny)
        near = np.zeros(cells.size, np.int64)  # neighbouring cells' minima within the band
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if dx or dy:
                    ni, nj = ci + dx, cj + dy
                    inside = (ni >= 0) & (ni < nx) & (nj >= 0) & (nj < ny)
                    nb = np.where(inside, cur[np.where(inside, ni * ny + nj, 0)], np.inf)
                    with np.errstate(invalid="ignore"):  # inf - inf
                        near += np.abs(nb - cur[cells]) <= band
        count = np.bincount(fp[zp <= cur[fp] + band], minlength=nx * ny)
        own[cells] = count[cells] >= need[cells]
        alone = np.zeros(nx * ny, bool)
        alone[cells] = ~own[cells] & (near < BACKED_NEIGHBOURS)
        if not alone.any():
            break
        # pass over the unbacked minimum of those cells: their next point is checked next
        rest = np.flatnonzero(alone[fp])  # few cells are alone: their points first, then the test
        rest = rest[zp[rest] > cur[fp[rest]]]
        zp, fp = zp[rest], fp[rest]
        cells = np.flatnonzero(alone)
        cur[cells] = np.inf
        np.minimum.at(cur, fp, zp)
        cells = cells[np.isfinite(cur[cells])]
    else:  # minima left unchecked after the last round
        cur[cells] = np.inf
    own &= np.isfinite(cur)
    return cur.reshape(nx, ny), own.reshape(nx, ny)


def _terrain_slope(local_min: np.ndarray, cell: float, foot: np.ndarray, *, cap: float) -> np.ndarray:
    """Slope of the terrain [m/m] at each cell, (nx, ny), from the surface of local minima
    (on a plane it is the plane moved a search radius downhill: same slope).

    The gradient of that surface, smoothed, is then taken as the smallest within
    SLOPE_WINDOW_RADII search radii: a step of the surface where it runs from ground onto the bottom of a
    crown is steep over a cell or two, a hillside everywhere. At most ``cap``.
    """
    finite = np.isfinite(local_min)
    if not finite.any() or min(local_min.shape) < 2:
        return np.zeros(local_min.shape)
    surface = _fill_nearest(np.where(finite, local_min, np.nan), finite)
    surface = ndimage.median_filter(surface, footprint=foot, mode="nearest")
    gx, gy = np.gradient(surface, cell)
    size = 2 * (SLOPE_WINDOW_RADII * (foot.shape[0] // 2)) + 1
    return np.minimum(ndimage.minimum_filter(np.hypot(gx, gy), size=size, mode="nearest"), cap)


def _too_steep(z: np.ndarray, cell: float, slope: float, allowance: float, corner=(0, 0)) -> np.ndarray:
    """Cells that stand more than ``allowance + slope * distance`` above another cell, (nx, ny) bool
    (False where ``z`` is inf).

    ``z`` holds the cells' heights (inf where there is none). The lower envelope
    min_j(z_j + slope * d_ij) is taken on ``SLOPE_BLOCK`` squares (the minimum of their
    cells) by repeated 3 x 3 erosions with a cone (at most ``SLOPE_STEPS`` squares of
    reach); a cell is too steep when it stands higher than its square's envelope by
    more than ``allowance`` plus the slope across one square's diagonal, so coarse
    squares never reject a cell that a fine test would keep. The squares are aligned to
    the block's grid (``corner``: the index of cell (0, 0) on it), so that tiles of one
    block share them.
    """
    f = max(1, round(SLOPE_BLOCK / cell))
    nx, ny = z.shape
    ax, ay = int(corner[0]) % f, int(corner[1]) % f  # cells of the first square before the raster
    px, py = -(nx + ax) % f, -(ny + ay) % f
    zc = np.pad(z, ((ax, px), (ay, py)), constant_values=np.inf)
    zc = zc.reshape((ax + nx + px) // f, f, (ay + ny + py) // f, f).min(axis=(1, 3))
    step = slope * f * cell
    cone = -step * np.array([[np.sqrt(2.0), 1.0, np.sqrt(2.0)], [1.0, 0.0, 1.0], [np.sqrt(2.0), 1.0, np.sqrt(2.0)]])
    env = zc
    for _ in range(SLOPE_STEPS):
        nxt = np.minimum(env, ndimage.grey_erosion(env, structure=cone, mode="constant", cval=np.inf))
        if np.array_equal(nxt, env):
            break
        env = nxt
    env = np.repeat(np.repeat(env, f, axis=0), f, axis=1)[ax : ax + nx, ay : ay + ny]
    with np.errstate(invalid="ignore"):  # empty cells: inf - inf
        return np.isfinite(z) & (z - env > allowance + step * np.sqrt(2.0))


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
        the tolerance grows to NOISE_WIDTHS times the estimated ground noise on noisy scans.
    """
    height = model.height_at(xyz)
    np.subtract(xyz[:, 2], height, out=height)
    tol = model.tolerance(params)
    below = -max(params.outlier_depth, NOISE_WIDTHS * model.noise)
    is_ground = np.empty(height.shape[0], bool)
    low = np.empty(min(height.shape[0], CACHE_POINTS), bool)
    for a in range(0, height.shape[0], CACHE_POINTS):  # the masks' temporaries stay in cache
        h = height[a : a + CACHE_POINTS]
        np.less_equal(h, tol, out=is_ground[a : a + CACHE_POINTS])
        is_ground[a : a + CACHE_POINTS] &= np.greater_equal(h, below, out=low[: h.shape[0]])
    return height, is_ground
