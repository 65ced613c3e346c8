"""The job model: how a block is tiled (`TilingParams`) beside what the pipeline does
with it (`PipelineParams`), together a `JobParams`.

A `JobParams` is what a job *computes*: it is made once from a request (an API body or
the command line's options), stored whole with the job and shipped to the workers.
How a job *runs* (the tiler's engine, workers, memory budget) is no part of it:
:mod:`workers.runoptions`. Every tiling default and bound is written here once (the
bounds are :mod:`pipeline.tilelimits`' constants): the command line's tiling options and
the API's tiling body are generated from `TilingParams`. The limits that depend on the
block (how many tiles, how many copies of a point, PDAL's narrower buffer, an origin
below the block) are checked at planning, against the block's actual grid
(:func:`workers.jobspec.plan_tiles`). All lengths are metres.
"""

from __future__ import annotations

from pydantic import Field, model_validator

from pipeline.params import PipelineParams, _Model
from pipeline.tilelimits import MAX_BUFFER, MAX_TILE_SIZE, MIN_TILE_SIZE, check_buffer, check_grid_origin


class TilingParams(_Model):
    """Split the block into square tiles processed on the dask workers."""

    tile_size: float | None = Field(
        None, ge=MIN_TILE_SIZE, le=MAX_TILE_SIZE,
        description="tile edge length [m]",
    )  # None: one tile, unless the block would not fit a worker's memory budget (then tiles chosen to fit it)
    buffer: float | None = Field(
        None, ge=0.0, le=MAX_BUFFER,
        description="overlap on every side [m]; default = the parameters' reach",
    )
    grid_origin: tuple[float, float] | None = Field(
        None,
        description="a corner of the tile grid, input CRS [m]; default: the block's minimum, rounded down",
    )

    @model_validator(mode="after")
    def _origin(self) -> "TilingParams":
        if self.grid_origin is not None:
            check_grid_origin(self.grid_origin)
        return self


class JobParams(_Model):
    """Everything a job computes besides its paths: the pipeline and the tiling.

    Checked once, when made: each field's bounds, and a given buffer against the
    parameters' reach (narrower, tiles would cut crowns whatever the block).
    """

    pipeline: PipelineParams = PipelineParams()
    tiling: TilingParams = TilingParams()

    @model_validator(mode="after")
    def _buffer_covers_reach(self) -> "JobParams":
        if self.tiling.buffer is not None:
            check_buffer(self.tiling.buffer, self.pipeline.reach())
        return self

    def buffer(self) -> float:
        """The tile buffer [m]: the one given, else the parameters' reach."""
        return self.pipeline.reach() if self.tiling.buffer is None else float(self.tiling.buffer)

    def with_tile_size(self, tile_size: float) -> "JobParams":
        """These parameters with tiles of ``tile_size`` [m] (a memory budget's choice)."""
        return self.model_copy(update={"tiling": self.tiling.model_copy(update={"tile_size": float(tile_size)})})
