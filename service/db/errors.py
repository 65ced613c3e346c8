"""Errors of the job store's lookups and state changes; each edge (HTTP, command line)
maps them in its one place."""

from __future__ import annotations

from pipeline.errors import OrchardError


class NotFoundError(OrchardError):
    """An id (block, job, schedule, tile) that does not exist for this caller."""


class ConflictError(OrchardError):
    """The request conflicts with the state of a resource (e.g. results of an unfinished job)."""
