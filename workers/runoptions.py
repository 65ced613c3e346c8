"""How a job runs, beside what it computes (:class:`pipeline.jobparams.JobParams`): the
tiler's engine, the embedded cluster's workers, a worker's memory budget and the points
read at a time. None of them changes a job's outputs but through the tile size a memory
budget chooses for a block without one (the budget and the workers that will run its tiles,
:func:`workers.jobspec.auto_tiled`), and that size is stored with the job; so none is
stored with a job: the command line takes them as options, the service from its settings."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from pipeline.chunks import CHUNK_POINTS

#: workers of an embedded dask cluster unless a command or setting says otherwise
WORKERS = 2


class RunOptions(BaseModel):
    """How to run a job: the tiler's engine and the dask workers' number and memory."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

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

    @property
    def memory_budget(self) -> float | None:
        """Bytes one worker may use (None: no budget)."""
        return None if self.worker_memory is None else self.worker_memory * 1e9
