"""A processing job: one block in, ``trees.parquet`` and ``points.parquet`` out.

Two paths share the same per-tile summary, merge and output code:

- **single block** (no client, no tile size): read the whole block, run the pipeline
  in this process, write the outputs — the fast path;
- **tiled**: the tiler writes buffered tiles to the work store; one task per tile
  (a dask task when a client is given, else in this process) reads its tile from the
  work store, runs the pipeline on the buffered tile, crops to the core, writes its
  per-point labels to the work store and returns a small summary (trunks, partial
  metrics); the merge reconciles trunks and the outputs are streamed tile by tile.

Failure policy (lidR's): the first tile of the plan is the canary (it is scheduled
first); if it fails after its retries the job stops, naming it. A later tile that
fails after its retries is recorded in ``JobOutcome.failed_tiles``; the job finishes
without it, the outcome is partial, and the work store keeps everything needed to
re-run that tile alone (:func:`run_tile`) and merge again (:func:`finish_job`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from pipeline.blockinfo import BlockInfo, read_info
from pipeline.errors import InputError, NoTreesError, OrchardError, ParameterError
from pipeline.ground import (
    ground_residuals,
    ground_stats,
    raw_ground_model,
    stats_stride,
)
from pipeline.laswriting import write_labelled_las
from pipeline.merge import GlobalTrunks, TileTrunks, reconcile_trunks
from pipeline.metrics import combine_partials, finalize_metrics, tree_partials
from pipeline.params import PipelineParams, RowParams
from pipeline.parquet import PointsParquetWriter, write_gaps_parquet, write_rows_parquet, write_trees_parquet
from pipeline.process import process_points
from pipeline.reading import read_points, to_local
from pipeline.rows import RowLayout, find_rows
from pipeline.tiling import TileGrid, core_tile, plan_grid, tile_size_for_budget
from workers.workstore import WorkStore, absolute_url, default_work_dir, own_entry
from workers.tiler import INDEX_KEY, check_engine, read_frame, read_tile, tile_block

JOB_KEY = "job.json"
#: how far beyond its core a tile claims a trunk, in cluster radii
OWNERSHIP_MARGIN = 0.5
#: Attempts after the first for a failing tile.
TILE_RETRIES = 2
#: Points per output window when streaming labels (bounded memory).
WINDOW_POINTS = 2_000_000


class _Stopped(OrchardError):
    """A tiled job stopped with its work store kept: ``reason`` says why, ``hint`` (for
    the command line) how to go on from that store; the message is both."""

    def __init__(self, reason: str, hint: str = ""):
        super().__init__(reason + hint)
        self.reason, self.hint = reason, hint


class TileFailed(_Stopped):
    """A tile's processing failed after its retries (the message names the tile)."""

    def __init__(self, reason: str, tile_id: int, hint: str = ""):
        super().__init__(reason, hint)
        self.tile_id = tile_id


class JobCancelled(OrchardError):
    """The job was cancelled before it finished."""


class ClusterLost(_Stopped):
    """The dask cluster had no workers for too long; the job stopped (it can be resumed)."""


#: Seconds without any dask worker before a job gives up instead of waiting forever.
NO_WORKER_TIMEOUT = 120.0


@dataclass
class JobSpec:
    """What to process and how.

    ``tile_size`` None processes the block as one tile, unless it would need more than
    ``memory_budget`` bytes in one piece: then :func:`auto_tiled` chooses tiles that fit
    it (None: no budget). ``buffer`` None uses ``params.reach()``; ``grid_origin`` None uses the block origin (floor of the header
    minimum), in the input CRS; ``work_dir`` None uses ``out_dir/_work``.
    ``inject_failure`` lists tiles whose task raises (testing the failure policy only).
    """

    input_path: str
    out_dir: str
    params: PipelineParams = field(default_factory=PipelineParams)
    tile_size: float | None = None
    buffer: float | None = None
    grid_origin: tuple[float, float] | None = None
    work_dir: str | None = None
    labelled_laz: bool = False
    engine: str = "laspy"
    chunk_points: int = 2_000_000
    inject_failure: tuple[int, ...] = ()
    memory_budget: float | None = None

    def __post_init__(self) -> None:
        # dask workers run in folders of their own: a relative path would name another
        # file there (or none), so every local path is made absolute here (an empty one
        # would become the current folder)
        for what, value in (("input file", self.input_path), ("output folder", self.out_dir)):
            if not os.fspath(value):
                raise ParameterError(f"no {what} given (an empty path)")
        self.input_path = os.path.abspath(os.fspath(self.input_path))
        self.out_dir = os.path.abspath(os.fspath(self.out_dir))
        if self.work_dir is not None:
            self.work_dir = absolute_url(self.work_dir)
        check_job_paths(self.input_path, self.out_dir, self.work_dir)


def check_job_paths(input_path: str, out_dir: str, work_dir: str | None) -> None:
    """ParameterError when the outputs would destroy the input or be destroyed: an input
    lying in the output folder under an output's name is replaced (or deleted, as an
    earlier run's ``labelled.laz``), and outputs inside the work folder are deleted with
    it when the job is done (the work store removes its ``results``, ``tiles``...; a
    folder of the user's in the work folder, or the work folder itself, are kept)."""
    out = Path(out_dir).resolve()
    source = Path(input_path).resolve()
    if source.parent == out and source.name in OUTPUT_NAMES:
        raise ParameterError(
            f"the input {source.name} lies in the output folder {out_dir} under the name of an output, "
            "which the run replaces: choose another --out"
        )
    if work_dir is not None and (work_dir.startswith("file://") or "://" not in work_dir):
        work = Path(work_dir.removeprefix("file://")).resolve()
        if work in out.parents and own_entry(out.relative_to(work).parts[0]):
            raise ParameterError(
                f"--out {out_dir} lies inside the folder {out.relative_to(work).parts[0]} of --work {work_dir}, "
                "which is deleted when the job is done: put the outputs elsewhere"
            )


@dataclass
class JobOutcome:
    n_points: int
    n_trees: int
    n_tiles: int
    failed_tiles: list[int]
    partial: bool
    timings: dict[str, float]
    outputs: dict[str, str]
    trees: dict | None = None  # the per-tree table (column → array), for summaries


# ------------------------------------------------------------------------- per tile


def _frame(index: dict) -> SimpleNamespace:
    return SimpleNamespace(scales=tuple(index["scales"]), offsets=tuple(index["offsets"]), origin=tuple(index["origin"]))


def _summarise(tile_id, xyz, core, result, grid: TileGrid | None, origin, params: PipelineParams) -> dict:
    """Small per-tile summary: trunks, ownership and partial metrics of the core points."""
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
    sel = slice(None) if core.all() else core  # a whole block: no copies
    partials = tree_partials(
        xyz[sel], result.tree_id[sel], result.is_wood[sel], trunks[:, 2], params=params.metrics
    )
    return {
        "tile_id": int(tile_id),
        "trunks": trunks,
        "support": np.asarray(result.trunk_support, dtype=np.float64),
        "diameter": np.asarray(result.trunk_diameter, dtype=np.float64),
        "owned": owned,
        "young": np.zeros(len(trunks), bool) if result.trunk_young is None else np.asarray(result.trunk_young, bool),
        "cluster_radius": cluster_radius,
        "partials": partials,
        "n_core": int(core.sum()),
    }


def result_key(tile_id: int) -> str:
    return f"results/{tile_id:06d}"


def _process(xyz: np.ndarray, params: PipelineParams, where: str, ground: tuple[float, float] | None = None):
    """``process_points`` on a block or tile; an InputError (e.g. points spread too wide
    for one ground model) names ``where``, the file or the tile."""
    try:
        return process_points(xyz, params=params, grid_origin=(0.0, 0.0, 0.0), ground_stats=ground)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _tile_points(store: WorkStore, tile_id: int, frame: dict) -> tuple[dict, np.ndarray]:
    """A buffered tile's record array and its points in the block's local frame
    (``frame``: the tile index, or its frame from :func:`workers.tiler.read_frame`)."""
    rec = read_tile(store, tile_id)
    ints = np.column_stack([rec["X"], rec["Y"], rec["Z"]])
    return rec, to_local(ints, _frame(frame))


def ground_sample(work_url: str, tile_id: int, params_json: str, stride: int) -> np.ndarray:
    """Task body: heights above the tile's raw ground model of the core points whose
    position in the block is a multiple of ``stride``.

    Over all tiles these are the very points an untiled run samples for the ground noise
    (every ``stride``-th point of the file), measured against the same terrain, so the
    block's statistics (and with them every tile's ground) come out as untiled.
    """
    store = WorkStore(work_url)
    frame = read_frame(store)
    params = PipelineParams.model_validate_json(params_json)
    rec, xyz = _tile_points(store, tile_id, frame)
    pick = rec["core"].astype(bool) & (rec["index"] % np.uint64(stride) == 0)
    try:
        model = raw_ground_model(xyz, params=params.ground)
    except InputError as exc:
        raise InputError(f"tile {tile_id}: {exc}") from None
    return ground_residuals(model, xyz[pick])


def _block_ground_stats(store, tiles, spec, client, cancel, n_points: int) -> list[float]:
    """The block's ground (shift, noise) from :func:`ground_sample` of every tile."""
    stride = stats_stride(n_points)
    params_json = spec.params.model_dump_json()
    parts = []
    if client is None:
        for t in tiles:
            _check_cancel(cancel)
            parts.append(ground_sample(store.url, t["id"], params_json, stride))
    else:
        by_id = {t["id"]: t for t in tiles}
        token = uuid.uuid4().hex[:8]
        futures = {
            client.submit(ground_sample, store.url, t["id"], params_json, stride, key=f"orchard-ground-{t['id']}-{token}",
                          retries=TILE_RETRIES, pure=False): t["id"]
            for t in tiles
        }
        with contextlib.closing(_completed(client, futures, cancel, store)) as done:
            for tid, fut in done:
                if fut.status == "finished":
                    parts.append(fut.result())
                    continue
                exc = fut.exception()
                if isinstance(exc, OrchardError):
                    raise exc
                raise TileFailed(
                    f"{_describe(by_id[tid])} failed after {TILE_RETRIES + 1} attempts to model its ground: {_error_line(exc)}",
                    tid,
                )
    return list(ground_stats(np.concatenate(parts) if parts else np.zeros(0)))


def process_tile(work_url: str, tile_id: int, params_json: str, fail: bool = False) -> dict:
    """Task body: process one buffered tile from the work store.

    Writes the core points' labels (``index`` sorted, ``tree_id`` local, ``is_ground``,
    ``is_wood``, ``wood_score``) and the summary under ``results/<tile>/``, and returns
    the summary (trunks, support, diameter, owned, partials).
    """
    store = WorkStore(work_url)
    if fail:  # testing the failure policy: leave a trace of each attempt, then fail
        store.put_json(f"attempts/{tile_id:06d}/{uuid.uuid4().hex}.json", {"tile": tile_id, "time": time.time()})
        raise RuntimeError(f"injected failure in tile {tile_id} (testing)")
    if not store.exists(JOB_KEY):  # the job ended (its store deleted) before this tile started
        return _abandon(store)
    stats = store.get_json(JOB_KEY).get("ground_stats")  # the block's, shared by every tile
    frame = read_frame(store)
    params = PipelineParams.model_validate_json(params_json)
    grid = TileGrid.from_dict(frame["grid"])
    rec, xyz = _tile_points(store, tile_id, frame)
    core = rec["core"].astype(bool)
    result = _process(xyz, params, f"tile {tile_id}", tuple(stats) if stats else None)
    key = result_key(tile_id)
    if not store.exists(JOB_KEY):  # the job was cancelled (its store deleted) while this tile ran
        return _abandon(store, tile_id)
    store.put_array(f"{key}/index.npy", rec["index"][core])
    store.put_array(f"{key}/tree_id.npy", np.asarray(result.tree_id[core], dtype=np.int64))
    store.put_array(f"{key}/is_ground.npy", np.asarray(result.is_ground[core], dtype=bool))
    store.put_array(f"{key}/is_wood.npy", np.asarray(result.is_wood[core], dtype=bool))
    store.put_array(f"{key}/wood_score.npy", np.asarray(result.wood_score[core], dtype=np.float32))
    summary = _summarise(tile_id, xyz, core, result, grid, frame["origin"], params)
    store.put_object(f"{key}/summary.pkl", summary)
    if not store.exists(JOB_KEY):  # deleted while these were written: take them back
        return _abandon(store, tile_id)
    return summary


def _kept(summary: dict, store: WorkStore, tile: dict) -> dict:
    """A tile's summary, unless its task found no job in the work store: the job's store
    was deleted under it (cancelled), or, if this process still sees the job there, the
    worker that ran the tile does not see the same store."""
    if summary.get("abandoned"):
        if store.exists(JOB_KEY):
            raise TileFailed(
                f"{_describe(tile)}: the dask worker that ran it does not see the job's work store {store.url}",
                tile["id"],
                hint="; every worker must reach the work store at the same address (--work or ORCHARD_WORK_DIR "
                "on a folder all of them share, or an fsspec URL)",
            )
        raise JobCancelled("job cancelled: its work store was deleted")
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


# ------------------------------------------------------------------------- labels


class _Labels:
    """Per-point labels of the block assembled from per-tile core results (bounded memory)."""

    FIELDS = ("tree_id", "is_ground", "is_wood", "wood_score")

    def __init__(self, parts: list[dict], n_points: int):
        self.parts = parts  # each: index (sorted), tree_id (global), is_ground, is_wood, wood_score
        self.n_points = n_points

    @classmethod
    def single(cls, result, id_map: np.ndarray) -> "_Labels":
        n = len(result.tree_id)
        part = {
            "index": np.arange(n, dtype=np.uint64),
            "tree_id": id_map[result.tree_id],
            "is_ground": result.is_ground,
            "is_wood": result.is_wood,
            "wood_score": result.wood_score,
            "map": None,
        }
        return cls([part], n)

    def window(self, a: int, b: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Labels of points a..b-1: (filled mask, dict of arrays)."""
        m = b - a
        out = {
            "tree_id": np.zeros(m, np.int64),
            "is_ground": np.zeros(m, bool),
            "is_wood": np.zeros(m, bool),
            "wood_score": np.zeros(m, np.float32),
        }
        filled = np.zeros(m, bool)
        for p in self.parts:
            idx = p["index"]
            lo, hi = np.searchsorted(idx, np.array([a, b], dtype=np.uint64))
            if hi <= lo:
                continue
            pos = (np.asarray(idx[lo:hi]) - np.uint64(a)).astype(np.int64)
            tree = np.asarray(p["tree_id"][lo:hi])
            out["tree_id"][pos] = tree if p.get("map") is None else p["map"][tree]
            out["is_ground"][pos] = p["is_ground"][lo:hi]
            out["is_wood"][pos] = p["is_wood"][lo:hi]
            out["wood_score"][pos] = p["wood_score"][lo:hi]
            filled[pos] = True
        not_tree = out["tree_id"] == 0  # e.g. of a tree a failed tile owned, in a partial result
        out["is_wood"][not_tree] = False
        out["wood_score"][not_tree] = 0.0
        return filled, out


# ------------------------------------------------------------------------- outputs


def _trees_table(summaries: list[dict], merged: GlobalTrunks, origin) -> dict:
    parts = [s["partials"] for s in summaries]
    maps = [merged.id_maps[s["tile_id"]] for s in summaries]
    partials = combine_partials(parts, maps)
    cols = finalize_metrics(partials, merged.trunks, merged.diameter)
    org = np.asarray(origin, dtype=np.float64)
    cols["trunk_x"] = cols["trunk_x"] + org[0]
    cols["trunk_y"] = cols["trunk_y"] + org[1]
    cols["trunk_z"] = cols["trunk_z"] + org[2]
    return cols


OUTPUT_NAMES = ("points.parquet", "labelled.laz", "trees.parquet", "rows.parquet", "gaps.parquet")


def _without_trunks_between_rows(merged: GlobalTrunks, params: PipelineParams) -> GlobalTrunks:
    """The merged trunks less those that stand between two rows (the row model as a
    prior: off both row lines is foliage or a weed touching down, not a tree); the
    material of each goes to the nearest remaining tree within the crown radius.
    Decided on the whole block's trunks, so tiled and untiled runs agree."""
    if not (params.rows.enabled and params.rows.drop_between_rows) or merged.n_trees < 3:
        return merged
    xy = merged.trunks[:, :2]
    drop = find_rows(xy, params=params.rows).between_rows
    if not drop.any() or drop.all():
        return merged
    keep = ~drop
    new_id = np.zeros(merged.n_trees + 1, dtype=np.int64)
    new_id[1:][keep] = np.arange(1, int(keep.sum()) + 1)
    dist, nearest = cKDTree(xy[keep]).query(xy[drop])
    new_id[1:][drop] = np.where(dist <= params.segment.max_crown_radius, nearest + 1, 0)
    return GlobalTrunks(
        merged.trunks[keep], merged.diameter[keep], merged.support[keep], merged.owner[keep],
        {t: new_id[m] for t, m in merged.id_maps.items()},
    )


def _replanted(summaries: list[dict], merged: GlobalTrunks) -> np.ndarray:
    """(K,) bool: trees that the tile owning their trunk let in as replants."""
    young = np.zeros(merged.n_trees, dtype=bool)
    for s in summaries:
        flags = s.get("young")
        if flags is None or not np.any(flags):
            continue
        glob = merged.id_maps[s["tile_id"]][1:]
        local = np.flatnonzero(np.asarray(flags, bool) & (glob > 0))
        g = glob[local] - 1
        young[g[merged.owner[g] == s["tile_id"]]] = True
    return young


def _with_rows(trees: dict, params: RowParams, replanted: np.ndarray | None = None) -> tuple[dict, RowLayout | None]:
    """The trees table with each tree's address (``row``, ``position``, ``young``), and
    the block's rows; computed on the merged trees, so tiled and untiled runs agree. A
    tree is young when it is much lower than its row neighbours or was let in as a
    replant."""
    if not params.enabled:
        return trees, None
    layout = find_rows(np.c_[trees["trunk_x"], trees["trunk_y"]], trees["height_m"], params=params)
    young = layout.young if replanted is None else layout.young | replanted
    return dict(trees, row=layout.row, position=layout.position, young=young), layout


def _write_outputs(out_dir: Path, info: BlockInfo, labels: _Labels, trees: dict, *, labelled_laz: bool, failed: list[int],
                   layout: RowLayout | None = None) -> dict:
    """Write the outputs of a job into ``out_dir`` as one set.

    Every file is written into a hidden staging folder first; only when all are complete
    do they replace the folder's outputs, and an output of an earlier run that this run
    does not write (``labelled.laz``) is removed, so ``out_dir`` never mixes two runs.
    A failure leaves ``out_dir`` as it was.
    """
    stage = out_dir / f".staging-{uuid.uuid4().hex[:12]}"
    try:
        stage.mkdir(parents=True)
    except OSError as exc:
        raise ParameterError(f"cannot write the outputs to {out_dir}: {exc.strerror or exc}") from None
    written: dict[str, Path] = {}
    meta = {"orchard:input": info.path}
    if failed:
        meta["orchard:failed_tiles"] = json.dumps(failed)
    try:
        path = stage / "points.parquet"
        with PointsParquetWriter(path, metadata=meta) as w:
            for a in range(0, labels.n_points, WINDOW_POINTS):
                b = min(labels.n_points, a + WINDOW_POINTS)
                filled, lab = labels.window(a, b)
                idx = np.arange(a, b, dtype=np.uint64)
                if not filled.all():
                    idx = idx[filled]
                    lab = {k: v[filled] for k, v in lab.items()}
                w.write(idx, lab["tree_id"], lab["is_ground"], lab["is_wood"], lab["wood_score"])
        written["points"] = path
        if labelled_laz:
            path = stage / "labelled.laz"
            write_labelled_las(
                info.path,
                path,
                labels=lambda a, b: {k: v for k, v in labels.window(a, b)[1].items() if k != "is_ground"},
            )
            written["labelled"] = path
        path = stage / "trees.parquet"
        write_trees_parquet(path, trees, crs_wkt=info.crs_wkt, metadata=meta)
        written["trees"] = path
        if layout is not None:
            path = stage / "rows.parquet"
            write_rows_parquet(path, layout.rows, layout.lines, crs_wkt=info.crs_wkt)
            written["rows"] = path
            path = stage / "gaps.parquet"
            write_gaps_parquet(path, layout.gaps, crs_wkt=info.crs_wkt)
            written["gaps"] = path
        outputs = {}
        for key, staged in written.items():  # complete: publish (each rename is atomic)
            final = out_dir / staged.name
            os.replace(staged, final)
            outputs[key] = str(final)
        for name in OUTPUT_NAMES:
            if name not in {p.name for p in written.values()}:
                (out_dir / name).unlink(missing_ok=True)  # an earlier run's, not this run's
        return outputs
    except OSError as exc:  # a full disk, a folder that turned read-only: one line, nothing half-written
        raise ParameterError(f"cannot write the outputs to {out_dir}: {exc.strerror or exc}") from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)


# ------------------------------------------------------------------------- the job


def _check_cancel(cancel: threading.Event | None) -> None:
    if cancel is not None and cancel.is_set():
        raise JobCancelled("job cancelled")


def _no_trees(info: BlockInfo) -> NoTreesError:
    return NoTreesError(
        f"{Path(info.path).name}: no trees found in {info.n_points} points "
        "(only ground or clutter?); check the block, or lower --trunks-min-tree-height / --trunks-min-canopy-voxels"
    )


def run_job(
    spec: JobSpec,
    *,
    client=None,
    progress: Callable[[int, int], None] | None = None,
    cancel: threading.Event | None = None,
) -> JobOutcome:
    """Process one block.

    Parameters
    ----------
    spec : JobSpec
    client : distributed.Client, optional
        Run one task per tile on this cluster. None with ``tile_size`` None runs the
        single-block path in this process; None with a tile size runs the tiles here.
    progress : callable (tiles done, tiles total), optional
    cancel : threading.Event, optional
        Set it to stop the job (raises JobCancelled).

    Raises
    ------
    InputError, ParameterError, NoTreesError, TileFailed, JobCancelled
    """
    t0 = time.perf_counter()
    info = read_info(spec.input_path)
    spec = auto_tiled(spec, info)
    if spec.tile_size is None and client is None:
        return _run_single(spec, info, t0, progress, cancel)
    return _run_tiled(spec, info, client, t0, progress, cancel)


def _run_single(spec, info, t0, progress, cancel) -> JobOutcome:
    timings = {}
    params = spec.params
    if progress:
        progress(0, 1)
    xyz, _ = read_points(info.path, chunk_points=spec.chunk_points)
    timings["read"] = time.perf_counter() - t0
    _check_cancel(cancel)
    t = time.perf_counter()
    result = _process(xyz, params, Path(info.path).name)
    timings["process"] = time.perf_counter() - t
    _check_cancel(cancel)
    t = time.perf_counter()
    core = np.ones(len(xyz), dtype=bool)
    summary = _summarise(0, xyz, core, result, None, info.origin, params)
    merged = reconcile_trunks(
        [_tile_trunks(summary)],
        cluster_radius=summary["cluster_radius"],
        fallback_radius=params.segment.max_crown_radius,
    )
    merged = _without_trunks_between_rows(merged, params)
    if merged.n_trees == 0:
        raise _no_trees(info)
    trees, layout = _with_rows(_trees_table([summary], merged, info.origin), params.rows, _replanted([summary], merged))
    labels = _Labels.single(result, merged.id_maps[0])
    outputs = _write_outputs(Path(spec.out_dir), info, labels, trees, labelled_laz=spec.labelled_laz, failed=[], layout=layout)
    timings["merge_write"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0
    if progress:
        progress(1, 1)
    return JobOutcome(info.n_points, merged.n_trees, 1, [], False, timings, outputs, trees)


def _tile_trunks(summary: dict) -> TileTrunks:
    return TileTrunks(summary["tile_id"], summary["trunks"], summary["support"], summary["diameter"], summary["owned"])


def check_job(spec: JobSpec, *, tiled: bool | None = None) -> tuple[BlockInfo, TileGrid | None]:
    """Check the input and the tiling parameters of a job without writing anything.

    Returns the block's header information and, for a tiled job, the planned grid.
    Raises InputError or ParameterError.
    """
    info = read_info(spec.input_path)
    check_out_dir(spec.out_dir)
    if tiled is None:
        tiled = spec.tile_size is not None
    if not tiled:
        if spec.buffer is not None:
            raise ParameterError("--buffer needs --tile-size: a block processed in one piece has no tile buffer")
        return info, None
    grid = _plan(spec, info)
    check_engine(spec.engine, grid)
    WorkStore(spec.work_dir or default_work_dir(spec.out_dir)).check_free()  # before any cluster starts
    return info, grid


def check_out_dir(out_dir) -> None:
    """ParameterError unless ``out_dir`` is a folder, or can be made one, that this
    process may write to (checked before any work; nothing is created)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ParameterError(f"output folder {out} is a file, not a folder")
    parent = out
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ParameterError(f"cannot make output folder {out}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ParameterError(f"cannot write to output folder {out}: {parent} is not writable")


def auto_tiled(spec: JobSpec, info: BlockInfo | None = None) -> JobSpec:
    """``spec`` with the tile size :func:`pipeline.tiling.tile_size_for_budget` chooses
    when it has none and a memory budget the whole block would not fit (else ``spec``).

    ``info``: the block's header, read from ``spec.input_path`` when not given.
    Raises ParameterError (a :class:`pipeline.tiling.BudgetError` when no tile fits).
    """
    if spec.tile_size is not None or spec.memory_budget is None:
        return spec
    info = info or read_info(spec.input_path)
    buffer = spec.params.reach() if spec.buffer is None else float(spec.buffer)
    size = tile_size_for_budget(info.n_points, info.mins, info.maxs, budget=spec.memory_budget, buffer=buffer)
    return spec if size is None else dataclasses.replace(spec, tile_size=size)


def _plan(spec: JobSpec, info: BlockInfo) -> TileGrid:
    reach = spec.params.reach()
    buffer = reach if spec.buffer is None else float(spec.buffer)
    origin = spec.grid_origin if spec.grid_origin is not None else info.origin[:2]
    if spec.tile_size is None:  # one tile holding the whole block
        size = max(info.maxs[0] - origin[0], info.maxs[1] - origin[1]) + 1.0
        if origin[0] > info.mins[0] or origin[1] > info.mins[1]:
            raise ParameterError("with no --tile-size the grid origin must lie below the block's minimum x and y")
        return plan_grid(info.mins, info.maxs, tile_size=size, buffer=buffer, grid_origin=origin, reach=reach)
    return plan_grid(info.mins, info.maxs, tile_size=spec.tile_size, buffer=buffer, grid_origin=origin, reach=reach)


def _job_record(spec: JobSpec, info: BlockInfo, grid: TileGrid, work: str) -> dict:
    return {
        "input_path": spec.input_path,
        "out_dir": spec.out_dir,
        "params": spec.params.model_dump(mode="json"),
        "tile_size": spec.tile_size,
        "buffer": grid.buffer,
        "grid": grid.to_dict(),
        "work_dir": work,
        "labelled_laz": spec.labelled_laz,
        "info": dataclasses.asdict(info),
        "failed_tiles": [],
    }


def _run_tiled(spec, info, client, t0, progress, cancel) -> JobOutcome:
    timings = {}
    grid = _plan(spec, info)
    check_engine(spec.engine, grid)
    out_dir = Path(spec.out_dir)
    made = [d for d in (out_dir, *out_dir.parents) if not d.exists()]  # deepest first
    work = spec.work_dir or default_work_dir(spec.out_dir)
    store = WorkStore(work)
    try:
        with store.lock():  # one job per work store: another would delete this one's tiles
            store.remove()  # an earlier job's tiles and results there must not mix with this job's
            store.claim()  # refused if the folder holds anything that is not a work store's
            return _run_tiled_locked(spec, info, client, t0, progress, cancel, grid, store, timings)
    finally:
        for folder in made:  # folders this run made for its outputs and left empty
            if not folder.is_dir() or any(folder.iterdir()):
                break
            folder.rmdir()


def _run_tiled_locked(spec, info, client, t0, progress, cancel, grid, store, timings) -> JobOutcome:
    record = _job_record(spec, info, grid, store.url)
    keep_work = False
    try:
        store.put_json(JOB_KEY, record)
        _check_cancel(cancel)
        index = tile_block(info, grid, store, chunk_points=spec.chunk_points, engine=spec.engine, client=client,
                           gather=lambda futures: _results(client, futures, cancel, store))
        timings["tile"] = time.perf_counter() - t0
        tiles = [t for t in index["tiles"] if t["n_core"] > 0]
        t = time.perf_counter()
        try:
            record["ground_stats"] = _block_ground_stats(store, tiles, spec, client, cancel, info.n_points)
            store.put_json(JOB_KEY, record)
            timings["ground"] = time.perf_counter() - t
            t = time.perf_counter()
            summaries, failed = _run_tiles(store, tiles, spec, client, progress, cancel)
        except (TileFailed, JobCancelled, ClusterLost):
            keep_work = True  # everything needed to re-run or resume stays in the work store
            raise
        timings["process"] = time.perf_counter() - t
        if failed:
            keep_work = True
            record["failed_tiles"] = sorted(failed)
            store.put_json(JOB_KEY, record)
        t = time.perf_counter()
        outcome = _finish(store, record, index, summaries, sorted(failed))
        timings["merge_write"] = time.perf_counter() - t
        timings["total"] = time.perf_counter() - t0
        outcome.timings = timings
        return outcome
    finally:
        if not keep_work:
            store.remove()


def _describe(tile: dict) -> str:
    x0, y0, x1, y1 = tile["core"]
    return f"tile {tile['id']} (core x {x0:.2f}..{x1:.2f}, y {y0:.2f}..{y1:.2f}, {tile['n_buffered']} points)"


def _error_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:300]}"


def _run_tiles(store, tiles, spec, client, progress, cancel) -> tuple[list[dict], dict[int, str]]:
    params_json = spec.params.model_dump_json()
    inject = set(spec.inject_failure)
    total = len(tiles)
    by_id = {t["id"]: t for t in tiles}
    canary = tiles[0]["id"] if tiles else None
    summaries: list[dict] = []
    failed: dict[int, str] = {}
    if progress:
        progress(0, total)

    def fail_canary(tid: int, exc: BaseException):
        return TileFailed(
            f"{_describe(by_id[tid])} failed after {TILE_RETRIES + 1} attempts: {_error_line(exc)}",
            tid,
            hint=f"; its data is kept in {store.url} (run the job's tiles again with --work {store.url} --resume)",
        )

    if client is None:
        for i, t in enumerate(tiles):
            _check_cancel(cancel)
            err = None
            for _ in range(TILE_RETRIES + 1):
                try:
                    summaries.append(_kept(process_tile(store.url, t["id"], params_json, t["id"] in inject), store, t))
                    err = None
                    break
                except OrchardError:
                    raise
                except Exception as exc:  # noqa: BLE001 - recorded per tile, as on dask
                    err = exc
            if err is not None:
                if t["id"] == canary:
                    raise fail_canary(t["id"], err)
                failed[t["id"]] = _error_line(err)
            if progress:
                progress(i + 1, total)
        return summaries, failed

    token = uuid.uuid4().hex[:8]
    futures = {}
    for t in tiles:
        fut = client.submit(
            process_tile,
            store.url,
            t["id"],
            params_json,
            t["id"] in inject,
            key=f"orchard-tile-{t['id']}-{token}",
            retries=TILE_RETRIES,
            pure=False,
            priority=1 if t["id"] == canary else 0,
        )
        futures[fut] = t["id"]
    done_count = 0
    with contextlib.closing(_completed(client, futures, cancel, store)) as done:
        for tid, fut in done:
            if fut.status == "finished":
                summaries.append(_kept(fut.result(), store, by_id[tid]))
            else:
                exc = fut.exception()
                if isinstance(exc, OrchardError):
                    raise exc
                if tid == canary:
                    raise fail_canary(tid, exc)
                failed[tid] = _error_line(exc)
            done_count += 1
            if progress:
                progress(done_count, total)
    summaries.sort(key=lambda s: s["tile_id"])
    return summaries, failed


def _results(client, futures: list, cancel, store: WorkStore) -> list:
    """The results of dask ``futures`` as they finish (in that order), stopping like
    :func:`_completed` on a cancel or a cluster left without workers."""
    with contextlib.closing(_completed(client, dict.fromkeys(futures), cancel, store)) as done:
        return [fut.result() for _, fut in done]


def _completed(client, futures: dict, cancel, store: WorkStore):
    """Yield ``(futures[f], f)`` for each dask future ``f`` as it finishes.

    Raises JobCancelled when ``cancel`` is set, and ClusterLost after NO_WORKER_TIMEOUT
    seconds without any worker; the futures still pending when it stops (or is closed)
    are cancelled.
    """
    from distributed import wait

    pending = set(futures)
    last_worker_seen = time.monotonic()
    last_check = 0.0
    try:
        while pending:
            _check_cancel(cancel)
            try:
                res = wait(pending, timeout=0.5, return_when="FIRST_COMPLETED")
            except TimeoutError:
                now = time.monotonic()
                if now - last_check > 5.0:
                    last_check = now
                    if client.scheduler_info().get("workers"):
                        last_worker_seen = now
                    elif now - last_worker_seen > NO_WORKER_TIMEOUT:
                        raise ClusterLost(
                            f"no dask worker for {NO_WORKER_TIMEOUT:.0f} s (they died or left; their logs say why) "
                            f"with {len(pending)} tiles to go",
                            hint=f"; start workers and resume with --work {store.url} --resume",
                        ) from None
                continue
            for fut in res.done:
                pending.discard(fut)
                yield futures[fut], fut
    finally:
        if pending:
            client.cancel(list(pending))


def _open_files_allow(n: int) -> bool:
    """Whether this process may hold ``n`` more open files, after raising its soft limit
    towards the hard one if needed (False: read arrays into memory instead)."""
    try:
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        in_use = len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else 64
        need = in_use + n
        if soft != resource.RLIM_INFINITY and soft < need:
            target = need if hard == resource.RLIM_INFINITY else min(hard, need)
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        return soft == resource.RLIM_INFINITY or soft >= need
    except (ImportError, OSError, ValueError):
        return False


def _finish(store: WorkStore, record: dict, index: dict, summaries: list[dict], failed: list[int]) -> JobOutcome:
    info = BlockInfo(**{k: tuple(v) if isinstance(v, list) else v for k, v in record["info"].items()})
    params = PipelineParams.model_validate(record["params"])
    summaries = sorted(summaries, key=lambda s: s["tile_id"])
    origin = np.asarray(index["origin"][:2], dtype=np.float64)
    dead = [np.asarray(t["core"], dtype=np.float64) - np.r_[origin, origin] for t in index["tiles"] if t["id"] in set(failed)]
    merged = reconcile_trunks(
        [_tile_trunks(s) for s in summaries],
        # the tiles' own clustering radii (they follow the trees' spacing): the smallest
        cluster_radius=min((s.get("cluster_radius", params.trunks.at_spacing(None).cluster_radius) for s in summaries),
                           default=params.trunks.at_spacing(None).cluster_radius),
        fallback_radius=params.segment.max_crown_radius,
        dead_zones=np.array(dead).reshape(-1, 4),
    )
    merged = _without_trunks_between_rows(merged, params)
    if merged.n_trees == 0:
        raise _no_trees(info)
    trees, layout = _with_rows(_trees_table(summaries, merged, info.origin), params.rows, _replanted(summaries, merged))
    fields = ("index",) + _Labels.FIELDS
    # each memory-mapped array holds a file descriptor: with hundreds of tiles the usual
    # limit of 1024 ran out after every tile was done ("Too many open files")
    mmap = _open_files_allow(len(fields) * len(summaries) + 64)
    parts = []
    for s in summaries:
        key = result_key(s["tile_id"])
        part = {f: store.get_array(f"{key}/{f}.npy", mmap=mmap) for f in fields}
        part["map"] = merged.id_maps[s["tile_id"]]
        parts.append(part)
    labels = _Labels(parts, info.n_points)
    outputs = _write_outputs(
        Path(record["out_dir"]), info, labels, trees, labelled_laz=record["labelled_laz"], failed=failed, layout=layout
    )
    n_tiles = len([t for t in index["tiles"] if t["n_core"] > 0])
    return JobOutcome(info.n_points, merged.n_trees, n_tiles, list(failed), bool(failed), {}, outputs, trees)


# ------------------------------------------------------------------------- replay


def run_tile(work_dir: str, tile_id: int) -> dict:
    """Re-run one tile alone, in this process, from the work store of an earlier job."""
    store = WorkStore(work_dir)
    if not store.exists(JOB_KEY):
        raise ParameterError(f"{work_dir} holds no job (no {JOB_KEY}); give the --work folder of a tiled run")
    record = store.get_json(JOB_KEY)
    index = store.get_json(INDEX_KEY)
    if tile_id not in {t["id"] for t in index["tiles"] if t["n_core"] > 0}:
        raise ParameterError(f"tile {tile_id} is not a tile of the job in {work_dir}")
    params = PipelineParams.model_validate(record["params"])
    with store.lock():
        return process_tile(store.url, tile_id, params.model_dump_json())


def resume_job(
    work_dir: str,
    *,
    out_dir: str | None = None,
    client=None,
    progress: Callable[[int, int], None] | None = None,
    cancel: threading.Event | None = None,
) -> JobOutcome:
    """Process every tile of an earlier job that has no result yet, then merge.

    Used after the job stopped (first tile failed, cancelled, client lost): the tiles
    in the work store are reused, nothing is read from the input again but the outputs.
    """
    store = WorkStore(work_dir)
    if not store.exists(JOB_KEY):
        raise ParameterError(f"{work_dir} holds no job (no {JOB_KEY}); give the --work folder of a tiled run")
    with store.lock():
        return _resume(store, out_dir, client, progress, cancel)


def _resume(store: WorkStore, out_dir, client, progress, cancel) -> JobOutcome:
    record = store.get_json(JOB_KEY)
    index = store.get_json(INDEX_KEY)
    todo = [
        t for t in index["tiles"]
        if t["n_core"] > 0 and not store.exists(f"{result_key(t['id'])}/summary.pkl")
    ]
    spec = JobSpec(record["input_path"], out_dir or record["out_dir"], params=PipelineParams.model_validate(record["params"]))
    if todo and "ground_stats" not in record:  # stopped before the block's ground statistics were taken
        tiles = [t for t in index["tiles"] if t["n_core"] > 0]
        record["ground_stats"] = _block_ground_stats(store, tiles, spec, client, cancel, record["info"]["n_points"])
        store.put_json(JOB_KEY, record)
    if todo:
        _run_tiles(store, todo, spec, client, progress, cancel)
    return _finish_job(store, out_dir)


def finish_job(work_dir: str, *, out_dir: str | None = None) -> JobOutcome:
    """Merge the stored tile results of a job again and write its outputs.

    Tiles still without results stay missing (the outcome is then partial). The work
    store is removed when nothing is missing.
    """
    store = WorkStore(work_dir)
    if not store.exists(JOB_KEY):
        raise ParameterError(f"{work_dir} holds no job (no {JOB_KEY}); give the --work folder of a tiled run")
    with store.lock():
        return _finish_job(store, out_dir)


def _finish_job(store: WorkStore, out_dir: str | None) -> JobOutcome:
    t0 = time.perf_counter()
    record = store.get_json(JOB_KEY)
    if out_dir is not None:
        out_dir = os.path.abspath(out_dir)
        check_job_paths(record["input_path"], out_dir, store.url)
        record["out_dir"] = out_dir
    index = store.get_json(INDEX_KEY)
    summaries, missing = [], []
    for t in index["tiles"]:
        if t["n_core"] == 0:
            continue
        key = f"{result_key(t['id'])}/summary.pkl"
        if store.exists(key):
            summaries.append(store.get_object(key))
        else:
            missing.append(t["id"])
    try:
        outcome = _finish(store, record, index, summaries, missing)
    except NoTreesError:
        if not missing:
            raise
        n = len([t for t in index["tiles"] if t["n_core"] > 0])
        raise ParameterError(  # not "no trees": most of the block has not been processed
            f"{len(missing)} of the job's {n} tiles have no result yet, and the others hold no tree; "
            f"process them with --work {store.url} --resume"
        ) from None
    record["failed_tiles"] = missing
    if missing:
        store.put_json(JOB_KEY, record)
    else:
        store.remove()
    outcome.timings = {"total": time.perf_counter() - t0}
    return outcome
