"""Going on from a job's work store: merge the stored tile results and write the outputs
(:func:`finish_job`), run the tiles still without a result first (:func:`resume_job`),
or re-run one tile alone (:func:`run_tile`).

A tiled job that stops (its canary failed, it was cancelled, its cluster was lost) or
finishes partial keeps its work store: the job record, the tiles and every tile result.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline.blockinfo import BlockInfo
from pipeline.errors import NoTreesError, ParameterError
from workers.dispatch import block_ground_stats, process_tiles, settle_slot_trees
from workers.jobspec import JobOutcome, JobSpec, check_job_paths, stored_job
from workers.outputs import Labels, merge_and_write
from workers.captures import Capture
from workers.tasks import process_tile, result_key
from workers.tiler import INDEX_KEY
from workers.workstore import JOB_KEY, WorkStore


def merge_stored(store: WorkStore, record: dict, index: dict, summaries: list[dict], failed: list[int]) -> JobOutcome:
    """Merge the tile results kept in ``store`` and write the job's outputs.

    ``record``: the job record; ``index``: the tile index; ``summaries``: the results'
    summaries; ``failed``: the tiles without a result (their cores are dead zones to
    the merge). The outcome's timings hold only ``seasons`` (registration and keys).
    """
    info = BlockInfo(**{k: tuple(v) if isinstance(v, list) else v for k, v in record["info"].items()})
    params = stored_job(record).pipeline
    summaries = sorted(summaries, key=lambda s: s["tile_id"])
    origin = np.asarray(index["origin"][:2], dtype=np.float64)
    dead = [np.asarray(t["core"], dtype=np.float64) - np.r_[origin, origin] for t in index["tiles"] if t["id"] in set(failed)]

    def labels(merged) -> Labels:
        fields = ("index",) + Labels.FIELDS
        parts = []
        for s in summaries:
            key = result_key(s["tile_id"])
            part = {f: store.open_array(f"{key}/{f}.npy") for f in fields}
            part["map"] = merged.id_maps[s["tile_id"]]
            parts.append(part)
        return Labels(parts, info.n_points)

    capture = Capture(**record["capture"]) if record.get("capture") else None
    timings: dict = {}
    n_trees, trees, outputs = merge_and_write(
        summaries, info, params, Path(record["out_dir"]), labels=labels, labelled_laz=record["labelled_laz"],
        failed=failed, dead_zones=np.array(dead).reshape(-1, 4), capture=capture, timings=timings,
    )
    n_tiles = len([t for t in index["tiles"] if t["n_core"] > 0])
    return JobOutcome(info.n_points, n_trees, n_tiles, list(failed), bool(failed), timings, outputs, trees)


def run_tile(work_dir: str, tile_id: int) -> dict:
    """Re-run one tile alone, in this process, from the work store of an earlier job."""
    store = WorkStore(work_dir)
    if not store.exists(JOB_KEY):
        raise ParameterError(f"{work_dir} holds no job (no {JOB_KEY}); ", hint="give the {job.work_dir} folder of a tiled run")
    record = store.get_json(JOB_KEY)
    index = store.get_json(INDEX_KEY)
    if tile_id not in {t["id"] for t in index["tiles"] if t["n_core"] > 0}:
        raise ParameterError(f"tile {tile_id} is not a tile of the job in {work_dir}")
    params = stored_job(record).pipeline
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
        raise ParameterError(f"{work_dir} holds no job (no {JOB_KEY}); ", hint="give the {job.work_dir} folder of a tiled run")
    with store.lock():
        return _resume(store, out_dir, client, progress, cancel)


def _resume(store: WorkStore, out_dir, client, progress, cancel) -> JobOutcome:
    record = store.get_json(JOB_KEY)
    index = store.get_json(INDEX_KEY)
    todo = [
        t for t in index["tiles"]
        if t["n_core"] > 0 and not store.exists(f"{result_key(t['id'])}/summary.pkl")
    ]
    spec = JobSpec(record["input_path"], out_dir or record["out_dir"], job=stored_job(record))
    if todo and "ground_stats" not in record:  # stopped before the block's ground statistics were taken
        tiles = [t for t in index["tiles"] if t["n_core"] > 0]
        record["ground_stats"] = block_ground_stats(store, tiles, spec, client, cancel, record["info"]["n_points"])
        store.put_json(JOB_KEY, record)
    if todo:
        process_tiles(store, todo, spec, client, progress, cancel)
    _settle_stored(store, record, index, spec, client, progress, cancel)
    return _finish_job(store, out_dir)


def _settle_stored(store: WorkStore, record: dict, index: dict, spec: JobSpec, client, progress, cancel) -> None:
    """The block's trees on open slots, once every tile has a result: the tiles run
    with other trees there run again."""
    summaries, missing = _stored_summaries(store, index)
    if not missing:  # else a partial job: the block's rows are not all known
        settle_slot_trees(store, record, index, summaries, spec, client, progress, cancel)


def _stored_summaries(store: WorkStore, index: dict) -> tuple[list[dict], list[int]]:
    """The summaries of the tiles with a result in ``store``, and the tiles without one."""
    summaries, missing = [], []
    for t in index["tiles"]:
        if t["n_core"] == 0:
            continue
        key = f"{result_key(t['id'])}/summary.pkl"
        if store.exists(key):
            summaries.append(store.get_object(key))
        else:
            missing.append(t["id"])
    return summaries, missing


def finish_job(work_dir: str, *, out_dir: str | None = None) -> JobOutcome:
    """Merge the stored tile results of a job again and write its outputs.

    Tiles still without results stay missing (the outcome is then partial). The work
    store is removed when nothing is missing.
    """
    store = WorkStore(work_dir)
    if not store.exists(JOB_KEY):
        raise ParameterError(f"{work_dir} holds no job (no {JOB_KEY}); ", hint="give the {job.work_dir} folder of a tiled run")
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
    summaries, missing = _stored_summaries(store, index)
    try:
        outcome = merge_stored(store, record, index, summaries, missing)
    except NoTreesError:
        if not missing:
            raise
        n = len([t for t in index["tiles"] if t["n_core"] > 0])
        raise ParameterError(  # not "no trees": most of the block has not been processed
            f"{len(missing)} of the job's {n} tiles have no result yet, and the others hold no tree; ",
            hint=f"process them with {{job.work_dir}} {store.url} {{job.resume}}",
        ) from None
    record["failed_tiles"] = missing
    if missing:
        store.put_json(JOB_KEY, record)
    else:
        store.remove()
    outcome.timings = {"total": time.perf_counter() - t0}
    return outcome
