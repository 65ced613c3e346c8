"""``/v1/orchard-blocks``: named orchard blocks, their captures over the seasons, and the
block's history (per tree, per capture).

A capture is an uploaded file (as ``POST /v1/blocks`` lands it) processed by a job (as
``POST /v1/jobs`` queues it) that registers its trees to the block's previous capture;
docs/orchard-blocks.md says how the routes map.
"""

from __future__ import annotations

from datetime import date
from pathlib import Path as FilePath
from typing import Annotated

import pyarrow.parquet as pq
from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from starlette.exceptions import HTTPException

from service.api.deps import SettingsDep, StoreDep, TenantDep, wake_runner
from service.api.downloads import DownloadResponse
from service.api.schemas import (
    JSON_BODY,
    OrchardCapture,
    OrchardCaptureCreate,
    ErrorBody,
    OrchardBlock,
    OrchardBlockCreate,
    TreeHistory,
    orchard_capture_out,
    orchard_block_out,
)
from service.api.uploads import UPLOAD_BODY, UPLOAD_SLACK, receive_upload
from service.db.block_files import accept_block
from service.db.errors import NotFoundError
from service.db.jobstore import Store
from service.jobfolders import job_dir
from service.jobrequests import request_job, stored
from service.seasons import HISTORY
from service.settings import Settings

router = APIRouter()
_QUEUE_FULL = {429: {"model": ErrorBody, "description": "the tenant has as many jobs queued as its quota allows"}}


@router.post("/orchard-blocks", response_model=OrchardBlock, status_code=201, tags=["orchard blocks"],
             summary="Create a named orchard block", responses={409: {"model": ErrorBody, "description": "the name is taken"},
                                                                 **JSON_BODY})
def create_orchard_block(body: OrchardBlockCreate, response: Response, tenant: TenantDep, store: StoreDep):
    rec = store.orchard_blocks.create(tenant["id"], body.name)
    response.headers["Location"] = f"/v1/orchard-blocks/{rec['id']}"
    return orchard_block_out(rec)


@router.get("/orchard-blocks", response_model=list[OrchardBlock], tags=["orchard blocks"])
def list_orchard_blocks(tenant: TenantDep, store: StoreDep):
    return [orchard_block_out(r) for r in store.orchard_blocks.list(tenant["id"])]


@router.get("/orchard-blocks/{orchard_block_id}", response_model=OrchardBlock, tags=["orchard blocks"])
def get_orchard_block(orchard_block_id: str, tenant: TenantDep, store: StoreDep):
    return orchard_block_out(store.orchard_blocks.get(tenant["id"], orchard_block_id))


def _capture_json_schema() -> dict:
    """`OrchardCaptureCreate`'s schema, its parts referring to the document's components (the
    parameters and the tiling, which ``POST /v1/jobs`` puts there)."""
    schema = OrchardCaptureCreate.model_json_schema(ref_template="#/components/schemas/{model}")
    schema.pop("$defs", None)
    return schema


_CAPTURE_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {"schema": _capture_json_schema()},
            **UPLOAD_BODY["requestBody"]["content"],
        },
    }
}


@router.post(
    "/orchard-blocks/{orchard_block_id}/captures",
    response_model=OrchardCapture,
    status_code=201,
    tags=["orchard blocks"],
    summary="Add a capture: a LAS/LAZ file (multipart field 'file') or an uploaded block (JSON block_id)",
    openapi_extra=_CAPTURE_BODY,
    responses={**_QUEUE_FULL, **JSON_BODY},
)
async def add_capture(
    orchard_block_id: str,
    request: Request,
    response: Response,
    tenant: TenantDep,
    store: StoreDep,
    settings: SettingsDep,
    captured_at: Annotated[date | None, Query(description="the day of the capture (YYYY-MM-DD) of a file sent as "
                                                          "multipart; used when the file has no date of its own")] = None,
):
    # the block first: a file for another farm's block is refused before it is received
    await run_in_threadpool(store.orchard_blocks.get, tenant["id"], orchard_block_id)
    if request.headers.get("content-type", "").lower().startswith("multipart/"):
        declared = request.headers.get("content-length", "")
        await run_in_threadpool(store.quotas.check_storage, tenant["id"],
                                max(int(declared) - UPLOAD_SLACK if declared.isdigit() else 0, 1))
        part = await receive_upload(request, settings)
        block, _ = await run_in_threadpool(
            accept_block, store, blocks_dir=settings.blocks_dir, tenant_id=tenant["id"], tmp_path=part.tmp_path,
            sha256=part.sha.hexdigest(), size_bytes=part.size, filename=part.filename)
        body = OrchardCaptureCreate(block_id=block["id"], captured_at=captured_at)
    else:
        if "json" not in request.headers.get("content-type", "").lower():
            raise HTTPException(415, "send the capture as multipart/form-data with the file in the field 'file' "
                                     "(curl -F file=@scan.laz), or as JSON {\"block_id\": ...} of an uploaded block with "
                                     "the header 'Content-Type: application/json'")
        body = OrchardCaptureCreate.model_validate_json(await request.body())  # (held to the small body limit: BodyLimit)
        if captured_at is not None and body.captured_at is None:
            body.captured_at = captured_at
    rec = await run_in_threadpool(_queue_capture, store, tenant, orchard_block_id, body)
    wake_runner(request.app)
    response.headers["Location"] = f"/v1/orchard-blocks/{orchard_block_id}/captures/{rec['id']}"
    return orchard_capture_out(rec)


def _queue_capture(store: Store, tenant: dict, orchard_block_id: str, body: OrchardCaptureCreate) -> dict:
    job = request_job(body.params, body.tiling and body.tiling.model_dump())
    return store.orchard_blocks.create_capture(tenant_id=tenant["id"], orchard_block_id=orchard_block_id, block_id=body.block_id,
                                job=stored(job),
                                captured_at=body.captured_at.isoformat() if body.captured_at else None)


@router.get("/orchard-blocks/{orchard_block_id}/captures", response_model=list[OrchardCapture], tags=["orchard blocks"],
            summary="A block's captures in arrival order (the order they are processed in)")
def list_captures(orchard_block_id: str, tenant: TenantDep, store: StoreDep):
    return [orchard_capture_out(c) for c in store.orchard_blocks.list_captures(tenant["id"], orchard_block_id)]


@router.get("/orchard-blocks/{orchard_block_id}/captures/{capture_id}", response_model=OrchardCapture, tags=["orchard blocks"])
def get_capture(orchard_block_id: str, capture_id: str, tenant: TenantDep, store: StoreDep):
    rec = store.orchard_blocks.get_capture(tenant["id"], capture_id)
    if rec["orchard_block_id"] != orchard_block_id:
        raise NotFoundError(f"orchard block {orchard_block_id!r} has no capture {capture_id!r}")
    return orchard_capture_out(rec)


def block_history(store: Store, settings: Settings, tenant: dict, orchard_block_id: str) -> FilePath:
    """The block's ``history.parquet``: that of its latest processed capture, which holds
    every capture before it (a failed capture leaves it as it was). NotFoundError while
    there is none."""
    store.orchard_blocks.get(tenant["id"], orchard_block_id)
    latest = store.orchard_blocks.latest_done_capture(tenant["id"], orchard_block_id)
    if latest is None:
        raise NotFoundError(f"orchard block {orchard_block_id} has no processed capture yet, so no history; "
                            f"GET /v1/orchard-blocks/{orchard_block_id}/captures shows where its captures are")
    path = job_dir(settings, latest["job_id"]) / HISTORY
    if not path.is_file():
        raise NotFoundError(f"the latest processed capture of orchard block {orchard_block_id} (job {latest['job_id']}) "
                            "has no history.parquet on the server")
    return path


_PARQUET = {200: {"content": {"application/vnd.apache.parquet": {}}, "description": "Parquet file"}}


@router.api_route("/orchard-blocks/{orchard_block_id}/history.parquet", methods=["GET", "HEAD"], tags=["orchard blocks"],
                  responses=_PARQUET, response_class=FileResponse,
                  summary="The block's history: one row per tree per capture (key, capture, date, address, sizes, status)")
def orchard_block_history(orchard_block_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    path = block_history(store, settings, tenant, orchard_block_id)
    return DownloadResponse(path, media_type="application/vnd.apache.parquet", filename=f"history-{orchard_block_id}.parquet")


@router.get("/orchard-blocks/{orchard_block_id}/trees/{tree_key}/history", response_model=TreeHistory, tags=["orchard blocks"],
            summary="One tree over the block's captures, oldest first")
def tree_history(orchard_block_id: str, tree_key: Annotated[int, Path(ge=0, le=2**63 - 1)], tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    path = block_history(store, settings, tenant, orchard_block_id)
    items = tree_history_rows(path, tree_key)
    if not items:
        raise NotFoundError(f"orchard block {orchard_block_id} has no tree {tree_key} in its history")
    return TreeHistory(orchard_block_id=orchard_block_id, tree_key=tree_key, items=items)


def tree_history_rows(path: FilePath, tree_key: int) -> list[dict]:
    """The rows of one tree in a ``history.parquet``, oldest first (NaN as null)."""
    rows = pq.read_table(str(path), filters=[("tree_key", "=", tree_key)]).to_pylist()  # row groups of other keys skipped
    for r in rows:
        for k, v in r.items():
            if isinstance(v, float) and v != v:
                r[k] = None
    return sorted(rows, key=lambda r: str(r.get("captured_at") or ""))  # stable: the file's order within a day
