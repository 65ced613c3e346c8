"""The tiler: read a block once, streamed in chunks, and write every tile's buffered
points to the work store, with a tile index.

Peak memory is one chunk (plus its tile assignment), whatever the block size: each
chunk's points are spilled to one part file per tile they fall in, so no per-tile
array of the whole block is ever held. A tile stores, per point, the file's integer
X, Y, Z (exact; workers turn them into the same float64 local coordinates as an
untiled read), the point's index in the input file and whether it lies in the core.

Two engines produce the same tiles: ``laspy`` (default, streamed) and ``pdal``
(``readers.las`` -> ``filters.splitter`` with length, buffer and origin), used when
PDAL's Python bindings import. Whatever the engine, tiles whose core points do not add
up to the block's points stop the run (:class:`TilesDoNotAddUp`) before the index is stored.

A COPC block is not split at all (:func:`index_from_nodes`): its octree's hierarchy is
the index, and each tile's task reads the nodes its box meets from the input
(:func:`source_tile`), so no pass over the block comes before the first tile and no
tile is written. Its tiles' counts are estimates until the tiles ran
(:func:`workers.settling.settle_index`).

A plain block that a job counts to choose its tile size is not split here either: the
pass that counts it writes its points once, sorted by cell, and each tile gathers its
own (:mod:`workers.cellranges`, engine :data:`CELLS_ENGINE`).
"""

from __future__ import annotations

import json
import math

import numpy as np

from pipeline.blockinfo import BlockInfo, input_error
from pipeline.errors import ParameterError
from pipeline.formats.copc import check_nodes_count, iter_box, nodes_meeting, read_nodes
from pipeline.mapsample import first_sampled, sample_stride
from pipeline.reading import CHUNK_POINTS, check_bounds, iter_raw, read_raw_range, to_local
from pipeline.tilelimits import check_split_buffer
from pipeline.tiling import TileGrid, buffered_tiles, core_tile
from workers.workstore import WorkStore

#: One record per (point, tile): stored integers, source index, core flag.
TILE_DTYPE = np.dtype([("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("index", "<u8"), ("core", "u1")])
INDEX_KEY = "tiles/index.json"
#: every :func:`pipeline.mapsample.sample_stride`-th point's local x, y, kept by the
#: tiler for the report's map (one part per chunk, named by its first point)
SAMPLE_KEY = "tiles/sample"
#: the index without its list of tiles: what a tile's task needs (frame and grid), so
#: that the tasks of a job of many tiles do not each read the whole list
FRAME_KEY = "tiles/frame.json"


def tile_key(tile_id: int) -> str:
    return f"tiles/{tile_id:06d}"


def absolute_xy(ints: np.ndarray, info: BlockInfo) -> np.ndarray:
    """Absolute x, y [m] computed as PDAL and laspy do: ``X * scale + offset``."""
    return ints[:, :2] * np.asarray(info.scales[:2]) + np.asarray(info.offsets[:2])


def _write_parts(store: WorkStore, part: str, ints, index, xy, grid, counts: dict) -> None:
    core = core_tile(xy, grid)
    p, t = buffered_tiles(xy, grid, core=core)
    if p.size == 0:
        return
    cuts = np.flatnonzero(np.diff(t)) + 1
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, p.size]):
        tid = int(t[lo])
        sel = p[lo:hi]
        rec = np.empty(sel.size, dtype=TILE_DTYPE)
        rec["X"] = ints[sel, 0]
        rec["Y"] = ints[sel, 1]
        rec["Z"] = ints[sel, 2]
        rec["index"] = index[sel]
        rec["core"] = core[sel] == tid
        store.put_array(f"{tile_key(tid)}/{part}.npy", rec)
        _merge_counts(counts, {int(tid): (int(rec["core"].sum()), len(rec))})


def _merge_counts(total: dict, part: dict) -> None:
    """Add ``part``'s point counts to ``total``, both {tile id: [core, buffered]}. Only
    tiles holding points are keys, so a block spanning millions of empty tiles costs nothing."""
    for tid, (core, every) in part.items():
        c = total.setdefault(tid, [0, 0])
        c[0] += core
        c[1] += every


def tile_index(info: BlockInfo, grid: TileGrid, counts: dict, engine: str) -> dict:
    tiles = []
    for tid in sorted(counts):
        t = grid.tile(int(tid))
        tiles.append(
            {
                "id": t.id,
                "col": t.col,
                "row": t.row,
                "core": list(t.core),
                "buffered": list(t.buffered),
                "n_core": int(counts[tid][0]),
                "n_buffered": int(counts[tid][1]),
            }
        )
    return {
        "version": 1,
        "engine": engine,
        "input": info.path,
        "n_points": info.n_points,
        "scales": list(info.scales),
        "offsets": list(info.offsets),
        "origin": list(info.origin),
        "mins": list(info.mins),
        "maxs": list(info.maxs),
        "grid": grid.to_dict(),
        "tiles": tiles,
    }


def _split_chunk(info, grid, store, start, ints, counts: dict) -> None:
    local = to_local(ints, info)
    check_bounds(local, info, start=start)
    stride = sample_stride(info.n_points)
    store.put_array(f"{SAMPLE_KEY}/part-{start:012d}.npy", local[first_sampled(start, stride) :: stride, :2])
    index = np.arange(start, start + len(ints), dtype=np.uint64)
    _write_parts(store, f"part-{start:012d}", ints, index, absolute_xy(ints, info), grid, counts)


def tile_range(info: BlockInfo, grid: TileGrid, store: WorkStore, start: int, count: int) -> dict:
    """Split points ``[start, start + count)`` of the block into tile parts (a dask task).

    Returns the point counts this range contributed, {tile id: [core, buffered]}.
    """
    counts = {}
    ints = read_raw_range(info.path, start, count, info=info)
    _split_chunk(info, grid, store, start, ints, counts)
    return counts


def tile_in_order(info: BlockInfo, grid: TileGrid, store: WorkStore, chunk_points: int) -> dict:
    """Split every point of the block into tile parts in one pass, ``chunk_points`` at a
    time (a dask task for a file that cannot be entered in the middle). Returns the
    point counts, {tile id: [core, buffered]}."""
    counts = {}
    for start, ints in iter_raw(info.path, chunk_points=chunk_points, info=info):
        _split_chunk(info, grid, store, start, ints, counts)
    return counts


def tile_block(
    info: BlockInfo,
    grid: TileGrid,
    store: WorkStore,
    *,
    chunk_points: int = CHUNK_POINTS,
    engine: str = "laspy",
    client=None,
    gather=None,
) -> dict:
    """Split a block into buffered tiles in the work store.

    Parameters
    ----------
    info : BlockInfo
        The checked header of the input.
    grid : TileGrid
        Planned in absolute coordinates (input CRS).
    store : WorkStore
    chunk_points : int
        Points read per chunk (bounds memory).
    engine : "laspy" or "pdal"
    client : distributed.Client, optional
        With a client, every chunk is split by a dask task that reads its own range of
        the file (one task reads all of a file that is not ``info.seekable``); the
        workers must see the input path.
    gather : callable, optional
        ``gather(futures)`` → their results, in any order: how to wait for those tasks
        (default ``client.gather``; a job passes one that stops on a cancel and on a
        cluster left without workers).

    Returns
    -------
    The tile index (also stored as ``tiles/index.json``): per tile its id, core and
    buffered bounds, and point counts (core and buffered). Only tiles holding points
    are listed.
    """
    check_engine(engine, grid)
    if info.copc:
        return index_from_nodes(info, grid, store)
    if engine == "pdal":
        return tile_block_pdal(info, grid, store)
    store.remove("tiles")
    counts = {}
    if client is not None:
        # the workers read the file, never the submitting process (the service's, whose
        # memory must not grow with a block): each its own range, in parallel, or one
        # worker all of it in one pass, for a LAZ of variable-size chunks, which cannot be
        # entered in the middle
        if info.seekable:
            futures = [client.submit(tile_range, info, grid, store, start, int(chunk_points),
                                     key=f"tile-range-{start}-{store.url}", pure=False)
                       for start in range(0, info.n_points, int(chunk_points))]
        else:
            futures = [client.submit(tile_in_order, info, grid, store, int(chunk_points), key=f"tile-all-{store.url}",
                                     pure=False)]
        for part in (gather or client.gather)(futures):
            _merge_counts(counts, part)
    else:
        counts = tile_in_order(info, grid, store, chunk_points)
    idx = tile_index(info, grid, counts, "laspy")
    check_tiles_add_up(idx, info.n_points, "laspy")
    put_index(store, idx)
    return idx


def pdal_available() -> bool:
    try:
        import pdal  # noqa: F401  (only whether it imports)
    except Exception:
        return False
    return True


def check_engine(engine: str, grid: TileGrid) -> None:
    """Raise ParameterError unless ``engine`` can make the tiles of ``grid`` here."""
    if engine == "laspy":
        return
    if engine != "pdal":
        raise ParameterError(f"unknown tiling engine {engine!r}; use 'laspy' or 'pdal'", param="tiling.engine", value=engine)
    check_split_buffer(grid.tile_size, grid.buffer)
    if not pdal_available():
        raise ParameterError("the PDAL engine needs PDAL's Python bindings (import pdal failed); ",
                             hint="use {tiling.engine} laspy", param="tiling.engine", value=engine)


def tile_block_pdal(info: BlockInfo, grid: TileGrid, store: WorkStore) -> dict:
    """The same tiles as :func:`tile_block`, made by a PDAL pipeline.

    ``readers.las`` reads the block; its X, Y, Z and a dimension ``OriginIndex`` (the
    point's position in the file) go to ``filters.splitter`` (``length`` = tile size, ``buffer``,
    ``origin_x``/``origin_y`` = grid origin) makes one view per cell; each view that is
    exactly a tile's buffered set is written to the work store (:func:`tiles_from_views`).
    PDAL holds the whole block in memory and needs a buffer smaller than half the tile size.
    """
    check_engine("pdal", grid)
    import pdal

    reader = pdal.Pipeline(json.dumps({"pipeline": [{"type": "readers.las", "filename": info.path}]}))
    reader.execute()
    arr = reader.arrays[0]
    # the splitter gets X, Y, Z and the point's index alone: the tiles need no more, and
    # its views are copies of what it gets
    pts = np.empty(len(arr), dtype=[("X", "<f8"), ("Y", "<f8"), ("Z", "<f8"), ("OriginIndex", "<u8")])
    for d in ("X", "Y", "Z"):
        pts[d] = arr[d]
    pts["OriginIndex"] = np.arange(len(arr), dtype=np.uint64)
    del arr, reader
    stage = {"type": "filters.splitter", "length": grid.tile_size, "buffer": grid.buffer,
             "origin_x": grid.origin[0], "origin_y": grid.origin[1]}
    splitter = pdal.Pipeline(json.dumps({"pipeline": [stage]}), arrays=[pts])
    splitter.execute()
    ints = _stored_ints(pts, info)
    del pts
    views = (v["OriginIndex"] for v in splitter.arrays)
    return tiles_from_views(ints, views, info, grid, store)


def _stored_ints(arr: np.ndarray, info: BlockInfo) -> np.ndarray:
    """The file's integers (n, 3) int32 back from PDAL's scaled X, Y, Z."""
    xyz = np.column_stack([arr["X"], arr["Y"], arr["Z"]]).astype(np.float64)
    return np.round((xyz - np.asarray(info.offsets)) / np.asarray(info.scales)).astype(np.int32)


class TilesDoNotAddUp(RuntimeError):
    """The tiles' core points are not the block's points, each once: a tiling engine
    lost or doubled points. Nothing is written from such tiles."""


def check_tiles_add_up(idx: dict, n_points: int, engine: str) -> None:
    """Raise :class:`TilesDoNotAddUp` unless the core points of the tiles in the index
    ``idx`` add up to the block's ``n_points``."""
    total = sum(int(t["n_core"]) for t in idx["tiles"])
    if total != n_points:
        raise TilesDoNotAddUp(
            f"the tiles made by the {engine!r} engine hold {total} core points, the block has {n_points}: "
            f"points were lost or doubled, so no result is written; tile with the 'laspy' engine")


def tiles_from_views(ints: np.ndarray, views, info: BlockInfo, grid: TileGrid, store: WorkStore) -> dict:
    """Write the tiles of a block from the views of PDAL's ``filters.splitter``.

    Parameters
    ----------
    ints : (n, 3) int32
        The block's stored integers, in file order.
    views : iterable of (k,) integer arrays
        Each view's points as indices into ``ints`` (PDAL's ``OriginIndex``), in any
        order, one per splitter cell.
    info, grid, store
        As :func:`tile_block`.

    Returns
    -------
    The tile index, equal to :func:`tile_block`'s with the laspy engine.

    Raises
    ------
    TilesDoNotAddUp
        When no view is exactly the buffered set of a tile holding points.
    """
    # Strategy: the splitter's cells follow the grid, but it also returns buffer-only
    # views of cells off the grid, and its cell of a point on an edge or outside the
    # header's bounds may differ from the grid's. So the grid's own counts are taken
    # (the laspy engine's assignment, without writing), and a view is tile t only when it
    # holds exactly t's buffered points; the rest are dropped.
    store.remove("tiles")
    stride = sample_stride(info.n_points)
    xy_all = absolute_xy(ints, info)
    expected = {}
    for a in range(0, len(ints), CHUNK_POINTS):
        local = to_local(ints[a : a + CHUNK_POINTS], info)
        check_bounds(local, info, start=a)
        store.put_array(f"{SAMPLE_KEY}/part-{a:012d}.npy", local[first_sampled(a, stride) :: stride, :2])
        xy = xy_all[a : a + CHUNK_POINTS]
        core = core_tile(xy, grid)
        _, t = buffered_tiles(xy, grid, core=core)
        tids, every = np.unique(t, return_counts=True)
        part = {int(k): [0, int(m)] for k, m in zip(tids, every)}
        for k, m in zip(*np.unique(core, return_counts=True)):
            part[int(k)][0] = int(m)
        _merge_counts(expected, part)
    written = {}
    for view in views:
        sel = np.sort(np.asarray(view, dtype=np.int64))
        if sel.size == 0 or (sel.size > 1 and not (np.diff(sel) > 0).all()):
            continue  # empty, or a point twice: no tile's set
        if sel[0] < 0 or sel[-1] >= len(ints):
            raise TilesDoNotAddUp(f"a PDAL view names point {int(sel[-1])} of a block of {len(ints)}")
        xy = xy_all[sel]
        core = core_tile(xy, grid)
        tid = _view_tile(xy, core, grid, expected, written)
        if tid is None:
            continue
        rec = np.empty(sel.size, dtype=TILE_DTYPE)
        rec["X"], rec["Y"], rec["Z"] = ints[sel, 0], ints[sel, 1], ints[sel, 2]
        rec["index"] = sel.astype(np.uint64)
        rec["core"] = core == tid
        store.put_array(f"{tile_key(tid)}/part-pdal.npy", rec)
        written[tid] = [int(rec["core"].sum()), len(rec)]
    missing = sorted(set(expected) - set(written))
    if missing:
        raise TilesDoNotAddUp(
            f"PDAL's splitter gave no view equal to the buffered points of tile(s) {missing[:5]}"
            f"{' ...' if len(missing) > 5 else ''} (of {len(expected)}): points on the grid's edges or "
            "outside the header's bounds fell in other cells; tile with the 'laspy' engine")
    idx = tile_index(info, grid, written, "pdal")
    check_tiles_add_up(idx, info.n_points, "pdal")
    put_index(store, idx)
    return idx


def _view_tile(xy: np.ndarray, core: np.ndarray, grid: TileGrid, expected: dict, taken) -> int | None:
    """The tile a PDAL view is, or None.

    Parameters
    ----------
    xy : (k, 2) float64
        The view's points, absolute [m].
    core : (k,) int64
        Their core tiles (:func:`pipeline.tiling.core_tile`).
    expected : dict
        {tile id: [core points, buffered points]} of the whole block.
    taken : container of int
        Tiles already written from another view.

    Returns
    -------
    The id of a tile not in ``taken`` whose buffered set is exactly the view's points
    (same count, every point inside), or None for a view that is no tile (a cell off the
    grid, a cell the splitter drew differently).
    """
    s, b = grid.tile_size, grid.buffer
    gx, gy = grid.origin
    (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)

    def span(lo, hi, g, first, n):
        # cells whose open buffered box can hold [lo, hi]; one more on each side for rounding
        a = math.floor((hi - g - s - b) / s) - 1
        z = math.ceil((lo - g + b) / s) + 1
        a, z = min(max(a, first), first + n - 1), min(max(z, first), first + n - 1)
        return range(a - first, z - first + 1)

    for row in span(y0, y1, gy, grid.row0, grid.nrows):
        for col in span(x0, x1, gx, grid.col0, grid.ncols):
            tid = row * grid.ncols + col
            if tid in taken or expected.get(tid, (0, 0))[1] != len(xy):
                continue
            bx0, by0, bx1, by1 = grid.tile(tid).buffered
            inside = ((bx0 < xy[:, 0]) & (xy[:, 0] < bx1) & (by0 < xy[:, 1]) & (xy[:, 1] < by1)) | (core == tid)
            if inside.all():
                return tid
    return None


def _frame_of(idx: dict) -> dict:
    """A tile index without its list of tiles."""
    return {k: v for k, v in idx.items() if k != "tiles"}


def put_index(store: WorkStore, idx: dict) -> None:
    """Store a tile index, and its frame (everything but the list of tiles) beside it."""
    store.put_json(FRAME_KEY, _frame_of(idx))
    store.put_json(INDEX_KEY, idx)


def read_frame(store: WorkStore) -> dict:
    """The tile index of a work store without its list of tiles (from the whole index
    in a work store written before the frame was stored on its own)."""
    if store.exists(FRAME_KEY):
        return store.get_json(FRAME_KEY)
    return _frame_of(store.get_json(INDEX_KEY))


def read_tile(store: WorkStore, tile_id: int) -> np.ndarray:
    """All records of one tile (TILE_DTYPE), ordered by source index."""
    parts = [store.get_array(k) for k in store.list(tile_key(tile_id)) if k.endswith(".npy")]
    if not parts:
        return np.zeros(0, dtype=TILE_DTYPE)
    rec = np.concatenate(parts)
    index = rec["index"]
    if len(parts) > 1 and (index[1:] < index[:-1]).any():  # no int64 copy and difference of every index
        rec = rec[np.argsort(index, kind="stable")]
    return rec


def read_sample(store: WorkStore, n_points: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The sample the tiler kept: local x, y (m, 2) [m] of every
    :func:`pipeline.mapsample.sample_stride`-th point of the block and those points'
    indices (m,) int64; None when the tiles were made without it (the PDAL engine, a
    work store of an earlier version)."""
    keys = sorted(k for k in store.list(SAMPLE_KEY) if k.endswith(".npy"))
    if not keys:
        return None
    stride = sample_stride(n_points)
    if "/tile-" in keys[0]:  # a streamed block's: each tile's share, with the points' positions
        part = np.concatenate([store.get_array(k) for k in keys])
        part = part[np.argsort(part["index"], kind="stable")]
        return np.column_stack([part["x"], part["y"]]), part["index"].astype(np.int64)
    xy, index = [], []
    for k in keys:
        start = int(k.rsplit("part-", 1)[1].split(".")[0])
        part = store.get_array(k)
        first = start + first_sampled(start, stride)
        xy.append(part)
        index.append(np.arange(first, first + len(part) * stride, stride, dtype=np.int64))
    return np.concatenate(xy), np.concatenate(index)


#: the engine of a block whose tiles read their own points from the input
SOURCE_ENGINE = "copc"
#: the engine of a block whose tiles gather their points from ranges sorted by cell
#: (:mod:`workers.cellranges`)
CELLS_ENGINE = "cells"


def index_from_nodes(info: BlockInfo, grid: TileGrid, store: WorkStore) -> dict:
    """The tile index of a COPC block from its hierarchy alone: no point is read or
    written. Every tile of the grid whose core meets a node is listed, its ``n_core`` and
    ``n_buffered`` the points of the nodes its core and buffered box meet (an upper bound,
    replaced by the counts its task finds, :func:`settle_index`).

    Raises
    ------
    InputError
        The hierarchy's points are not the header's count, or a node holding points lies
        wholly outside the header's bounds.
    """
    nodes = read_nodes(info.path)
    check_nodes_count(info, nodes)
    # a node beyond the header's bounds holds points no tile of the grid reads
    outside = np.setdiff1d(np.arange(len(nodes.count)), nodes_meeting(nodes, (*info.mins[:2], *info.maxs[:2])))
    if outside.size:
        k = int(outside[0])
        raise input_error(info.path, f"{int(nodes.count[k])} points of its COPC octree lie in a node "
                                     f"({nodes.boxes[k].round(3).tolist()}) outside the header's bounds; the file is corrupt")
    store.remove("tiles")
    counts = {}
    for t in grid.tiles():
        core = int(nodes.count[nodes_meeting(nodes, t.core)].sum())
        if core:
            counts[t.id] = [core, int(nodes.count[nodes_meeting(nodes, t.buffered)].sum())]
    idx = tile_index(info, grid, counts, SOURCE_ENGINE)
    idx["estimated"] = True
    put_index(store, idx)
    return idx


def read_box(grid: TileGrid, tile_id: int) -> tuple[float, float, float, float]:
    """The box whose points a tile of ``grid`` may hold: its buffered box, open to
    infinity on the grid's outer edges (points there go to the edge tiles' cores)."""
    t = grid.tile(int(tile_id))
    x0, y0, x1, y1 = t.buffered
    col, row = tile_id % grid.ncols, tile_id // grid.ncols
    return (-math.inf if col == 0 else x0, -math.inf if row == 0 else y0,
            math.inf if col == grid.ncols - 1 else x1, math.inf if row == grid.nrows - 1 else y1)


def source_tile(frame: dict, tile_id: int) -> np.ndarray:
    """One tile's records (TILE_DTYPE, ordered by source index) read from the input of
    the tile index ``frame`` (its frame is enough): the same records the tiler would
    have written for it. Its nodes are decoded a batch at a time and cut to the tile's
    box at once, so memory is one batch and the tile's points.

    Raises
    ------
    InputError
        A point read lies outside the header's bounds, or the input's data is corrupt.
    """
    info = _frame_info(frame)
    grid = TileGrid.from_dict(frame["grid"])
    box = read_box(grid, tile_id)
    scales, offsets = np.asarray(info.scales), np.asarray(info.offsets)
    # the box and the header's bounds (and their 1 m of slack) as stored integers, a step
    # wider on each side: the exact tests are the tiler's own, on the points kept
    with np.errstate(invalid="ignore", over="ignore"):
        lo = np.nan_to_num(np.floor((np.asarray(box[:2]) - offsets[:2]) / scales[:2]) - 1, neginf=-2**31)
        hi = np.nan_to_num(np.ceil((np.asarray(box[2:]) - offsets[:2]) / scales[:2]) + 1, posinf=2**31)
    valid_lo = np.floor((np.asarray(info.mins) - 1.0 - offsets) / scales) - 1
    valid_hi = np.ceil((np.asarray(info.maxs) + 1.0 - offsets) / scales) + 1
    parts = []
    for ints, index in iter_box(info, box):
        if (ints.min(axis=0) < valid_lo).any() or (ints.max(axis=0) > valid_hi).any():
            check_bounds(to_local(ints, info), info, start=0)  # raises, naming the point
        keep = (ints[:, 0] >= lo[0]) & (ints[:, 0] <= hi[0]) & (ints[:, 1] >= lo[1]) & (ints[:, 1] <= hi[1])
        ints, index = ints[keep], index[keep]
        core = core_tile(absolute_xy(ints, info), grid)
        # the tiler's own assignment: every point in exactly the tiles it gives
        p, t = buffered_tiles(absolute_xy(ints, info), grid, core=core)
        sel = p[t == tile_id]  # ascending
        del p, t
        rec = np.empty(sel.size, dtype=TILE_DTYPE)
        rec["X"], rec["Y"], rec["Z"] = ints[sel, 0], ints[sel, 1], ints[sel, 2]
        rec["index"] = index[sel]
        rec["core"] = core[sel] == tile_id
        parts.append(rec)
    # in file order already: the batches' nodes are, and each keeps its points' order
    return np.concatenate(parts) if parts else np.zeros(0, dtype=TILE_DTYPE)


def _frame_info(frame: dict) -> BlockInfo:
    """The block's header as the tile index's frame keeps it."""
    return BlockInfo(path=frame["input"], n_points=int(frame["n_points"]), version="1.4", point_format=6,
                     compressed=True, scales=tuple(frame["scales"]), offsets=tuple(frame["offsets"]),
                     mins=tuple(frame["mins"]), maxs=tuple(frame["maxs"]), crs_wkt=None,
                     origin=tuple(frame["origin"]), seekable=False, copc=True)
