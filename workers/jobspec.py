"""A job's contract: what to process (:class:`JobSpec`), what came of it
(:class:`JobOutcome`), how a run can stop (:mod:`workers.stops`' classes, named here
too), the checks made before any work and the planning of its tiles."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.blockinfo import BlockInfo, read_info
from pipeline.budget import fits_whole, job_tile_size
from pipeline.errors import ParameterError
from pipeline.jobparams import JobParams, TilingParams
from pipeline.params import PipelineParams
from pipeline.reading import read_counted, read_points, sample_density
from pipeline.tiling import TileGrid, plan_grid
from workers.captures import check_date, check_previous
from workers.runoptions import RunOptions
from workers.stops import ClusterLost, JobCancelled, TileFailed  # noqa: F401  (the contract names them)
from workers.tiler import check_engine
from workers.workstore import WorkStore, absolute_url, default_work_dir, own_entry

#: the files a job writes into its output folder (:mod:`workers.outputs` writes them)
OUTPUT_NAMES = ("points.parquet", "labelled.laz", "trees.parquet", "rows.parquet", "gaps.parquet", "history.parquet")


@dataclass
class JobSpec:
    """What to process and how: the block, the outputs' folder, the job's parameters
    ``job`` (a :class:`pipeline.jobparams.JobParams`, checked when it was made: the
    pipeline's ``params`` and the ``tiling``) and how to run it, ``run``
    (:class:`workers.runoptions.RunOptions`, which change no output).

    ``tiling.tile_size`` None processes the block as one tile, unless it would need more
    than ``run.worker_memory`` in one piece: then :func:`auto_tiled` chooses tiles that
    fit it (None: no budget). ``tiling.buffer`` None uses ``params.reach()``;
    ``tiling.grid_origin`` None uses the block origin (floor of the header minimum), in
    the input CRS; ``work_dir`` None uses ``out_dir/_work``. ``inject_failure`` lists
    tiles whose task raises (testing the failure policy only).

    A job processes one *capture* of an orchard block (:mod:`workers.seasons`):

    - ``previous``: the output folder of the block's latest processed capture (made
      absolute); the trees are registered onto its trees and keep their keys, and the
      change columns and ``history.parquet`` continue its history. None: the block's
      first capture (keys 1..K, every tree new).
    - ``capture_id``: the capture's id in the history; None: the input's file stem.
    - ``captured_at``: the capture's date (ISO ``YYYY-MM-DD``) given by the caller, used
      when the file's header has no creation date.
    - ``captured_at_fallback``: the date used when neither has one: the upload or
      arrival day the service passes (the command line: the file's modification day,
      which is also the default).
    """

    input_path: str
    out_dir: str
    job: JobParams = field(default_factory=JobParams)
    run: RunOptions = field(default_factory=RunOptions)
    work_dir: str | None = None
    labelled_laz: bool = False
    inject_failure: tuple[int, ...] = ()
    previous: str | None = None
    capture_id: str | None = None
    captured_at: str | None = None
    captured_at_fallback: str | None = None

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
        if self.previous is not None:
            self.previous = check_previous(self.previous)
        if self.captured_at is not None:
            self.captured_at = check_date(self.captured_at, "job.captured_at")

    @property
    def params(self) -> PipelineParams:
        """The pipeline's parameters (``job.pipeline``)."""
        return self.job.pipeline

    @property
    def tiling(self) -> TilingParams:
        """The tiling (``job.tiling``)."""
        return self.job.tiling


def stored_job(record: dict) -> JobParams:
    """The parameters of the job a work store's record (``job.json``) describes: stored
    whole; a store written before they were (its ``params``, its grid's tile size and
    buffer) is read as it was."""
    if "job" in record:
        return JobParams.model_validate(record["job"])
    tiling = {"tile_size": record.get("tile_size"), "buffer": (record.get("grid") or {}).get("buffer")}
    return JobParams.model_validate({"pipeline": record.get("params") or {}, "tiling": tiling})


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
            "which the run replaces: ", hint="choose another {job.out_dir}", param="job.out_dir", value=out_dir,
        )
    if work_dir is not None and (work_dir.startswith("file://") or "://" not in work_dir):
        work = Path(work_dir.removeprefix("file://")).resolve()
        if work in out.parents and own_entry(out.relative_to(work).parts[0]):
            raise ParameterError(
                f"{{job.out_dir}} {out_dir} lies inside the folder {out.relative_to(work).parts[0]} of {{job.work_dir}} "
                f"{work_dir}, which is deleted when the job is done: ", hint="put the outputs elsewhere",
                param="job.out_dir", value=out_dir,
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
    # every stride-th point of the block for the report's map, when the job had them in
    # memory (``xy`` local [m], final ``tree_id``, ``origin``, ``max_points``): the report
    # then need not decode the block again
    sample: dict | None = None


def check_job(spec: JobSpec, *, tiled: bool | None = None) -> tuple[BlockInfo, TileGrid | None]:
    """Check the input and the tiling parameters of a job without writing anything.

    Returns the block's header information and, for a tiled job, the planned grid.
    Raises InputError or ParameterError.
    """
    info = read_info(spec.input_path)
    check_out_dir(spec.out_dir)
    if tiled is None:
        tiled = spec.tiling.tile_size is not None
    if not tiled:
        if spec.tiling.buffer is not None:
            raise ParameterError("{tiling.buffer} needs {tiling.tile_size}: a block processed in one piece has no tile buffer",
                                 param="tiling.buffer", value=spec.tiling.buffer)
        return info, None
    grid = plan_tiles(spec.job, info)
    check_engine(spec.run.engine, grid)
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


def auto_tiled(spec: JobSpec, info: BlockInfo | None = None, *, count: Callable | None = None,
               n_workers: int | None = None) -> JobSpec:
    """``spec`` with a tile size chosen for its memory budget when it has none and the
    whole block would not fit the budget (else ``spec``).

    The size comes from the block's points and voxel-graph nodes counted per square cell
    (:func:`pipeline.reading.sample_density`, read only for a block that does not surely
    fit whole) and the job's actual grid (:func:`pipeline.budget.job_tile_size`: the largest
    core that keeps the budget, cut into as many tiles that ``n_workers`` finish soonest).
    ``info``: the block's header, read from ``spec.input_path`` when not given.
    ``count(info, voxel_size)`` → the density sample: how to count (default: in this
    process; :func:`workers.counting.count_block` with a client counts on the cluster).
    ``n_workers``: the workers that will run its tiles (default ``spec.run.workers``, the
    embedded cluster's).
    Raises ParameterError (a :class:`pipeline.budget.BudgetError` when no tile fits),
    InputError (truncated or corrupt point data met while counting).
    """
    budget = spec.run.memory_budget
    if spec.tiling.tile_size is not None or budget is None:
        return spec
    info = info or read_info(spec.input_path)
    if fits_whole(info.n_points, budget):
        return spec
    voxel_size = spec.params.graph.voxel_size
    sample = count(info, voxel_size) if count else sample_density(info.path, info=info, voxel_size=voxel_size)
    # no client yet (orchard process counts before its cluster starts): the embedded
    # cluster's workers, which will run the tiles (2 unless --workers or the service says)
    workers = n_workers or spec.run.workers
    size = job_tile_size(sample, info.mins, info.maxs, budget=budget, buffer=spec.job.buffer(),
                         grid_origin=grid_origin(spec.tiling, info), n_workers=workers)
    return spec if size is None else dataclasses.replace(spec, job=spec.job.with_tile_size(size))


def budgeted(spec: JobSpec, info: BlockInfo | None = None) -> tuple[JobSpec, np.ndarray | None]:
    """:func:`auto_tiled`, counting in this process, and the block's local coordinates
    (:func:`pipeline.reading.read_points`) when it stays in one piece: read with the
    count when it was counted, else here, before the job imports the pipeline (a damaged
    block fails in a fraction of the time). A job given them (``run_job(points=...)``)
    does not decode the block again. None when it is tiled (points read to count it are
    let go before any tile)."""
    kept = []

    def count(info, voxel_size):
        if info.copc:  # counted from its hierarchy: no pass over its points
            return sample_density(info.path, info=info, voxel_size=voxel_size)
        xyz, sample = read_counted(info.path, info=info, voxel_size=voxel_size)
        kept.append(xyz)
        return sample

    spec = auto_tiled(spec, info, count=count)
    if spec.tiling.tile_size is not None:
        return spec, None
    if not kept:
        kept.append(read_points(spec.input_path, chunk_points=spec.run.chunk_points)[0])
    return spec, kept[0]


def grid_origin(tiling: TilingParams, info: BlockInfo) -> tuple[float, float]:
    """The corner [m] of a job's tile grid: the one given, else the block's origin (the
    budget's tile size is chosen on the grid the job will plan)."""
    return tiling.grid_origin if tiling.grid_origin is not None else info.origin[:2]


def plan_tiles(job: JobParams, info: BlockInfo) -> TileGrid:
    """The tile grid of a job over the block ``info`` (one tile holding the whole block
    when ``job`` has no tile size): where the tiling's limits that depend on the block are
    checked, once, against its actual grid (how many tiles, how many copies of a point,
    an origin the block lies above).

    Raises
    ------
    ParameterError
    """
    tiling, origin = job.tiling, grid_origin(job.tiling, info)
    size = tiling.tile_size
    if size is None:  # one tile holding the whole block
        size = max(info.maxs[0] - origin[0], info.maxs[1] - origin[1]) + 1.0
        if origin[0] > info.mins[0] or origin[1] > info.mins[1]:
            raise ParameterError("with no {tiling.tile_size} the grid origin must lie below the block's minimum x and y",
                                 param="tiling.grid_origin", value=tuple(origin))
    return plan_grid(info.mins, info.maxs, tile_size=size, buffer=job.buffer(), grid_origin=origin,
                     reach=job.pipeline.reach())
