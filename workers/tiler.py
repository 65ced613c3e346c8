"""The tiler: read a block once, streamed in chunks, and write every tile's buffered
points to the work store, with a tile index.

Peak memory is one chunk (plus its tile assignment), whatever the block size: each
chunk's points are spilled to one part file per tile they fall in, so no per-tile
array of the whole block is ever held. A tile stores, per point, the file's integer
X, Y, Z (exact; workers turn them into the same float64 local coordinates as an
untiled read), the point's index in the input file and whether it lies in the core.

Two engines produce the same tiles: ``laspy`` (default, streamed) and ``pdal``
(``readers.las`` -> ``filters.splitter`` with length, buffer and origin), used when
PDAL's Python bindings import.
"""

from __future__ import annotations

import json

import numpy as np

from pipeline.blockinfo import BlockInfo
from pipeline.errors import ParameterError
from pipeline.jobparams import CHUNK_POINTS, first_sampled, sample_stride
from pipeline.reading import check_bounds, iter_raw, read_raw_range, to_local
from pipeline.tilelimits import check_split_buffer
from pipeline.tiling import TileGrid, buffered_tiles, core_tile
from workers.workstore import WorkStore

#: One record per (point, tile): stored integers, source index, core flag.
TILE_DTYPE = np.dtype([("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("index", "<u8"), ("core", "u1")])
INDEX_KEY = "tiles/index.json"
#: every :func:`pipeline.jobparams.sample_stride`-th point's local x, y, kept by the
#: tiler for the report's map (one part per chunk, named by its first point)
SAMPLE_KEY = "tiles/sample"
#: the index without its list of tiles: what a tile's task needs (frame and grid), so
#: that the tasks of a job of many tiles do not each read the whole list
FRAME_KEY = "tiles/frame.json"


def tile_key(tile_id: int) -> str:
    return f"tiles/{tile_id:06d}"


def _absolute_xy(ints: np.ndarray, info: BlockInfo) -> np.ndarray:
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


def _index(info: BlockInfo, grid: TileGrid, counts: dict, engine: str) -> dict:
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
        "grid": grid.to_dict(),
        "tiles": tiles,
    }


def _split_chunk(info, grid, store, start, ints, counts: dict) -> None:
    local = to_local(ints, info)
    check_bounds(local, info, start=start)
    stride = sample_stride(info.n_points)
    store.put_array(f"{SAMPLE_KEY}/part-{start:012d}.npy", local[first_sampled(start, stride) :: stride, :2])
    index = np.arange(start, start + len(ints), dtype=np.uint64)
    _write_parts(store, f"part-{start:012d}", ints, index, _absolute_xy(ints, info), grid, counts)


def tile_range(info: BlockInfo, grid: TileGrid, store: WorkStore, start: int, count: int) -> dict:
    """Split points ``[start, start + count)`` of the block into tile parts (a dask task).

    Returns the point counts this range contributed, {tile id: [core, buffered]}.
    """
    counts = {}
    ints = read_raw_range(info.path, start, count, info=info)
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
        With a client (and more than one chunk), every chunk is split by a dask task
        that reads its own range of the file; the workers must see the input path.
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
    if engine == "pdal":
        return tile_block_pdal(info, grid, store)
    store.remove("tiles")
    counts = {}
    if client is not None and info.n_points > chunk_points and info.seekable:
        # each worker reads and splits its own range of the file: tiling runs in parallel
        # (a LAZ of variable-size chunks cannot be entered in the middle: read in one pass)
        starts = list(range(0, info.n_points, int(chunk_points)))
        futures = [
            client.submit(tile_range, info, grid, store, start, int(chunk_points), key=f"tile-range-{start}-{store.url}", pure=False)
            for start in starts
        ]
        for part in (gather or client.gather)(futures):
            _merge_counts(counts, part)
    else:
        for start, ints in iter_raw(info.path, chunk_points=chunk_points, info=info):
            _split_chunk(info, grid, store, start, ints, counts)
    idx = _index(info, grid, counts, "laspy")
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

    ``readers.las`` reads the block; a dimension ``OriginIndex`` (the point's position in
    the file) is added; ``filters.splitter`` (``length`` = tile size, ``buffer``,
    ``origin_x``/``origin_y`` = grid origin) makes one view per tile; each view is written
    to the work store. PDAL holds the whole block in memory and needs a buffer smaller
    than half the tile size.
    """
    check_engine("pdal", grid)
    import pdal
    from numpy.lib import recfunctions as rfn

    s, b = grid.tile_size, grid.buffer
    reader = pdal.Pipeline(json.dumps({"pipeline": [{"type": "readers.las", "filename": info.path}]}))
    reader.execute()
    arr = reader.arrays[0]
    arr = rfn.append_fields(arr, "OriginIndex", np.arange(len(arr), dtype=np.uint64), usemask=False)
    splitter = pdal.Pipeline(
        json.dumps(
            {
                "pipeline": [
                    {
                        "type": "filters.splitter",
                        "length": s,
                        "buffer": b,
                        "origin_x": grid.origin[0],
                        "origin_y": grid.origin[1],
                    }
                ]
            }
        ),
        arrays=[arr],
    )
    splitter.execute()
    store.remove("tiles")
    counts = {}
    scales = np.asarray(info.scales)
    offsets = np.asarray(info.offsets)
    for view in splitter.arrays:
        if len(view) == 0:
            continue
        order = np.argsort(view["OriginIndex"], kind="stable")
        view = view[order]
        xyz = np.column_stack([view["X"], view["Y"], view["Z"]]).astype(np.float64)
        ints = np.round((xyz - offsets) / scales).astype(np.int32)
        xy = _absolute_xy(ints, info)
        core = core_tile(xy, grid)
        tid = _view_tile(xy, core, grid)
        rec = np.empty(len(view), dtype=TILE_DTYPE)
        rec["X"], rec["Y"], rec["Z"] = ints[:, 0], ints[:, 1], ints[:, 2]
        rec["index"] = view["OriginIndex"].astype(np.uint64)
        rec["core"] = core == tid
        store.put_array(f"{tile_key(tid)}/part-pdal.npy", rec)
        _merge_counts(counts, {int(tid): (int(rec["core"].sum()), len(rec))})
    idx = _index(info, grid, counts, "pdal")
    put_index(store, idx)
    return idx


def _view_tile(xy: np.ndarray, core: np.ndarray, grid: TileGrid) -> int:
    """Which tile a PDAL view is: the core tile of its points whose buffered box holds them all."""
    cands, counts = np.unique(core, return_counts=True)
    for tid in cands[np.argsort(-counts, kind="stable")]:
        t = grid.tile(int(tid))
        x0, y0, x1, y1 = t.buffered
        inside = ((x0 < xy[:, 0]) & (xy[:, 0] < x1) & (y0 < xy[:, 1]) & (xy[:, 1] < y1)) | (core == tid)
        if inside.all():
            return int(tid)
    raise RuntimeError("a PDAL view matches no tile of the grid")


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
    :func:`pipeline.jobparams.sample_stride`-th point of the block and those points'
    indices (m,) int64; None when the tiles were made without it (the PDAL engine, a
    work store of an earlier version)."""
    keys = sorted(k for k in store.list(SAMPLE_KEY) if k.endswith(".npy"))
    if not keys:
        return None
    stride = sample_stride(n_points)
    xy, index = [], []
    for k in keys:
        start = int(k.rsplit("part-", 1)[1].split(".")[0])
        part = store.get_array(k)
        first = start + first_sampled(start, stride)
        xy.append(part)
        index.append(np.arange(first, first + len(part) * stride, stride, dtype=np.int64))
    return np.concatenate(xy), np.concatenate(index)
