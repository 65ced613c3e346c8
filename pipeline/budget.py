"""The memory budget of one worker: whether a block fits it whole, and otherwise the
largest tile core whose buffered tiles each fit it (and the core that cuts the block into
as many tiles that the job's workers finish soonest: :func:`balanced_tile_size`).

A process's memory follows the points it holds and the nodes of its voxel graph (the
occupied voxels): :func:`bytes_needed`. Whether the block surely fits whole needs its
header's count only, every point taken as its own node (:func:`fits_whole`). The tile
size counts the points and nodes of every buffered tile of the actual grid from a
:class:`DensitySample` (both per square cell, counted in the file by
:func:`pipeline.reading.sample_density`): :func:`tile_size_for_sample`. Dense rows, a
turned block's empty corners, a crowded headland and a sparse scan's many nodes per
point are seen as they are, where the header's mean density would hide them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from pipeline.errors import ParameterError
from pipeline.tilelimits import min_tile_size

#: peak memory of processing points in one piece, per point [bytes]: reading, per-point
#: labels and writing the outputs, with headroom over the measured (docs/performance.md,
#: "The budget refitted")
BYTES_PER_POINT = 95

#: peak memory per node of the voxel graph [bytes]: its edges, their analysis and the
#: segmentation, with headroom over the measured; a sparse scan's tiles, with most nodes
#: a point, set it (docs/performance.md)
BYTES_PER_NODE = 850

#: memory of a worker process whatever it processes [bytes]: the interpreter, dask and
#: the libraries, and what the heap keeps between tiles (docs/performance.md)
FIXED_BYTES = 300e6

#: peak memory of reading and splitting a range of the file's points into tile parts,
#: per point of the range [bytes]: 214-225 measured on 0.5 and 2 M points of a hedge at
#: mobile density (docs/performance.md), with headroom (counting a range takes 88-99:
#: its ranges stay at CHUNK_POINTS, the single pass's runs)
RANGE_BYTES_PER_POINT = 250

#: fewest points a task reads as one range of the file, whatever the budget
MIN_RANGE_POINTS = 50_000

#: a count read from part of the file's points is scaled to all of them and raised by
#: this factor for the sampling error (none when every point was counted);
#: tests/pipeline/test_budget.py bounds the error on generated blocks
SAMPLE_MARGIN = 1.25

#: smallest tile core chosen for a budget, in buffer widths: a core of one buffer
#: processes nine times its own points (its buffer's too), and time grows with them
MIN_CORE_PER_BUFFER = 1.0


class BudgetError(ParameterError):
    """No tile size keeps a worker within the memory budget: at the smallest tile the
    buffer allows, a tile's estimated points and nodes still need more.

    Attributes
    ----------
    budget : float — bytes one worker may use
    density : float — the point density of the buffered tile that needs most [points/m^2]
    tile_size, buffer : float — the smallest tile tried and its buffer [m]
    need : float — estimated bytes of processing such a tile
    """

    def __init__(self, budget: float, density: float, tile_size: float, buffer: float, need: float):
        super().__init__(
            f"a memory budget of {budget / 1e9:.3g} GB per worker is too small for this block: at "
            f"{density:.0f} points/m^2 the smallest tile ({tile_size:g} m with a {buffer:g} m buffer) needs about "
            f"{need / 1e9:.3g} GB; raise the budget"
        )
        self.budget, self.density, self.tile_size, self.buffer, self.need = budget, density, tile_size, buffer, need


def bytes_needed(n_points, n_nodes=None):
    """Estimated peak memory [bytes] of a process that processes ``n_points`` at once,
    whose voxel graph has ``n_nodes`` (at most one a point; None: one a point, the most
    any ``n_points`` can need). Scalars or arrays alike."""
    nodes = n_points if n_nodes is None else np.minimum(n_nodes, n_points)
    return FIXED_BYTES + np.multiply(n_points, BYTES_PER_POINT) + np.multiply(nodes, BYTES_PER_NODE)


def fits_whole(n_points: int, budget: float) -> bool:
    """Whether processing ``n_points`` in one piece surely needs no more than ``budget``
    [bytes], from the count alone (every point its own node)."""
    return bool(bytes_needed(n_points) <= budget)


def surely_tiled(n_points: int, budget: float | None) -> bool:
    """Whether ``n_points`` in one piece need more than ``budget`` [bytes] even with no
    voxel-graph node at all (None: no budget, never)."""
    return budget is not None and bool(bytes_needed(n_points, 0) > budget)


def range_points(budget: float | None, most: int) -> int:
    """Points a worker reads as one range of the file to split it into tiles: ``most``, or
    fewer where the budget [bytes] (None: none) allows fewer above the fixed part (but
    not below :data:`MIN_RANGE_POINTS`)."""
    if budget is None:
        return int(most)
    return int(min(most, max(MIN_RANGE_POINTS, (budget - FIXED_BYTES) // RANGE_BYTES_PER_POINT)))


def smallest_tile(buffer: float) -> float:
    """Smallest tile core chosen for a budget [m]: whole metres, at least
    :data:`MIN_CORE_PER_BUFFER` buffers, :func:`pipeline.tilelimits.min_tile_size` and 1 m."""
    return float(math.ceil(max(MIN_CORE_PER_BUFFER * buffer, min_tile_size(buffer), 1.0)))


@dataclass(frozen=True)
class DensitySample:
    """Points and voxel-graph nodes counted per square cell over part (or all) of a block.

    Attributes
    ----------
    counts : (ny, nx) int64
        Points counted in each cell; row ``j``, column ``i`` is the cell
        ``[ox + i*cell, ox + (i+1)*cell) x [oy + j*cell, oy + (j+1)*cell)`` (points just
        outside the header's bounds are counted in the edge cells).
    origin : (ox, oy) float
        Corner of cell (0, 0) [m], in the block's coordinates.
    cell : float
        Cell side [m].
    sampled : int
        Points counted (the sum of ``counts``).
    n_points : int
        Points of the block (its header's count).
    nodes : (ny, nx) int64 or None
        Occupied voxels counted in each cell (by the voxel's centre), each run of points
        read counting the voxels it occupies: a voxel that several runs reach counts in
        each, so no tile's nodes are undercounted. None: not counted (every point is
        taken as its own node, the most it can be).
    """

    counts: np.ndarray
    origin: tuple[float, float]
    cell: float
    sampled: int
    n_points: int
    nodes: np.ndarray | None = None

    @property
    def exact(self) -> bool:
        """Every point of the block was counted."""
        return self.sampled >= self.n_points

    def weight(self) -> float:
        """Points of the block one counted point stands for, with :data:`SAMPLE_MARGIN`
        unless every point was counted."""
        scale = self.n_points / max(self.sampled, 1)
        return scale if self.exact else scale * SAMPLE_MARGIN

    # summed-area tables, made once: the rule sums them for every tile size it tries
    @cached_property
    def point_table(self) -> np.ndarray:
        return _summed_area(self.counts)

    @cached_property
    def node_table(self) -> np.ndarray | None:
        return None if self.nodes is None else _summed_area(self.nodes)


def _summed_area(counts: np.ndarray) -> np.ndarray:
    """(ny + 1, nx + 1) int64: ``[j, i]`` is the sum of ``counts[:j, :i]``."""
    table = np.zeros((counts.shape[0] + 1, counts.shape[1] + 1), dtype=np.int64)
    np.cumsum(np.cumsum(counts, axis=0), axis=1, out=table[1:, 1:])
    return table


def count_cells(x: np.ndarray, y: np.ndarray, *, origin, cell: float, shape: tuple[int, int]) -> np.ndarray:
    """Points per cell of a grid of ``shape`` (ny, nx) square cells of side ``cell`` [m]
    with its corner at ``origin`` [m], shape ``shape`` int64; points beyond the grid are
    counted in its edge cells. ``x``, ``y``: (n,) coordinates [m] in the same frame."""
    ny, nx = shape
    i = np.clip(np.floor((x - origin[0]) / cell), 0, nx - 1).astype(np.int64)
    j = np.clip(np.floor((y - origin[1]) / cell), 0, ny - 1).astype(np.int64)
    return np.bincount(j * nx + i, minlength=nx * ny).reshape(ny, nx)


def _tile_sums(sample: DensitySample, table: np.ndarray, tile_size: float, buffer: float, mins, maxs,
               grid_origin) -> np.ndarray:
    """Counts of the cells of ``sample`` (their summed-area ``table``) summed over every
    cell each buffered tile's open box overlaps, times the sample's weight and at most
    the block's points."""
    # Strategy: a summed-area table of the counts gives any run of cells in four
    # look-ups; the grid's column and row boxes map to cell ranges once per axis.
    s, b, c = float(tile_size), float(buffer), sample.cell
    ranges = []
    for d in range(2):
        k0 = math.floor((float(mins[d]) - grid_origin[d]) / s)
        k1 = math.floor((float(maxs[d]) - grid_origin[d]) / s)
        lo = grid_origin[d] + np.arange(k0, k1 + 1, dtype=np.float64) * s - b
        n_cells = table.shape[1 - d] - 1
        first = np.clip(np.floor((lo - sample.origin[d]) / c), 0, n_cells).astype(np.int64)
        stop = np.clip(np.ceil((lo + s + 2 * b - sample.origin[d]) / c), 0, n_cells).astype(np.int64)
        ranges.append((first, stop))
    (x0, x1), (y0, y1) = ranges
    held = table[y1][:, x1] - table[y0][:, x1] - table[y1][:, x0] + table[y0][:, x0]
    return np.minimum(held * sample.weight(), float(sample.n_points))


def sampled_tile_points(sample: DensitySample, tile_size: float, buffer: float, mins, maxs, grid_origin) -> np.ndarray:
    """Estimated points of every buffered tile of the grid over ``mins``–``maxs`` with
    core ``tile_size`` [m], ``buffer`` [m] and ``grid_origin`` (as
    :func:`pipeline.tiling.plan_grid`), shape (nrows, ncols).

    A tile's estimate counts every cell its open buffered box overlaps (never fewer
    points than it holds, when every point was counted) times :meth:`DensitySample.weight`,
    and is at most the block's count.
    """
    return _tile_sums(sample, sample.point_table, tile_size, buffer, mins, maxs, grid_origin)


def sampled_tile_nodes(sample: DensitySample, tile_size: float, buffer: float, mins, maxs, grid_origin) -> np.ndarray:
    """Estimated voxel-graph nodes of every buffered tile of the grid (as
    :func:`sampled_tile_points`), shape (nrows, ncols): the counted nodes of every cell
    its box overlaps, at most its points; its points when the sample has no node counts."""
    points = sampled_tile_points(sample, tile_size, buffer, mins, maxs, grid_origin)
    if sample.nodes is None:
        return points
    return np.minimum(_tile_sums(sample, sample.node_table, tile_size, buffer, mins, maxs, grid_origin), points)


def sampled_tile_bytes(sample: DensitySample, tile_size: float, buffer: float, mins, maxs, grid_origin) -> np.ndarray:
    """Estimated peak memory [bytes] of processing every buffered tile of the grid (as
    :func:`sampled_tile_points`), shape (nrows, ncols): :func:`bytes_needed` of its points
    and of its nodes (every point its own node when the sample has no node counts)."""
    points = sampled_tile_points(sample, tile_size, buffer, mins, maxs, grid_origin)
    nodes = None if sample.nodes is None else _tile_sums(sample, sample.node_table, tile_size, buffer, mins, maxs, grid_origin)
    return bytes_needed(points, nodes)  # nodes at most the points: bytes_needed caps them


def block_bytes(sample: DensitySample) -> float:
    """Estimated peak memory [bytes] of processing the whole block in one piece."""
    nodes = None if sample.nodes is None else min(float(sample.nodes.sum()) * sample.weight(), sample.n_points)
    return float(bytes_needed(sample.n_points, nodes))


def tile_size_for_sample(sample: DensitySample, mins, maxs, *, budget: float, buffer: float, grid_origin) -> float | None:
    """The largest tile core whose every buffered tile keeps processing within ``budget``,
    counted from a sample of the block's points (and nodes), or None when the whole
    block fits.

    Parameters
    ----------
    sample : DensitySample
        The block's points and nodes counted per cell (:func:`pipeline.reading.sample_density`).
    mins, maxs : (2,) or (3,) float
        The block's bounds [m].
    budget : float
        Bytes one worker process may use, :data:`FIXED_BYTES` included.
    buffer : float
        Tile buffer [m].
    grid_origin : (2,) float
        The grid's corner [m], as the job will plan it.

    Returns
    -------
    float or None
        Whole metres, at least :func:`smallest_tile`; None also when the smallest tile
        with its buffer would hold the whole block.

    Raises
    ------
    BudgetError
        Even at the smallest tile some buffered tile's estimate needs more than the budget.
    """
    if block_bytes(sample) <= budget:
        return None
    smallest = smallest_tile(buffer)
    if smallest + 2.0 * buffer >= max(float(maxs[0]) - float(mins[0]), float(maxs[1]) - float(mins[1])):
        return None  # the smallest tile and its buffer hold the whole block: tiles would save nothing
    gx, gy = float(grid_origin[0]), float(grid_origin[1])
    widest = math.ceil(max(float(maxs[0]) - float(mins[0]), float(maxs[1]) - float(mins[1]))) + 1
    # the densest tile is not monotone in the size (the grid shifts against the rows):
    # every whole metre is tried from the largest down
    for size in range(int(widest), int(smallest) - 1, -1):
        if sampled_tile_bytes(sample, float(size), buffer, mins, maxs, (gx, gy)).max() <= budget:
            return float(size)
    need = sampled_tile_bytes(sample, smallest, buffer, mins, maxs, (gx, gy))
    worst = np.unravel_index(int(np.argmax(need)), need.shape)
    points = float(sampled_tile_points(sample, smallest, buffer, mins, maxs, (gx, gy))[worst])
    raise BudgetError(budget, points / (smallest + 2.0 * buffer) ** 2, smallest, buffer, float(need[worst]))


def makespan(work, n_workers: int) -> float:
    """The time [units of ``work``] until ``n_workers`` workers finish every task of
    ``work`` when the largest is handed out first and each worker takes the next when it
    is free (:func:`workers.dispatch.run_order`'s order; LPT scheduling).

    Parameters
    ----------
    work : array_like of float
        Each task's work (a tile's buffered points).
    n_workers : int
        At least 1.

    Returns
    -------
    float
        The busiest worker's summed work: the total on 1 worker, the largest task on as
        many workers as tasks.
    """
    loads = np.zeros(max(1, int(n_workers)))
    for w in np.sort(np.asarray(work, dtype=np.float64).ravel())[::-1]:
        loads[int(np.argmin(loads))] += w  # the least loaded worker is the first free
    return float(loads.max())


def balanced_tile_size(sample: DensitySample, size: float, mins, maxs, *, budget: float, buffer: float,
                       grid_origin, n_workers: int) -> float:
    """The tile core that cuts the block into as many tiles along each axis as ``size``
    does and that ``n_workers`` workers finish soonest, as the sample tells.

    ``size``, the largest core that keeps the budget (:func:`tile_size_for_sample`),
    leaves the block's remainder to the last tile of each axis: a 45 m block in 30 m
    tiles is a 30 m tile and a 15 m one, and the larger holds most of the block's points.
    A tile's time follows its buffered points, so the whole metres from ``size`` down to
    the least that still gives that many tiles are tried: of those whose every tile
    keeps ``budget``, the one with the least :func:`makespan` of its buffered tiles'
    estimated points (:func:`sampled_tile_points`) on ``n_workers`` (ties: the larger).
    On 1 worker that is the least total; on as many workers as tiles, the fullest tile
    the least.

    Parameters
    ----------
    sample : DensitySample
    size : float
        Whole metres, at least :func:`smallest_tile`: the largest core that keeps the budget.
    mins, maxs : (2,) or (3,) float
        The block's bounds [m].
    budget : float
        Bytes one worker process may use.
    buffer : float
        Tile buffer [m].
    grid_origin : (2,) float
        The grid's corner [m].
    n_workers : int
        Workers that run the job's tiles at once (at least 1).

    Returns
    -------
    float
        Whole metres, at most ``size`` and at least :func:`smallest_tile`.
    """
    g = (float(grid_origin[0]), float(grid_origin[1]))
    points = sampled_tile_points(sample, float(size), buffer, mins, maxs, g)
    shape, best, soonest = points.shape, float(size), makespan(points, n_workers)
    # n tiles of s metres along an axis cover its extent only when n * s exceeds it
    least = max(smallest_tile(buffer), *(math.floor((float(maxs[d]) - float(mins[d])) / shape[1 - d]) for d in range(2)))
    for s in range(int(size) - 1, int(least) - 1, -1):
        points = sampled_tile_points(sample, float(s), buffer, mins, maxs, g)
        if points.shape != shape:
            continue
        span = makespan(points, n_workers)
        if span < soonest and sampled_tile_bytes(sample, float(s), buffer, mins, maxs, g).max() <= budget:
            best, soonest = float(s), span
    return best


def job_tile_size(sample: DensitySample, mins, maxs, *, budget: float, buffer: float, grid_origin,
                  n_workers: int) -> float | None:
    """The tile core a job takes for this block: None when it fits whole, else the
    largest core that keeps the budget (:func:`tile_size_for_sample`) cut so that its
    ``n_workers`` workers finish soonest (:func:`balanced_tile_size`). Raises what
    :func:`tile_size_for_sample` raises."""
    where = dict(budget=budget, buffer=buffer, grid_origin=grid_origin)
    size = tile_size_for_sample(sample, mins, maxs, **where)
    return None if size is None else balanced_tile_size(sample, size, mins, maxs, **where, n_workers=n_workers)
