"""A processing job: one block in, ``trees.parquet`` and ``points.parquet`` out.

Two paths share the same per-tile summary, merge and output code:

- **single block** (no client, no tile size): read the whole block, run the pipeline
  in this process, write the outputs — the fast path;
- **tiled**: the tiler writes buffered tiles to the work store; one task per tile
  (:mod:`workers.dispatch`: a dask task when a client is given, else in this process)
  reads its tile from the work store, runs the pipeline on the buffered tile, crops to
  the core, writes its per-point labels to the work store and returns a small summary
  (trunks, partial metrics); the merge reconciles trunks and the outputs are streamed
  tile by tile (:mod:`workers.outputs`).

The failure policy is :mod:`workers.tilestate`'s: a first tile that keeps failing stops
the job; a later one is recorded in ``JobOutcome.failed_tiles`` and the job finishes
without it, partial, keeping its work store to re-run that tile alone and merge again
(:mod:`workers.replay`).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

from pipeline.blockinfo import BlockInfo, read_info
from pipeline.budget import fits_whole, range_points
from pipeline.mapsample import REPORT_POINTS, sample_stride
from pipeline.parquet import sampled_tree_ids
from pipeline.reading import read_points
from pipeline.tiling import TileGrid
from workers.cellranges import aligned, index_from_cells, split_block
from workers.counting import count_block
from workers.dispatch import (
    block_ground_stats,
    check_cancel,
    cluster_threads,
    gather,
    process_tiles,
    run_task,
    settle_slot_trees,
)
from workers.jobspec import (
    ClusterLost,
    JobCancelled,
    JobOutcome,
    JobSpec,
    TileFailed,
    auto_tiled,
    budgeted,
    grid_origin,
    plan_tiles,
)
from workers.outputs import Labels, merge_and_write
from workers.replay import merge_stored
from workers.captures import capture_of
from workers.tasks import process, summarise
from workers.settling import settle_index
from workers.tiler import check_engine, read_sample, tile_block
from workers.workstore import JOB_KEY, WorkStore, default_work_dir


def run_job(
    spec: JobSpec,
    *,
    client=None,
    progress: Callable[[int, int], None] | None = None,
    cancel: threading.Event | None = None,
    points: np.ndarray | None = None,
    on_tiles: Callable[[JobSpec], None] | None = None,
    counting: Callable[[int, int], None] | None = None,
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
    points : (n, 3) float64, optional
        The block's local coordinates, read already by :func:`workers.jobspec.budgeted`,
        which kept it whole: a job in this process uses them instead of reading the file
        again, and does not run the memory budget a second time.
    on_tiles : callable (spec), optional
        Told the job's spec with the tile size its memory budget chose, when the job
        counted its block itself (:func:`splits_while_counting`).
    counting : callable (ranges counted, ranges), optional
        Progress of that count, as each range is (for more than one).

    Raises
    ------
    InputError, ParameterError, NoTreesError, TileFailed, JobCancelled
    """
    t0 = time.perf_counter()
    info = read_info(spec.input_path)
    if client is not None:  # its workers count the block, each its own ranges of the file
        if splits_while_counting(spec, info):  # and split it by cell in the same pass
            return _run_tiled(spec, info, client, t0, progress, cancel, split=True, on_tiles=on_tiles,
                              counting=counting)
        spec = auto_tiled(spec, info, count=partial(count_block, client=client, cancel=cancel),
                          n_workers=cluster_threads(client))
    elif points is None:  # counted here: a block that stays whole is then decoded once, not twice
        spec, points = budgeted(spec, info)
    # given points, the caller's budget kept the block whole: it is not budgeted again
    if spec.tiling.tile_size is None and client is None:
        return _run_single(spec, info, t0, progress, cancel, points)
    return _run_tiled(spec, info, client, t0, progress, cancel)


def _run_single(spec, info, t0, progress, cancel, xyz=None) -> JobOutcome:
    timings = {}
    params = spec.params
    if progress:
        progress(0, 1)
    if xyz is None:
        xyz, _ = read_points(info.path, chunk_points=spec.run.chunk_points)
    timings["read"] = time.perf_counter() - t0
    check_cancel(cancel)
    t = time.perf_counter()
    result = process(xyz, params, Path(info.path).name)
    timings["process"] = time.perf_counter() - t
    check_cancel(cancel)
    t = time.perf_counter()
    core = np.ones(len(xyz), dtype=bool)
    summary = summarise(0, xyz, core, result, None, info.origin, params)
    final_ids = []

    def labels(merged):
        single = Labels.single(result, merged.id_maps[0])
        final_ids.append(single.parts[0]["tree_id"])
        return single

    n_trees, trees, outputs = merge_and_write(
        [summary], info, params, Path(spec.out_dir), labels=labels, labelled_laz=spec.labelled_laz, failed=[],
        capture=capture_of(spec), timings=timings,
    )
    timings["merge_write"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0
    if progress:
        progress(1, 1)
    return JobOutcome(info.n_points, n_trees, 1, [], False, timings, outputs, trees,
                      report_sample(xyz, final_ids[0], info.origin))


def report_sample(xyz: np.ndarray, tree_id: np.ndarray, origin, max_points: int = REPORT_POINTS) -> dict:
    """Every :func:`pipeline.mapsample.sample_stride`-th point of a whole block: the
    points ``service.reports.sampling.sample_points`` takes from the block's file and
    ``points.parquet``, from memory.

    Parameters
    ----------
    xyz : (n, 3) float64 — the block's points, local [m]
    tree_id : (n,) int — their final tree ids (``points.parquet``'s)
    origin : (3,) float — the block's origin [m]

    Returns
    -------
    dict: ``xy`` (m, 2) float64 [m], ``tree_id`` (m,) int64, ``origin`` (3,) float64, ``max_points``
    """
    stride = sample_stride(len(xyz), max_points)
    return {"xy": xyz[::stride, :2].copy(), "tree_id": np.asarray(tree_id[::stride], dtype=np.int64),
            "origin": np.asarray(origin, dtype=np.float64), "max_points": max_points}


def _stored_sample(store: WorkStore, info: BlockInfo, points_parquet: str) -> dict | None:
    """:func:`report_sample` of a tiled job: the points the tiler kept, with their tree
    ids in ``points_parquet`` (None without a kept sample: the report reads the files)."""
    kept = read_sample(store, info.n_points)
    if kept is None:
        return None
    xy, index = kept
    return {"xy": xy, "tree_id": sampled_tree_ids(points_parquet, index, sample_stride(info.n_points)),
            "origin": np.asarray(info.origin, dtype=np.float64), "max_points": REPORT_POINTS}


def merged_outcome(store: WorkStore, info: BlockInfo, record: dict, index: dict, summaries: list[dict],
                   failed: list[int]) -> JobOutcome:
    """The task that ends a tiled job: :func:`workers.replay.merge_stored` of its work
    store (the outputs written) and the report map's sample (:func:`_stored_sample`)."""
    outcome = merge_stored(store, record, index, summaries, failed)
    if outcome.sample is None and outcome.outputs.get("points"):
        outcome.sample = _stored_sample(store, info, outcome.outputs["points"])
    return outcome


def _job_record(spec: JobSpec, info: BlockInfo, grid: TileGrid, work: str) -> dict:
    """What the work store keeps of a tiled job to resume it or re-run a tile: the job's
    parameters whole (:func:`workers.jobspec.stored_job` reads them back) and its grid."""
    return {
        "input_path": spec.input_path,
        "out_dir": spec.out_dir,
        "job": spec.job.model_dump(mode="json"),
        "grid": grid.to_dict(),
        "work_dir": work,
        "labelled_laz": spec.labelled_laz,
        "info": dataclasses.asdict(info),
        "failed_tiles": [],
        "capture": dataclasses.asdict(capture_of(spec)),
    }


def splits_while_counting(spec: JobSpec, info: BlockInfo) -> bool:
    """Whether a job on a cluster counts its block for the memory budget and splits it
    into ranges sorted by cell in the same pass (:mod:`workers.cellranges`): a plain
    LAS/LAZ block (a COPC block is counted from its hierarchy) with no tile size given,
    tiled by the laspy engine, that may not fit whole."""
    budget = spec.run.memory_budget
    return (spec.tiling.tile_size is None and budget is not None and not fits_whole(info.n_points, budget)
            and not info.copc and spec.run.engine == "laspy")


def _run_tiled(spec, info, client, t0, progress, cancel, *, split: bool = False, on_tiles=None,
               counting=None) -> JobOutcome:
    """A tiled job; ``split``: its tile size is chosen from the count of the same pass
    that splits the block (:func:`splits_while_counting`), its grid planned then."""
    timings = {}
    grid = None
    if not split:
        grid = plan_tiles(spec.job, info)
        check_engine(spec.run.engine, grid)
    out_dir = Path(spec.out_dir)
    made = [d for d in (out_dir, *out_dir.parents) if not d.exists()]  # deepest first
    work = spec.work_dir or default_work_dir(spec.out_dir)
    store = WorkStore(work)
    try:
        with store.lock():  # one job per work store: another would delete this one's tiles
            store.remove()  # an earlier job's tiles and results there must not mix with this job's
            store.claim()  # refused if the folder holds anything that is not a work store's
            return _run_tiled_locked(spec, info, client, t0, progress, cancel, grid, store, timings, on_tiles,
                                     counting)
    finally:
        for folder in made:  # folders this run made for its outputs and left empty
            if not folder.is_dir() or any(folder.iterdir()):
                break
            folder.rmdir()


def _run_tiled_locked(spec, info, client, t0, progress, cancel, grid, store, timings, on_tiles=None,
                      counting=None) -> JobOutcome:
    keep_work = False
    try:
        check_cancel(cancel)

        def wait(futures, progress=None):
            return gather(client, futures, cancel, store, progress)

        split = None
        if grid is None:  # one pass over the file counts it and writes its points once, sorted by cell
            sample, cells, parts = split_block(info, grid_origin(spec.tiling, info), store,
                                               voxel_size=spec.params.graph.voxel_size, client=client,
                                               gather=wait, progress=counting)
            spec = auto_tiled(spec, info, count=lambda info, voxel_size: sample, n_workers=cluster_threads(client))
            if on_tiles:
                on_tiles(spec)
            grid = plan_tiles(spec.job, info)
            check_engine(spec.run.engine, grid)
            split = (cells, parts) if aligned(grid, cells) else None
        record = _job_record(spec, info, grid, store.url)
        store.put_json(JOB_KEY, record)
        check_cancel(cancel)
        if split is not None:
            index = index_from_cells(info, grid, *split, store)
        else:
            # a worker's range of the file follows the memory budget, as its tiles do
            chunk = range_points(spec.run.memory_budget, spec.run.chunk_points)
            index = tile_block(info, grid, store, chunk_points=chunk, engine=spec.run.engine, client=client,
                               gather=wait)
        timings["tile"] = time.perf_counter() - t0
        tiles = [t for t in index["tiles"] if t["n_core"] > 0]
        t = time.perf_counter()
        try:
            record["ground_stats"] = block_ground_stats(store, tiles, spec, client, cancel, info.n_points)
            store.put_json(JOB_KEY, record)
            timings["ground"] = time.perf_counter() - t
            t = time.perf_counter()
            summaries, failed = process_tiles(store, tiles, spec, client, progress, cancel)
            index, summaries = settle_index(store, index, summaries, failed, info.n_points)  # a streamed block's counts
            if not failed:  # trees on open slots, decided on the block's rows: tiles that differ run again
                summaries, failed = settle_slot_trees(store, record, index, summaries, spec, client, progress, cancel)
        except (TileFailed, JobCancelled, ClusterLost):
            keep_work = True  # everything needed to re-run or resume stays in the work store
            raise
        timings["process"] = time.perf_counter() - t
        if failed:
            keep_work = True
            record["failed_tiles"] = sorted(failed)
            store.put_json(JOB_KEY, record)
        t = time.perf_counter()
        if client is None:
            outcome = merged_outcome(store, info, record, index, summaries, sorted(failed))
        else:  # the merge streams every point's labels: a worker's memory, not the submitting process's
            outcome = run_task(client, merged_outcome, store, info, record, index, summaries, sorted(failed),
                               key="orchard-merge", store=store)
        timings["merge_write"] = time.perf_counter() - t
        timings["total"] = time.perf_counter() - t0
        timings.update(outcome.timings)  # the merge's own (seasons)
        outcome.timings = timings
        return outcome
    finally:
        if not keep_work:
            store.remove()
