"""The task bodies a worker runs on one tile of the work store.

:func:`process_tile` runs the pipeline on a buffered tile, crops to its core, writes the
core points' labels under ``results/<tile>/`` and returns a small summary (trunks,
ownership, partial metrics); :func:`ground_sample` gives the residuals the block's
ground statistics are taken from. Both take the store's URL and plain values, so dask
ships them to any worker that reaches the store.
"""

from __future__ import annotations

import time
import uuid
from types import SimpleNamespace

import numpy as np

from pipeline.canopy import canopy_cells
from pipeline.coverage import occupied_cells, stem_cells
from pipeline.errors import InputError
from pipeline.ground import GroundModel, ground_residuals, raw_ground_model
from pipeline.metrics import tree_partials
from pipeline.params import PipelineParams
from pipeline.passes import indices_where
from pipeline.process import process_points
from pipeline.reading import to_local
from pipeline.tiling import TileGrid, core_tile
from workers.slottrees import SLOT_KEY, trees_in_tile
from workers.cellranges import gather_tile
from workers.settling import put_tile_sample, streamed
from workers.tiler import CELLS_ENGINE, SOURCE_ENGINE, read_frame, read_tile, source_tile, tile_key
from workers.workstore import JOB_KEY, WorkStore

#: how far beyond its core a tile claims a trunk, in cluster radii
OWNERSHIP_MARGIN = 0.5


def result_key(tile_id: int) -> str:
    """The work-store folder of a tile's results."""
    return f"results/{tile_id:06d}"


def raw_ground_key(tile_id: int) -> str:
    """Where the ground pass keeps a tile's raw terrain model: beside the tile's points,
    so that tiling the block again (which removes them) removes it too."""
    return f"{tile_key(tile_id)}/raw_ground.pkl"


def records_key(tile_id: int) -> str:
    """Where the ground pass keeps the records it gathered of a streamed tile (from the
    ranges sorted by cell, or decoded from the input), for the tile's own task: gathered
    once, not once a pass. Beside the tile's ground model, removed with the tiles."""
    return f"{tile_key(tile_id)}/records.npy"


def _frame(index: dict) -> SimpleNamespace:
    return SimpleNamespace(scales=tuple(index["scales"]), offsets=tuple(index["offsets"]), origin=tuple(index["origin"]))


def summarise(tile_id, xyz, core, result, grid: TileGrid | None, origin, params: PipelineParams,
              index: np.ndarray | None = None) -> dict:
    """Small per-tile summary: trunks, ownership and partial metrics of the core points,
    the core's evidence for the block's trees on open slots and the ones the tile let in
    (:mod:`workers.slottrees`), and the cells the core saw (:mod:`pipeline.coverage`).

    ``grid`` None: the tile is the whole block and owns every trunk. ``index``: the
    points' positions in the block's file (None: the whole block, in file order).
    """
    trunks = np.asarray(result.trunks, dtype=np.float64).reshape(-1, 3)
    cluster_radius = params.trunks.at_spacing(result.spacing).cluster_radius  # the radius the tile used
    if grid is None:
        owned = np.ones(len(trunks), dtype=bool)
    else:
        # a tile claims trunks up to half a cluster radius beyond its core: two tiles may
        # place one trunk a few cm apart (their ground models differ slightly), each in the
        # other's core, and it must not be owned by neither (the merge keeps one of two)
        xy = trunks[:, :2] + np.asarray(origin[:2])
        x0, y0, x1, y1 = grid.tile(int(tile_id)).core
        m = OWNERSHIP_MARGIN * cluster_radius
        near = (x0 - m <= xy[:, 0]) & (xy[:, 0] < x1 + m) & (y0 - m <= xy[:, 1]) & (xy[:, 1] < y1 + m)
        owned = (core_tile(xy, grid) == tile_id) | near
    evidence = result.slot_evidence
    if grid is not None and evidence is not None:  # the core's only: each position in one tile
        def in_core(xy):
            return core_tile(np.asarray(xy).reshape(-1, 2) + np.asarray(origin[:2]), grid) == tile_id
        t_in, c_in = in_core(evidence["trunks"]), in_core(evidence["xy"])
        evidence = {k: v[t_in] if k.startswith("trunk") else v[c_in] for k, v in evidence.items()}
    # the core's points picked by masks, not copied out: copies of a large tile's core
    # cost more than the passes that read them
    whole = bool(core.all())
    above = ~result.is_ground if whole else core & ~result.is_ground  # the core's points above the ground
    partials = tree_partials(
        xyz, result.tree_id, result.is_wood, trunks[:, 2], params=params.metrics, among=None if whole else core
    )
    return {
        "tile_id": int(tile_id),
        "trunks": trunks,
        "support": np.asarray(result.trunk_support, dtype=np.float64),
        "diameter": np.asarray(result.trunk_diameter, dtype=np.float64),
        "owned": owned,
        "young": np.zeros(len(trunks), bool) if result.trunk_young is None else np.asarray(result.trunk_young, bool),
        "own_stem": np.zeros(len(trunks), bool) if result.trunk_own_stem is None else np.asarray(result.trunk_own_stem, bool),
        "cluster_radius": cluster_radius,
        "partials": partials,
        "n_core": int(core.sum()),
        # the canopy of the core, for rows whose trunks are hidden (cells in the input CRS)
        "canopy": canopy_cells(xyz[:, :2], result.height, offset=origin[:2], among=above),
        "slot_evidence": evidence,
        # the 1 m cells the core saw: the part of the block this capture covered (input CRS)
        "coverage": occupied_cells(_coverage_points(xyz, core, index), origin[:2]),
        "stems": stem_cells(xyz[:, :2], result.height, above, origin[:2]),
        SLOT_KEY: np.zeros((0, 3)) if result.slot_trees is None else np.asarray(result.slot_trees, np.float64).reshape(-1, 3),
    }


#: every this many-th point of the file (by its position) tells the coverage: 1 m cells
#: hold hundreds of points, and tiles pick the same points as a whole block
COVERAGE_STRIDE = 16


def _coverage_points(xyz, core, index) -> np.ndarray:
    if index is None:
        return xyz[::COVERAGE_STRIDE, :2]  # a view: no copy of the block
    stride = np.uint64(COVERAGE_STRIDE)
    return xyz[indices_where(len(index), lambda s: core[s] & (index[s] % stride == 0)), :2]


def process(xyz: np.ndarray, params: PipelineParams, where: str, ground: tuple[float, float] | None = None,
            slot_trees: np.ndarray | None = None, raw_ground: GroundModel | None = None):
    """``process_points`` on a block or tile; an InputError (e.g. points spread too wide
    for one ground model) names ``where``, the file or the tile. ``slot_trees``: the
    block's trees on open slots, for a tile run again with them; ``raw_ground``: the
    tile's raw terrain model from the ground pass."""
    try:
        return process_points(xyz, params=params, grid_origin=(0.0, 0.0, 0.0), ground_stats=ground, slot_trees=slot_trees,
                              raw_ground=raw_ground)
    except InputError as exc:
        raise exc.prefixed(f"{where}: ") from None


def _tile_points(store: WorkStore, tile_id: int, frame: dict, *, keep: bool = False) -> tuple[dict, np.ndarray]:
    """A buffered tile's record array and its points in the block's local frame
    (``frame``: the tile index, or its frame from :func:`workers.tiler.read_frame`),
    read from the work store, or from the input for a streamed block. ``keep``: keep a
    streamed tile's records in the store (:func:`records_key`), where the next read takes them."""
    if not streamed(frame):
        rec = read_tile(store, tile_id)
    elif store.exists(records_key(tile_id)):
        rec = store.get_array(records_key(tile_id))
    else:
        rec = gather_tile(store, frame, tile_id) if frame.get("engine") == CELLS_ENGINE else source_tile(frame, tile_id)
        if keep:
            store.put_array(records_key(tile_id), rec)
    return rec, to_local((rec["X"], rec["Y"], rec["Z"]), _frame(frame))


def ground_sample(work_url: str, tile_id: int, params_json: str, stride: int) -> np.ndarray:
    """Task body: heights above the tile's raw ground model of the core points whose
    position in the block is a multiple of ``stride``.

    Over all tiles these are the very points an untiled run samples for the ground noise
    (every ``stride``-th point of the file), measured against the same terrain, so the
    block's statistics (and with them every tile's ground) come out as untiled.
    The tile's raw model is kept in the work store (:func:`raw_ground_key`), where
    :func:`process_tile` takes it instead of fitting it again, and so are a streamed
    tile's records (:func:`records_key`), which it takes instead of gathering them again.
    """
    store = WorkStore(work_url)
    frame = read_frame(store)
    params = PipelineParams.model_validate_json(params_json)
    rec, xyz = _tile_points(store, tile_id, frame, keep=True)
    if not rec["core"].any():  # a streamed tile whose estimate was wrong: it holds no core point
        return np.zeros(0)
    pick = rec["core"].astype(bool) & (rec["index"] % np.uint64(stride) == 0)
    try:
        model = raw_ground_model(xyz, params=params.ground)
    except InputError as exc:
        raise exc.prefixed(f"tile {tile_id}: ") from None
    store.put_object(raw_ground_key(tile_id), model)
    return ground_residuals(model, xyz[pick])


def process_tile(work_url: str, tile_id: int, params_json: str, fail: bool = False) -> dict:
    """Task body: process one buffered tile from the work store.

    Writes the core points' labels (``index`` sorted, ``tree_id`` local, ``is_ground``,
    ``is_wood``, ``wood_score``) and the summary under ``results/<tile>/``, and returns
    the summary (trunks, support, diameter, owned, partials); ``{"abandoned": True}``
    when the job's store went away before the tile was done. ``fail``: raise instead
    (testing the failure policy only).
    """
    store = WorkStore(work_url)
    if fail:  # testing the failure policy: leave a trace of each attempt, then fail
        store.put_json(f"attempts/{tile_id:06d}/{uuid.uuid4().hex}.json", {"tile": tile_id, "time": time.time()})
        raise RuntimeError(f"injected failure in tile {tile_id} (testing)")
    if not store.exists(JOB_KEY):  # the job ended (its store deleted) before this tile started
        return _abandon(store)
    record = store.get_json(JOB_KEY)
    stats = record.get("ground_stats")  # the block's, shared by every tile
    frame = read_frame(store)
    params = PipelineParams.model_validate_json(params_json)
    grid = TileGrid.from_dict(frame["grid"])
    # none yet: the tile decides on its own rows; after the block's decision, the block's
    given = record.get(SLOT_KEY)
    slot_trees = None if given is None else trees_in_tile(given, {"buffered": grid.tile(int(tile_id)).buffered}, frame["origin"])
    rec, xyz = _tile_points(store, tile_id, frame)
    n_buffered = len(rec)
    core = rec["core"].astype(bool)
    if not core.any():  # a streamed tile whose estimate was wrong (workers.settling.settle_index drops it)
        return {"tile_id": int(tile_id), "n_core": 0, "n_buffered": n_buffered}
    # the records' coordinates are in xyz now: through the analysis only their indices
    # are held (a field is a view that would keep every record's bytes)
    index = rec["index"].copy()
    del rec
    if frame.get("engine") == SOURCE_ENGINE:  # the ranges of a block split by cell keep theirs
        put_tile_sample(store, tile_id, xyz[core, :2], index[core], int(frame["n_points"]))
    raw = store.get_object(raw_ground_key(tile_id)) if store.exists(raw_ground_key(tile_id)) else None
    result = process(xyz, params, f"tile {tile_id}", tuple(stats) if stats else None, slot_trees, raw)
    key = result_key(tile_id)
    if not store.exists(JOB_KEY):  # the job was cancelled (its store deleted) while this tile ran
        return _abandon(store, tile_id)
    store.put_array(f"{key}/index.npy", index[core])
    store.put_array(f"{key}/tree_id.npy", np.asarray(result.tree_id[core], dtype=np.int64))
    store.put_array(f"{key}/is_ground.npy", np.asarray(result.is_ground[core], dtype=bool))
    store.put_array(f"{key}/is_wood.npy", np.asarray(result.is_wood[core], dtype=bool))
    store.put_array(f"{key}/wood_score.npy", np.asarray(result.wood_score[core], dtype=np.float32))
    summary = summarise(tile_id, xyz, core, result, grid, frame["origin"], params, index=index)
    if streamed(frame):  # its count is known only now (workers.settling.settle_index)
        summary["n_buffered"] = n_buffered
    store.put_object(f"{key}/summary.pkl", summary)
    if not store.exists(JOB_KEY):  # deleted while these were written: take them back
        return _abandon(store, tile_id)
    return summary


def _abandon(store: WorkStore, tile_id: int | None = None) -> dict:
    """A tile that finished after its job ended: what it wrote goes (its results, and the
    folders they leave empty)."""
    if tile_id is not None:
        store.remove(result_key(tile_id))
        for folder in (store.path("results"), store.root):
            try:
                if store.fs.exists(folder) and not store.fs.ls(folder, detail=False):
                    store.fs.rmdir(folder)
            except OSError:
                pass
    return {"abandoned": True}
