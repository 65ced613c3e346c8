"""A streamed block's tile index and sample, settled as its tiles run.

The tiles of a COPC block, or of a block split by cell (:mod:`workers.cellranges`), find
their points only when they run: the index the job starts from holds upper bounds, and
each tile keeps its own share of the report's sample. This module knows such an index
and replaces its counts by the ones the tiles found.
"""

from __future__ import annotations

import numpy as np

from pipeline.blockinfo import input_error
from pipeline.mapsample import sample_stride
from workers.tiler import CELLS_ENGINE, SAMPLE_KEY, SOURCE_ENGINE, put_index
from workers.workstore import WorkStore


def streamed(frame: dict) -> bool:
    """Whether the tiles of this tile index (or its frame) find their points when they
    run (from the input, or from ranges sorted by cell): its counts are settled then
    (:func:`settle_index`)."""
    return frame.get("engine") in (SOURCE_ENGINE, CELLS_ENGINE)


def sample_key(tile_id: int) -> str:
    """Where a streamed tile keeps its core's share of the report's sample."""
    return f"{SAMPLE_KEY}/tile-{tile_id:06d}.npy"


def put_tile_sample(store: WorkStore, tile_id: int, local_xy: np.ndarray, index: np.ndarray, n_points: int) -> None:
    """Keep the sampled points (every :func:`pipeline.jobparams.sample_stride`-th of the
    file) among a streamed tile's core points ``local_xy`` (k, 2) [m] of file positions
    ``index`` (k,): the share the tiler keeps for a tile it writes."""
    pick = index % np.uint64(sample_stride(n_points)) == 0
    part = np.empty(int(pick.sum()), dtype=[("x", "<f8"), ("y", "<f8"), ("index", "<i8")])
    part["x"], part["y"], part["index"] = local_xy[pick, 0], local_xy[pick, 1], index[pick].astype(np.int64)
    store.put_array(sample_key(tile_id), part)


def settle_index(store: WorkStore, idx: dict, summaries: list[dict], failed, n_points: int) -> tuple[dict, list[dict]]:
    """A streamed tile index with the counts its tiles found (``summaries``: their
    :func:`workers.tasks.process_tile` results; those of tiles with no core point are
    dropped, with the tiles), stored, and the summaries kept. Any other index is returned
    as it is.

    Raises
    ------
    InputError
        Every tile ran and their core points are not the header's count: the header lies
        about the block's count or extent. Nothing is written from such tiles.
    """
    if not streamed(idx):
        return idx, summaries
    found = {int(s["tile_id"]): s for s in summaries}
    tiles = []
    for t in idx["tiles"]:
        s = found.get(int(t["id"]))
        if s is not None:
            if int(s["n_core"]) == 0:
                continue
            t = dict(t, n_core=int(s["n_core"]), n_buffered=int(s.get("n_buffered", t["n_buffered"])))
        tiles.append(t)
    idx = dict(idx, tiles=tiles, estimated=bool(failed))
    total = sum(int(t["n_core"]) for t in tiles)
    if not failed and total != n_points:
        raise input_error(idx["input"], f"its header announces {n_points:,} points within x {idx['mins'][0]}..{idx['maxs'][0]}, "
                                        f"y {idx['mins'][1]}..{idx['maxs'][1]} but its tiles there hold {total:,}; the file is corrupt")
    put_index(store, idx)
    return idx, [s for s in summaries if int(s["n_core"]) > 0]
