"""Square tiles with a buffer: the pure geometry of splitting a block.

A grid of square tiles of side ``tile_size`` starts at an explicit ``origin``. Tile
``(col, row)`` has the half-open *core* ``[x0, x0 + s) x [y0, y0 + s)`` with
``x0 = origin_x + col * s`` (so every point lies in exactly one core), and the open
*buffered* box ``(x0 - b, x0 + s + b) x (y0 - b, y0 + s + b)`` (as PDAL's
``filters.splitter``), which always also holds the tile's own core points (with no
buffer, the buffered set is just the core, as in PDAL). Tiles are
numbered row-major over the planned grid. Coordinates may be in any frame, as long as
points and origin share it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.errors import ParameterError
from pipeline.tilelimits import check_copies, check_grid_origin, check_tiling, copies_per_point


@dataclass(frozen=True)
class Tile:
    """One tile of a grid.

    Attributes
    ----------
    id : int
        Row-major number within the planned grid.
    col, row : int
        Grid column and row counted from the grid origin.
    core : (xmin, ymin, xmax, ymax)
        Half-open core bounds [m].
    buffered : (xmin, ymin, xmax, ymax)
        Open bounds of the core plus the buffer [m].
    """

    id: int
    col: int
    row: int
    core: tuple[float, float, float, float]
    buffered: tuple[float, float, float, float]


@dataclass(frozen=True)
class TileGrid:
    """A planned grid: ``ncols x nrows`` tiles starting at column ``col0``, row ``row0``."""

    origin: tuple[float, float]
    tile_size: float
    buffer: float
    col0: int
    row0: int
    ncols: int
    nrows: int

    @property
    def n_tiles(self) -> int:
        return self.ncols * self.nrows

    def tile(self, tile_id: int) -> Tile:
        """The tile numbered ``tile_id``."""
        if not 0 <= tile_id < self.n_tiles:
            raise IndexError(f"tile {tile_id} is not in this grid of {self.n_tiles} tiles")
        col = self.col0 + tile_id % self.ncols
        row = self.row0 + tile_id // self.ncols
        s, b = self.tile_size, self.buffer
        x0 = self.origin[0] + col * s
        y0 = self.origin[1] + row * s
        bx0 = self.origin[0] + col * s - b
        by0 = self.origin[1] + row * s - b
        return Tile(
            id=int(tile_id),
            col=int(col),
            row=int(row),
            core=(x0, y0, self.origin[0] + (col + 1) * s, self.origin[1] + (row + 1) * s),
            buffered=(bx0, by0, bx0 + s + 2 * b, by0 + s + 2 * b),
        )

    def tiles(self) -> list[Tile]:
        return [self.tile(i) for i in range(self.n_tiles)]

    def to_dict(self) -> dict:
        return {
            "origin": list(self.origin),
            "tile_size": self.tile_size,
            "buffer": self.buffer,
            "col0": self.col0,
            "row0": self.row0,
            "ncols": self.ncols,
            "nrows": self.nrows,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "TileGrid":
        return cls(
            origin=(float(d["origin"][0]), float(d["origin"][1])),
            tile_size=float(d["tile_size"]),
            buffer=float(d["buffer"]),
            col0=int(d["col0"]),
            row0=int(d["row0"]),
            ncols=int(d["ncols"]),
            nrows=int(d["nrows"]),
        )


#: :func:`buffered_tiles` lists the points of each tile with a mask over the points
#: (a pass per tile) when they fall in at most this many tiles, whose ids span fewer
#: than MASK_SORT_SPAN; else it sorts the (tile, point) pairs
MASK_SORT_TILES = 16
MASK_SORT_SPAN = 1 << 20
def plan_grid(
    mins,
    maxs,
    *,
    tile_size: float,
    buffer: float,
    grid_origin=(0.0, 0.0),
    reach: float | None = None,
    max_tiles: int = 100_000_000,
) -> TileGrid:
    """Plan the tiles that cover a block.

    Parameters
    ----------
    mins, maxs : (2,) or (3,) float
        Block bounds [m] (only x and y are used).
    tile_size : float
        Side of a tile core [m], > 0.
    buffer : float
        Width added on every side of a core [m], >= 0.
    grid_origin : (2,) float
        A corner of the grid [m]; tile edges lie at ``origin + k * tile_size``.
    reach : float, optional
        The parameters' reach (``PipelineParams.reach()``); the buffer must cover it.
    max_tiles : int
        Refuse grids with more tiles than this (the grid is never enumerated: only tiles
        holding points are written, so this bounds tile ids, not work).

    Returns
    -------
    TileGrid

    Raises
    ------
    ParameterError
        Non-positive or non-finite sizes, a buffer below the reach, too many tiles.
    """
    check_tiling(tile_size, buffer, reach)
    s, b = float(tile_size), float(buffer)
    gx, gy = check_grid_origin(grid_origin)
    spans = [(float(maxs[d]) - float(mins[d])) / s + 2.0 for d in range(2)]
    if spans[0] * spans[1] > max_tiles:  # before any cell number is cast to an integer
        raise ParameterError(f"tile size {s:g} m gives more than {max_tiles} tiles over the block; ",
                             hint="use a larger {tiling.tile_size}", param="tiling.tile_size", value=s)
    far = max(abs(float(v) - o) for v, o in ((mins[0], gx), (maxs[0], gx), (mins[1], gy), (maxs[1], gy))) / s
    if not far < 2.0**52:  # tile numbers counted from the origin stay exact integers
        raise ParameterError(f"the grid origin {(gx, gy)} lies {far:.3g} tiles of {s:g} m from the block; ",
                             hint="use a larger {tiling.tile_size} or an origin nearer the block",
                             param="tiling.grid_origin", value=(gx, gy))
    (c0, c1), (r0, r1) = (
        (_cell(np.asarray([mins[0]]), gx, s)[0], _cell(np.asarray([maxs[0]]), gx, s)[0]),
        (_cell(np.asarray([mins[1]]), gy, s)[0], _cell(np.asarray([maxs[1]]), gy, s)[0]),
    )
    ncols, nrows = int(c1 - c0 + 1), int(r1 - r0 + 1)
    if ncols * nrows > max_tiles:
        raise ParameterError(f"tile size {s:g} m gives {ncols * nrows} tiles (more than {max_tiles}); ",
                             hint="use a larger {tiling.tile_size}", param="tiling.tile_size", value=s, limit=max_tiles)
    check_copies(s, b, copies_per_point(s, b, ncols, nrows))
    return TileGrid(origin=(gx, gy), tile_size=s, buffer=b, col0=int(c0), row0=int(r0), ncols=ncols, nrows=nrows)


def _cell(v: np.ndarray, origin: float, size: float) -> np.ndarray:
    """Cell number k with ``origin + k*size <= v < origin + (k+1)*size``, exactly as the bounds are computed."""
    k = np.floor((v - origin) / size)
    # the division may round across an edge: settle it with the same formula the bounds use
    k = np.where(v < origin + k * size, k - 1, k)
    k = np.where(v >= origin + (k + 1) * size, k + 1, k)
    return k.astype(np.int64)


def core_tile(xy: np.ndarray, grid: TileGrid) -> np.ndarray:
    """Tile whose core holds each point.

    Parameters
    ----------
    xy : (n, 2) or (n, 3) float64 [m]
    grid : TileGrid

    Returns
    -------
    (n,) int64 tile ids. Points outside the planned grid go to the nearest edge tile,
    so every point has exactly one core tile.
    """
    col = np.clip(_cell(xy[:, 0], grid.origin[0], grid.tile_size) - grid.col0, 0, grid.ncols - 1)
    row = np.clip(_cell(xy[:, 1], grid.origin[1], grid.tile_size) - grid.row0, 0, grid.nrows - 1)
    return row * grid.ncols + col


def buffered_tiles(xy: np.ndarray, grid: TileGrid, *, core: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every (point, tile) pair where the tile's buffered box holds the point.

    A point always belongs to its core tile's buffered set, and to every other tile of
    the grid whose open buffered box contains it.

    Parameters
    ----------
    xy : (n, 2) or (n, 3) float64 [m]
    grid : TileGrid
    core : (n,) int64, optional
        ``core_tile(xy, grid)`` if already computed.

    Returns
    -------
    point : (m,) int64
        Indices into ``xy``.
    tile : (m,) int64
        Tile ids; pairs sorted by tile, then point.
    """
    # Strategy: a buffer of b reaches at most floor(b/s) + 1 cells away. Only points within
    # b (plus a rounding margin) of their core's edges can be in another tile's buffer;
    # for those, test each neighbour offset with the buffered-box formula.
    if core is None:
        core = core_tile(xy, grid)
    n = len(xy)
    pts = [np.arange(n, dtype=np.int64)]
    tiles = [core.astype(np.int64)]
    if grid.buffer > 0 and n:
        _add_neighbours(xy, grid, core, pts, tiles)
    return _by_tile(np.concatenate(pts), np.concatenate(tiles), n, only_cores=len(tiles) == 1)


def in_buffered(xy: np.ndarray, grid: TileGrid, tile_id: int, *, core: np.ndarray | None = None) -> np.ndarray:
    """Which points the buffered set of one tile holds: :func:`buffered_tiles`' pairs of
    ``tile_id``, as a mask, without the pairs of every other tile.

    Parameters
    ----------
    xy : (n, 2) or (n, 3) float64 [m]
    grid : TileGrid
    tile_id : int
    core : (n,) int64, optional
        ``core_tile(xy, grid)`` if already computed.

    Returns
    -------
    (n,) bool
    """
    if core is None:
        core = core_tile(xy, grid)
    held = core == tile_id
    if grid.buffer > 0:
        # the open box's test written as _add_neighbours writes it, for the same floats
        s, b = grid.tile_size, grid.buffer
        gx, gy = grid.origin
        c = np.int64(grid.col0 + tile_id % grid.ncols)
        r = np.int64(grid.row0 + tile_id // grid.ncols)
        minx = gx + c * s - b
        miny = gy + r * s - b
        x, y = xy[:, 0], xy[:, 1]
        held |= (minx < x) & (x < minx + s + 2 * b) & (miny < y) & (y < miny + s + 2 * b)
    return held


def _add_neighbours(xy: np.ndarray, grid: TileGrid, core: np.ndarray, pts: list, tiles: list) -> None:
    """Append to ``pts`` and ``tiles`` the (point, tile) pairs of the tiles other than a
    point's core whose open buffered box holds it (`buffered_tiles`)."""
    s, b = grid.tile_size, grid.buffer
    gx, gy = grid.origin
    col = core % grid.ncols + grid.col0
    row = core // grid.ncols + grid.row0
    tol = 1e-9 * (s + b + abs(gx) + abs(gy))
    fx = xy[:, 0] - (gx + col * s)
    fy = xy[:, 1] - (gy + row * s)
    near = (fx < b + tol) | (fx > s - b - tol) | (fy < b + tol) | (fy > s - b - tol)
    near |= (fx < 0) | (fx >= s) | (fy < 0) | (fy >= s)  # outside the grid (clipped)
    sub = np.flatnonzero(near)
    x, y = xy[sub, 0], xy[sub, 1]
    col, row = col[sub], row[sub]
    reach = int(math.floor(b / s)) + 1  # ceil(b/s), plus one where b/s is whole (rounding)
    # no neighbour lies farther than the grid is wide: a buffer far wider than the
    # block costs nothing extra
    col_offsets = range(-min(reach, grid.ncols - 1), min(reach, grid.ncols - 1) + 1)
    row_offsets = range(-min(reach, grid.nrows - 1), min(reach, grid.nrows - 1) + 1)
    # column/row tests once per offset, then combine them per neighbour
    xin, yin = {}, {}
    for d in col_offsets:
        c = col + d
        minx = gx + c * s - b
        xin[d] = (minx < x) & (x < minx + s + 2 * b) & (c >= grid.col0) & (c < grid.col0 + grid.ncols)
    for d in row_offsets:
        r = row + d
        miny = gy + r * s - b
        yin[d] = (miny < y) & (y < miny + s + 2 * b) & (r >= grid.row0) & (r < grid.row0 + grid.nrows)
    for dc in col_offsets:
        if not xin[dc].any():
            continue
        for dr in row_offsets:
            if dc == 0 and dr == 0:
                continue
            idx = np.flatnonzero(xin[dc] & yin[dr])
            if idx.size:
                pts.append(sub[idx])
                tiles.append((row[idx] + dr - grid.row0) * grid.ncols + (col[idx] + dc - grid.col0))


def _by_tile(p: np.ndarray, t: np.ndarray, n: int, *, only_cores: bool) -> tuple[np.ndarray, np.ndarray]:
    """The (point, tile) pairs sorted by tile, then point (`buffered_tiles`)."""
    if only_cores:  # no point in any neighbour's buffer: already sorted by point
        order = np.argsort(t, kind="stable")
        return p[order], t[order]
    lo, hi = int(t.min()), int(t.max())
    present = np.flatnonzero(np.bincount(t - lo)) + lo if hi - lo < MASK_SORT_SPAN else None
    if present is None or len(present) > MASK_SORT_TILES:
        order = np.argsort(t * np.int64(max(n, 1)) + p)  # keys are unique
        return p[order], t[order]
    # few tiles (a chunk of a mobile scan spans a handful): a mask of each one's points
    # lists them in order, in passes over the points instead of a sort of the pairs
    mask = np.empty(n, bool)
    out_p = []
    for tid in present:
        mask[:] = False
        mask[p[t == tid]] = True
        out_p.append(np.flatnonzero(mask))
    sizes = [len(q) for q in out_p]
    return np.concatenate(out_p).astype(np.int64, copy=False), np.repeat(present.astype(np.int64), sizes)
