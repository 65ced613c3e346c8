"""The limits of a tile grid's parameters: a tile size, its buffer against the
parameters' reach, how many tiles a point may be copied into, the grid's origin and
PDAL's narrower buffer. Plain arithmetic, so options are checked without numpy.

One set of bounds for a job's tiling: a tile is :data:`MIN_TILE_SIZE` (1 m) to
:data:`MAX_TILE_SIZE` wide, a buffer 0 to :data:`MAX_BUFFER`; `pipeline.jobparams.
TilingParams` states them as its fields' bounds. The grid's geometry
(:func:`pipeline.tiling.plan_grid`) takes any positive size: it also plans the small
grids of tests, and a block's one tile."""

from __future__ import annotations

import math

from pipeline.errors import ParameterError


def check_buffer(buffer: float, reach: float) -> None:
    """Raise ParameterError when a tile buffer [m] is narrower than the parameters' reach [m]."""
    if buffer < reach:
        raise ParameterError(
            f"tile buffer {buffer:g} m is smaller than the reach of the parameters ({reach:g} m = "
            "segment.max_crown_radius + 1 m + graph.edge_radius): tiles would cut crowns; ",
            hint=f"use {{tiling.buffer}} {math.ceil(reach * 100) / 100:g} or more, or a smaller {{segment.max_crown_radius}}",
            param="tiling.buffer", value=buffer, limit=reach,
        )


#: Most buffered tiles one point may fall in (each holds a copy of it): 8 x 8, i.e. a
#: buffer up to 3.5 tile sizes wide. More is only the cost of the buffer many times over
#: (memory and time grow with it), never a better result.
MAX_COPIES = 64


#: narrowest tile of a job [m]: below a metre a tile holds less than a tree's trunk, and
#: the buffer (the reach, 6 m by default) would copy each point into hundreds of tiles
MIN_TILE_SIZE = 1.0
#: widest tile [m] and widest tile buffer [m]: a block spans at most 1e5 m
#: (``pipeline.blockinfo.MAX_EXTENT``), so neither ever needs to be wider
MAX_TILE_SIZE = 1e5
MAX_BUFFER = 1e5

#: farthest a grid origin may lie from 0 [m], like a block's coordinates (``pipeline.blockinfo.MAX_ABS_COORD``)
MAX_ORIGIN = 1e8


def copies_per_point(tile_size: float, buffer: float, ncols: int = 2**62, nrows: int = 2**62) -> int:
    """Most buffered tiles of an ``ncols`` x ``nrows`` grid that one point falls in."""
    per_axis = math.ceil(2.0 * buffer / tile_size) + 1
    return min(per_axis, ncols) * min(per_axis, nrows)


def min_tile_size(buffer: float) -> float:
    """Smallest tile size [m], rounded up to cm, for which a ``buffer`` [m] keeps
    :func:`copies_per_point` within :data:`MAX_COPIES`."""
    per_axis = math.isqrt(MAX_COPIES)
    return math.ceil(2.0 * buffer / (per_axis - 1) * 100.0) / 100.0


def check_tiling(tile_size: float, buffer: float, reach: float | None = None) -> None:
    """Raise ParameterError unless ``tile_size`` [m] is positive and finite and ``buffer``
    [m] is non-negative, finite, at most :data:`MAX_BUFFER` and at least ``reach`` (when
    given): the geometry's own conditions (how many tiles copy a point depends on the
    block's grid: :func:`pipeline.tiling.plan_grid` checks it there)."""
    s = float(tile_size)
    if not (math.isfinite(s) and s > 0):
        raise ParameterError(f"tile size must be a positive number of metres, not {tile_size}",
                             param="tiling.tile_size", value=tile_size, limit=0.0)
    b = float(buffer)
    if not (math.isfinite(b) and b >= 0):
        raise ParameterError(f"tile buffer must be a non-negative number of metres, not {buffer}",
                             param="tiling.buffer", value=buffer, limit=0.0)
    if b > MAX_BUFFER:
        raise ParameterError(f"tile buffer {buffer:g} m is wider than any block ({MAX_BUFFER:g} m at most)",
                             param="tiling.buffer", value=buffer, limit=MAX_BUFFER)
    if reach is not None:
        check_buffer(b, reach)


def check_copies(tile_size: float, buffer: float, copies: int) -> None:
    """ParameterError when a point would be copied into more than :data:`MAX_COPIES` tiles."""
    if copies > MAX_COPIES:
        raise ParameterError(
            f"tile size {tile_size:g} m with a {buffer:g} m buffer would copy each point into up to {copies} tiles "
            f"(at most {MAX_COPIES}); ",
            hint=f"use a {{tiling.tile_size}} of at least {min_tile_size(buffer):g} m",
            param="tiling.tile_size", value=tile_size, limit=min_tile_size(buffer),
        )


def check_grid_origin(grid_origin) -> tuple[float, float]:
    """The grid origin as two floats [m]; ParameterError unless both are finite and
    within :data:`MAX_ORIGIN` of 0."""
    gx, gy = (float(v) for v in grid_origin)
    if not (math.isfinite(gx) and math.isfinite(gy)) or max(abs(gx), abs(gy)) > MAX_ORIGIN:
        raise ParameterError(f"grid origin must be finite and within {MAX_ORIGIN:g} m of 0, not {tuple(grid_origin)}",
                             param="tiling.grid_origin", value=tuple(grid_origin), limit=MAX_ORIGIN)
    return gx, gy


def check_split_buffer(tile_size: float, buffer: float) -> None:
    """ParameterError unless ``buffer`` [m] is below half ``tile_size`` [m]: PDAL's
    ``filters.splitter`` takes a buffer only that narrow."""
    if buffer >= tile_size / 2:
        raise ParameterError(
            f"the PDAL engine needs a buffer ({buffer:g} m) below half the tile size ({tile_size:g} m); ",
            hint="use a larger {tiling.tile_size} or the laspy engine",
            param="tiling.tile_size", value=tile_size, limit=2 * buffer,
        )


