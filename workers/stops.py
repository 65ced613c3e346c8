"""How a job's run can stop short of its outputs: its own classes, apart from the job's
contract (:mod:`workers.jobspec`) so that the service sorts them without importing the
pipeline (:mod:`service.failures`)."""

from __future__ import annotations

from pipeline.errors import OrchardError


class Stopped(OrchardError):
    """A tiled job stopped with its work store kept: ``reason`` says why, ``hint`` how to
    go on from that store (the command line's advice: the service never resumes a job)."""

    def __init__(self, reason: str, hint: str = ""):
        super().__init__(reason, hint=hint)
        self.reason = reason


class TileFailed(Stopped):
    """A tile's processing failed after its retries (the message names the tile)."""

    def __init__(self, reason: str, tile_id: int, hint: str = ""):
        super().__init__(reason, hint)
        self.tile_id = tile_id


class JobCancelled(OrchardError):
    """The job was cancelled before it finished."""


class ClusterLost(Stopped):
    """The dask cluster had no workers for too long; the job stopped (it can be resumed)."""
