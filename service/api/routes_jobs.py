"""``/v1/jobs``: submit a job for a block, list, read and cancel jobs (results: `routes_results`)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response

from service.api.deps import StoreDep, TenantDep, wake_runner
from service.api.schemas import JSON_BODY, ErrorBody, Job, JobCreate, JobsPage, job_out
from service.jobrequests import request_job, stored

router = APIRouter()


@router.post("/jobs", response_model=Job, status_code=201, tags=["jobs"], summary="Submit a job for a block",
         responses={429: {"model": ErrorBody, "description": "the tenant has as many jobs queued as its quota allows"},
                    **JSON_BODY})
def create_job(body: JobCreate, request: Request, response: Response, tenant: TenantDep, store: StoreDep):
    block = store.blocks.get(tenant["id"], body.block_id)
    params = request_job(body.params, body.tiling and body.tiling.model_dump())
    job = store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job=stored(params))
    wake_runner(request.app)
    response.headers["Location"] = f"/v1/jobs/{job['id']}"
    return job_out(job)


@router.get("/jobs", response_model=JobsPage | list[Job], tags=["jobs"], summary="List jobs, newest first, a page at a time")
def list_jobs(
    tenant: TenantDep,
    store: StoreDep,
    state: Annotated[Literal["queued", "running", "done", "failed", "cancelled"] | None, Query()] = None,
    block_id: Annotated[str | None, Query(max_length=200)] = None,
    schedule_id: Annotated[str | None, Query(max_length=200)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
    paged: Annotated[bool, Query(description="false: the page's jobs as a bare list, as before pages (deprecated)")] = True,
):
    filters = {"state": state, "block_id": block_id, "schedule_id": schedule_id}
    items = [job_out(j) for j in store.jobs.list(tenant["id"], **filters, limit=limit, offset=offset)]
    if not paged:
        return items
    return JobsPage(items=items, total=store.jobs.count(tenant["id"], **filters), limit=limit, offset=offset)


@router.get("/jobs/{job_id}", response_model=Job, tags=["jobs"])
def get_job(job_id: str, tenant: TenantDep, store: StoreDep):
    job = store.jobs.get(tenant["id"], job_id)
    return job_out(job, capture=store.orchard_blocks.capture_of_job(tenant["id"], job["id"]))


@router.delete(
    "/jobs/{job_id}",
    response_model=Job,
    status_code=202,
    tags=["jobs"],
    summary="Cancel a queued or running job",
    responses={409: {"model": ErrorBody, "description": "the job has already finished"}},
)
def cancel_job(job_id: str, request: Request, tenant: TenantDep, store: StoreDep):
    job = store.jobs.request_cancel(tenant["id"], job_id)
    runner = request.app.state.runner
    if runner is not None:
        runner.cancel(job_id)
    return job_out(job)
