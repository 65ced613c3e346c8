"""A block decoded once before its tiles: counted for the memory budget and split into
ranges sorted by cell, from which each tile gathers its own points.

A job that must count its block to choose the tile size (:func:`workers.jobspec.auto_tiled`)
used to decode it twice before the first tile: once to count, once to write every
tile's buffered points. Here each range of :data:`pipeline.chunks.CHUNK_POINTS` points
is decoded once by one task (:func:`split_range`), which gives the same density
sample as :func:`pipeline.reading.count_range` and writes the range's points once (no
buffer copies) to the work store, sorted by the 1 m cell of the job's grid origin that
holds them, with the cells' offsets. Once the tile size is chosen the tile index comes
from the cells' counts (:func:`index_from_cells`: a whole-metre tile from that origin
is a block of whole cells, so its core count is exact; its buffered count is an upper
bound until its task ran, :func:`workers.settling.settle_index`), and each tile's task
reads the cells its buffered box meets from the ranges whose cells do
(:func:`gather_tile`) and keeps the tiler's own points, in file order: the records
:func:`workers.tiler.read_tile` gives for the same tile.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.blockinfo import BlockInfo
from pipeline.budget import DensitySample
from pipeline.chunks import CHUNK_POINTS
from pipeline.mapsample import first_sampled, sample_stride
from pipeline.reading import check_bounds, count_ints, iter_raw, read_raw_range, sample_from_ranges, to_local
from pipeline.tiling import TileGrid, core_tile, in_buffered
from workers.tiler import (
    CELLS_ENGINE,
    SAMPLE_KEY,
    TILE_DTYPE,
    absolute_xy,
    check_tiles_add_up,
    put_index,
    read_box,
    tile_index,
)
from workers.workstore import WorkStore

#: side of the cells a range's points are sorted by [m]: every budget's tile size is
#: whole metres (:func:`pipeline.budget.tile_size_for_sample`)
CELL = 1.0
RANGES_KEY = "tiles/ranges"
#: one record per point of a range: its stored integers and its position in the range
RANGE_DTYPE = np.dtype([("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("at", "<u4")])
#: cells of a range read as one request when fewer than this many points lie between
#: them (a tile's box is one run of cells per row of cells)
READ_GAP_POINTS = 16_384


def range_key(start: int) -> str:
    return f"{RANGES_KEY}/{int(start):012d}"


def cell_grid(info: BlockInfo, origin) -> TileGrid:
    """The grid of :data:`CELL` cells from ``origin`` (the job's grid origin [m]) that the
    ranges are sorted by, 3 m wider than the header's bounds on every side: a point
    further out fails :func:`pipeline.reading.check_bounds` first, so no point's cell is
    clipped and each cell's box holds its points."""
    gx, gy = float(origin[0]), float(origin[1])
    c0, c1 = math.floor(info.mins[0] - gx) - 3, math.floor(info.maxs[0] - gx) + 3
    r0, r1 = math.floor(info.mins[1] - gy) - 3, math.floor(info.maxs[1] - gy) + 3
    return TileGrid(origin=(gx, gy), tile_size=CELL, buffer=0.0, col0=c0, row0=r0, ncols=c1 - c0 + 1, nrows=r1 - r0 + 1)


def aligned(grid: TileGrid, cells: TileGrid) -> bool:
    """Whether every core of ``grid`` is a block of whole ``cells`` (or ``grid`` is one
    tile): then a cell's points all lie in one core, and the cores' counts are exact."""
    return grid.n_tiles == 1 or (grid.origin == cells.origin and float(grid.tile_size).is_integer())


def _split(info: BlockInfo, cells: TileGrid, store: WorkStore, start: int, ints: np.ndarray,
           voxel_size: float | None) -> dict:
    density = count_ints(info, ints, voxel_size=voxel_size)
    local = to_local(ints, info)
    check_bounds(local, info, start=start)
    stride = sample_stride(info.n_points)
    # the report map's sample, as the tiler keeps it (workers.tiler.read_sample)
    store.put_array(f"{SAMPLE_KEY}/part-{start:012d}.npy", local[first_sampled(start, stride) :: stride, :2])
    del local
    cell = core_tile(absolute_xy(ints, info), cells)
    # ids of at most 65536 cells sorted as uint16, which numpy sorts by radix: the same
    # stable order in half the time of int64's
    order = np.argsort(cell.astype(np.uint16) if cells.n_tiles <= 1 << 16 else cell, kind="stable")
    cell = cell[order]
    rec = np.empty(len(ints), dtype=RANGE_DTYPE)
    moved = np.take(ints, order, axis=0)  # whole rows at a time: a gather down each strided column costs more
    rec["X"], rec["Y"], rec["Z"] = moved[:, 0], moved[:, 1], moved[:, 2]
    del moved
    rec["at"] = order
    del ints, order
    first = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]]) if len(cell) else np.zeros(0, np.int64)
    ids = cell[first]
    offsets = np.r_[first, len(cell)].astype(np.int64)
    key = range_key(start)
    store.put_array(f"{key}/points.npy", rec)
    store.put_array(f"{key}/cells.npy", ids)
    store.put_array(f"{key}/offsets.npy", offsets)
    col, row = ids % cells.ncols, ids // cells.ncols
    box = [int(col.min()), int(row.min()), int(col.max()), int(row.max())] if len(ids) else None
    return {"start": int(start), "count": len(rec), "density": density, "cells": ids, "counts": np.diff(offsets),
            "box": box}


def split_range(info: BlockInfo, cells: TileGrid, store: WorkStore, start: int, count: int,
                voxel_size: float | None) -> dict:
    """Decode points ``[start, start + count)`` once (a dask task): count them as
    :func:`pipeline.reading.count_range` does and write them to the work store sorted by
    their cell of ``cells`` (:func:`cell_grid`).

    Returns
    -------
    dict: ``start``, ``count``, ``density`` (:func:`pipeline.reading.count_range`'s result),
    ``cells`` (k,) int64 the cells holding points (ids of ``cells``, ascending),
    ``counts`` (k,) their points, ``box`` [col0, row0, col1, row1] of those cells (None
    for no point).

    Raises
    ------
    InputError
        The range lies beyond the points the file holds, its data is corrupt, or a point
        lies outside the header's bounds.
    """
    return _split(info, cells, store, start, read_raw_range(info.path, start, count, info=info), voxel_size)


def split_in_order(info: BlockInfo, cells: TileGrid, store: WorkStore, chunk_points: int,
                   voxel_size: float | None) -> list[dict]:
    """:func:`split_range` of every ``chunk_points`` points of the block in one pass (a
    task for a file that cannot be entered in the middle)."""
    return [_split(info, cells, store, start, ints, voxel_size)
            for start, ints in iter_raw(info.path, chunk_points=chunk_points, info=info)]


def split_block(info: BlockInfo, origin, store: WorkStore, *, voxel_size: float | None, client=None,
                gather=None, progress=None) -> tuple[DensitySample, TileGrid, list[dict]]:
    """Decode the block ``info`` once into ranges sorted by cell (:func:`split_range`, one
    task per :data:`pipeline.chunks.CHUNK_POINTS` points on ``client``'s workers, one task
    for a file that cannot be entered in the middle, or in this process without a client)
    and count it.

    Parameters
    ----------
    origin : (2,) float
        The job's grid origin [m] (:func:`workers.jobspec.grid_origin`).
    voxel_size : float or None
        As :func:`pipeline.reading.count_range`'s.
    gather : callable, optional
        ``gather(futures, progress)`` → their results, in any order, calling
        ``progress(done, total)`` as each is, when given (default ``client.gather``).
    progress : callable (ranges split, ranges), optional
        Handed to ``gather`` when there is more than one range.

    Returns
    -------
    sample : DensitySample
        The one :func:`workers.counting.count_block` gives.
    cells : TileGrid
        The cells the ranges are sorted by (:func:`cell_grid`).
    parts : list of dict
        The ranges (:func:`split_range`'s results without their density), for
        :func:`index_from_cells`.
    """
    store.remove("tiles")
    cells = cell_grid(info, origin)
    if client is None:
        parts = split_in_order(info, cells, store, CHUNK_POINTS, voxel_size)
    else:
        # the workers read the file, never the submitting process (the service's)
        if info.seekable:
            futures = [client.submit(split_range, info, cells, store, start, CHUNK_POINTS, voxel_size,
                                     key=f"split-range-{start}-{store.url}", pure=False)
                       for start in range(0, info.n_points, CHUNK_POINTS)]
        else:
            futures = [client.submit(split_in_order, info, cells, store, CHUNK_POINTS, voxel_size,
                                     key=f"split-all-{store.url}", pure=False)]
        if gather is None:
            parts = client.gather(futures)
        else:
            parts = gather(futures, progress if len(futures) > 1 else None)
        if not info.seekable:
            parts = parts[0]
    sample = sample_from_ranges(info, [p.pop("density") for p in parts])
    return sample, cells, sorted(parts, key=lambda p: p["start"])


def _cell_span(box, cells: TileGrid) -> tuple[int, int, int, int]:
    """Columns and rows (first, last, as indices of ``cells``) of the cells that can hold
    a point of the open ``box`` (xmin, ymin, xmax, ymax) [m], infinite sides allowed:
    one cell more on each side, for the rounding of a point's cell."""
    gx, gy = cells.origin

    def span(lo, hi, g, first, n):
        a = 0 if lo == -math.inf else min(max(math.floor(lo - g) - 1 - first, 0), n - 1)
        z = n - 1 if hi == math.inf else min(max(math.floor(hi - g) + 1 - first, 0), n - 1)
        return a, z

    c0, c1 = span(box[0], box[2], gx, cells.col0, cells.ncols)
    r0, r1 = span(box[1], box[3], gy, cells.row0, cells.nrows)
    return c0, c1, r0, r1


def _row_runs(ids: np.ndarray, cells: TileGrid, span) -> tuple[np.ndarray, np.ndarray]:
    """For each row of cells in ``span`` (:func:`_cell_span`), the first and one past the
    last position in ``ids`` (sorted cell ids) of its cells in the span's columns."""
    c0, c1, r0, r1 = span
    rows = np.arange(r0, r1 + 1, dtype=np.int64)
    return (np.searchsorted(ids, rows * cells.ncols + c0, side="left"),
            np.searchsorted(ids, rows * cells.ncols + c1, side="right"))


def _cell_tiles(ids: np.ndarray, cells: TileGrid, grid: TileGrid) -> np.ndarray:
    """The tile of ``grid`` (aligned with ``cells``, :func:`aligned`) whose core holds each
    cell ``ids``: its column counted in whole tiles from the origin, clipped to the grid as
    :func:`pipeline.tiling.core_tile` clips a point outside it."""
    size = max(1, int(grid.tile_size))
    col = np.clip((ids % cells.ncols + cells.col0) // size - grid.col0, 0, grid.ncols - 1)
    row = np.clip((ids // cells.ncols + cells.row0) // size - grid.row0, 0, grid.nrows - 1)
    return row * grid.ncols + col


def index_from_cells(info: BlockInfo, grid: TileGrid, cells: TileGrid, parts: list[dict], store: WorkStore) -> dict:
    """The tile index of a block split by :func:`split_range` (``parts``: their results),
    stored with the ranges in its frame.

    Every tile whose core holds a point is listed, with its exact core count (``grid``
    must be :func:`aligned` with ``cells``) and, as ``n_buffered``, the points of the
    cells its buffered box meets (an upper bound, settled once its task counted them,
    :func:`workers.settling.settle_index`).

    Raises
    ------
    TilesDoNotAddUp
        The cells' points are not the header's count (never expected: every range was read whole).
    """
    if not aligned(grid, cells):
        raise ValueError("the tile grid is not aligned with the cells its ranges are sorted by")
    ids = np.concatenate([p["cells"] for p in parts]) if parts else np.zeros(0, np.int64)
    n = np.concatenate([p["counts"] for p in parts]) if parts else np.zeros(0, np.int64)
    ids, inverse = np.unique(ids, return_inverse=True)
    n = np.bincount(inverse.ravel(), weights=n, minlength=len(ids)).astype(np.int64)
    tiles, core = np.unique(_cell_tiles(ids, cells, grid), return_inverse=True)
    core = np.bincount(core.ravel(), weights=n, minlength=len(tiles)).astype(np.int64)
    cum = np.r_[0, np.cumsum(n)]
    counts = {}
    for t, c in zip(tiles.tolist(), core.tolist()):
        a, z = _row_runs(ids, cells, _cell_span(read_box(grid, t), cells))
        counts[t] = [c, int((cum[z] - cum[a]).sum())]
    idx = tile_index(info, grid, counts, CELLS_ENGINE)
    idx["estimated"] = True
    idx["cells"] = cells.to_dict()
    idx["ranges"] = sorted(({"start": p["start"], "count": p["count"], "box": p["box"]} for p in parts),
                           key=lambda r: r["start"])
    check_tiles_add_up(idx, info.n_points, CELLS_ENGINE)
    put_index(store, idx)
    return idx


def _read_runs(points, a: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The records of rows ``[a[i], z[i])`` of a range's ``points``
    (:class:`workers.workstore.StoredArray`), ascending, runs merged into one request
    when fewer than :data:`READ_GAP_POINTS` lie between them."""
    keep = z > a
    a, z = a[keep], z[keep]
    if not len(a):
        return np.zeros(0, RANGE_DTYPE)
    out = []
    lo, hi, pieces = int(a[0]), int(z[0]), [(int(a[0]), int(z[0]))]

    def flush():
        data = points.rows(lo, hi)
        out.extend(data[p - lo : q - lo] for p, q in pieces)

    for p, q in zip(a[1:].tolist(), z[1:].tolist()):
        if p - hi < READ_GAP_POINTS:
            hi = max(hi, q)
            pieces.append((p, q))
        else:
            flush()
            lo, hi, pieces = p, q, [(p, q)]
    flush()
    return np.concatenate(out)


def _cells_in_tile(ids: np.ndarray, cells: TileGrid, grid: TileGrid, tile_id: int) -> tuple[np.ndarray, ...]:
    """For cells ``ids`` of ``cells`` (aligned with ``grid``, :func:`aligned`): whether
    their points lie in the core of ``tile_id``, all in its open buffered box, or surely
    none in it (else they are tested one by one)."""
    core = _cell_tiles(ids, cells, grid) == tile_id
    if grid.buffer <= 0:  # no buffer: the buffered set is the core
        return core, core, ~core
    # a cell's points lie in [gx + j, gx + j + 1) (core_tile's own test, cells of 1 m),
    # against in_buffered's box, written as it writes it
    s, b = grid.tile_size, grid.buffer
    gx, gy = cells.origin
    j, k = ids % cells.ncols + cells.col0, ids // cells.ncols + cells.row0
    minx = gx + np.int64(grid.col0 + tile_id % grid.ncols) * s - b
    miny = gy + np.int64(grid.row0 + tile_id // grid.ncols) * s - b
    maxx, maxy = minx + s + 2 * b, miny + s + 2 * b
    x0, x1 = gx + j * CELL, gx + (j + 1) * CELL
    y0, y1 = gy + k * CELL, gy + (k + 1) * CELL
    inside = (x0 > minx) & (x1 <= maxx) & (y0 > miny) & (y1 <= maxy)
    outside = (x1 <= minx) | (x0 >= maxx) | (y1 <= miny) | (y0 >= maxy)
    return core, core | inside, ~core & outside


def _file_order(at: np.ndarray, count: int) -> np.ndarray:
    """The permutation that sorts ``at`` (distinct positions in a range of ``count``
    points): a pass over the range instead of a sort."""
    slot = np.empty(count, dtype=np.int64)
    slot[at] = np.arange(len(at))
    seen = np.zeros(count, dtype=bool)
    seen[at] = True
    return slot[seen]


def gather_tile(store: WorkStore, frame: dict, tile_id: int) -> np.ndarray:
    """One tile's records (TILE_DTYPE, ordered by source index) gathered from the ranges
    of a block split by :func:`split_range` (``frame``: its tile index or the index's
    frame): the records :func:`workers.tiler.read_tile` gives for the tile the tiler
    would have written. Memory is one range's cells and the tile's records.
    """
    # Strategy: the cells that can hold a point of the tile's buffered box are read from
    # each range whose cells meet them (a run of cells per row). A cell lies in one core
    # (the grid is aligned with the cells), and most lie wholly inside the tile's open
    # buffered box or wholly outside it: only the points of the cells on its edge are
    # tested, with pipeline.tiling.in_buffered. Each range's points go back to their
    # file order (ranges are disjoint and taken in file order).
    grid = TileGrid.from_dict(frame["grid"])
    cells = TileGrid.from_dict(frame["cells"])
    span = _cell_span(read_box(grid, tile_id), cells)
    c0, c1, r0, r1 = span
    scale, offset = np.asarray(frame["scales"][:2]), np.asarray(frame["offsets"][:2])
    parts = []
    for r in frame["ranges"]:
        box = r["box"]
        if box is None or box[2] < c0 or box[0] > c1 or box[3] < r0 or box[1] > r1:
            continue
        key = range_key(r["start"])
        ids = store.get_array(f"{key}/cells.npy")
        offsets = store.get_array(f"{key}/offsets.npy")
        a, z = _row_runs(ids, cells, span)
        rec = _read_runs(store.open_array(f"{key}/points.npy"), offsets[a], offsets[z])
        # the cells read, in the order of their points
        lengths = z - a
        picked = np.repeat(a - np.r_[0, np.cumsum(lengths)[:-1]], lengths) + np.arange(int(lengths.sum()))
        core, inside, outside = _cells_in_tile(ids[picked], cells, grid, tile_id)
        per_cell = np.diff(offsets)[picked]
        keep = np.repeat(inside, per_cell)
        edge = np.flatnonzero(np.repeat(~inside & ~outside, per_cell))
        if edge.size:  # absolute x, y as workers.tiler.absolute_xy computes them
            xy = np.column_stack([rec["X"][edge], rec["Y"][edge]]) * scale + offset
            keep[edge] = in_buffered(xy, grid, tile_id, core=np.full(len(edge), -1))
        sel = np.flatnonzero(keep)
        sel = sel[_file_order(rec["at"][sel], int(r["count"]))]
        # one gather of whole records; the tile's records are filled once all ranges are
        parts.append((rec[sel], np.repeat(core, per_cell)[sel], np.uint64(r["start"])))
        del rec, sel, keep
    out = np.empty(sum(len(p[0]) for p in parts), dtype=TILE_DTYPE)
    at = 0
    for rec, core, start in parts:
        part = out[at : at + len(rec)]
        part["X"], part["Y"], part["Z"] = rec["X"], rec["Y"], rec["Z"]
        part["index"] = rec["at"]
        part["index"] += start
        part["core"] = core
        at += len(rec)
    return out
