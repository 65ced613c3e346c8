"""The job model: how a block is tiled (`TilingParams`) beside what the pipeline does
with it (`PipelineParams`), together a `JobParams`.

Every tiling default and bound is written here once: the command line's tiling
options and the API's tiling body are generated from `TilingParams`, and a job's
parameters are checked by `JobParams` wherever it is made. Defaults that a deployment
sets (the workers, the memory budget) are applied at the edge from its settings, whose
own defaults are these (the memory budget's is the settings': a model has none). All
lengths are metres.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.params import PipelineParams, _Model
from pipeline.tilelimits import check_buffer, check_grid_origin, check_split_buffer, check_tiling

#: points read from a block at a time (bounded memory)
CHUNK_POINTS = 2_000_000
#: points of a report's map at most: every stride-th point of the block (:func:`sample_stride`)
REPORT_POINTS = 150_000
#: workers of an embedded dask cluster unless a command or setting says otherwise
WORKERS = 2


class TilingParams(_Model):
    """Split the block into square tiles processed on the dask workers."""

    tile_size: float | None = Field(
        None, ge=1.0, le=100_000.0,
        description="tile edge length [m]",
    )  # None: one tile, unless the block would not fit worker_memory (then tiles chosen to fit it)
    buffer: float | None = Field(
        None, ge=0.0, le=1_000.0,
        description="overlap on every side [m]; default = the parameters' reach",
    )
    grid_origin: tuple[float, float] | None = Field(
        None,
        description="a corner of the tile grid, input CRS [m]; default: the block's minimum, rounded down",
    )
    engine: Literal["laspy", "pdal"] = Field(
        "laspy", description="tiler engine (pdal needs PDAL's Python bindings)",
    )
    workers: int = Field(WORKERS, ge=1, le=256, description="workers of the embedded dask cluster")
    worker_memory: float | None = Field(
        None, gt=0.0, le=4096.0,
        description="memory budget of one worker [GB]: a block without a tile size that would need more in one piece "
        "is tiled, with tiles chosen to fit it",
    )  # None: no budget, a block without a tile size is one piece (a deployment sets one: ORCHARD_WORKER_MEMORY_GB)
    chunk_points: int = Field(CHUNK_POINTS, ge=1, le=1_000_000_000, description="points read at a time when tiling [points]")

    @model_validator(mode="after")
    def _tiles(self) -> "TilingParams":
        if self.grid_origin is not None:
            check_grid_origin(self.grid_origin)
        if self.tile_size is not None:
            check_tiling(self.tile_size, self.buffer)  # copies per point, when the buffer is given
            if self.engine == "pdal" and self.buffer is not None:
                check_split_buffer(self.tile_size, self.buffer)
        return self

    @property
    def memory_budget(self) -> float | None:
        """Bytes one worker may use (None: no budget)."""
        return None if self.worker_memory is None else self.worker_memory * 1e9


class JobParams(_Model):
    """Everything a job needs besides its paths: the pipeline and the tiling."""

    pipeline: PipelineParams = PipelineParams()
    tiling: TilingParams = TilingParams()

    @model_validator(mode="after")
    def _buffer_covers_reach(self) -> "JobParams":
        reach = self.pipeline.reach()
        t = self.tiling
        if t.buffer is not None:
            check_buffer(t.buffer, reach)
        if t.tile_size is not None:
            buffer = self.buffer()
            check_tiling(t.tile_size, buffer)
            if t.engine == "pdal":
                check_split_buffer(t.tile_size, buffer)
        return self

    def buffer(self) -> float:
        """The tile buffer [m]: the one given, else the parameters' reach."""
        return self.pipeline.reach() if self.tiling.buffer is None else float(self.tiling.buffer)


def sample_stride(n_points: int, max_points: int = REPORT_POINTS) -> int:
    """Every how-many-th point a sample of at most ``max_points`` of ``n_points`` takes
    (the first, then every stride-th): ceil(n_points / max_points), at least 1."""
    return max(1, -(-int(n_points) // max_points))


def first_sampled(start: int, stride: int) -> int:
    """Offset, in a run of points starting at the file's point ``start``, of the run's
    first point on the sample of every ``stride``-th point of the file (those whose index
    is a multiple of ``stride``): every reader of the sample picks the same points."""
    return (-int(start)) % int(stride)
