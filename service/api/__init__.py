"""The HTTP API under ``/v1``: blocks, jobs, results, schedules and orchard blocks, plus ``/healthz``.

One module per resource (`routes_blocks`, `routes_jobs`, `routes_results`,
`routes_schedules`, `routes_orchard_blocks`, `routes_webhooks`, `routes_health`), the bodies in `schemas`, the dependencies in
`deps`, upload streaming in `uploads`, result files with byte ranges in `downloads`, the
API document's operationIds in `openapi`; `service.app.create_app` wires them into an app.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends

from service.api import (
    routes_blocks,
    routes_jobs,
    routes_orchard_blocks,
    routes_results,
    routes_schedules,
    routes_webhooks,
)
from service.api.queryparams import no_unknown_query
from service.api.schemas import ERRORS


def v1_router() -> APIRouter:
    """The ``/v1`` routes, each documented with the error answers in `schemas.ERRORS`."""
    v1 = APIRouter(prefix="/v1", responses=ERRORS, dependencies=[Depends(no_unknown_query)])
    for routes in (routes_blocks, routes_jobs, routes_results, routes_schedules, routes_orchard_blocks, routes_webhooks):
        v1.include_router(routes.router)
    return v1
