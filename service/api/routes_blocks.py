"""``/v1/blocks``: upload a block (LAS/LAZ, or PLY, PCD, E57, text converted to LAZ) (streamed, deduplicated by content), list and read blocks."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from pipeline.errors import ParameterError
from pipeline.formats.convert import parse_crs_option
from service.api.deps import SettingsDep, StoreDep, TenantDep
from service.api.schemas import Block, block_out
from service.api.uploads import UPLOAD_BODY, UPLOAD_SLACK, receive_upload
from service.db.block_files import accept_block

router = APIRouter()


@router.post(
    "/blocks",
    response_model=Block,
    status_code=201,
    tags=["blocks"],
    openapi_extra=UPLOAD_BODY,
    responses={200: {"model": Block, "description": "this file was uploaded before: the existing block"}},
    summary="Upload a block: LAS/LAZ, PLY, PCD, E57 or text (multipart field 'file')",
)
async def upload_block(
    request: Request, response: Response, tenant: TenantDep, store: StoreDep, settings: SettingsDep,
    crs: Annotated[str | None, Query(max_length=40, description="EPSG:NNNN: the CRS of a PLY, PCD or text file's points "
                                     "(they store none; an E57 file's own is used otherwise)")] = None,
    columns: Annotated[str | None, Query(max_length=400, description="a text file's columns in order, comma-separated, "
                                         "among them x, y and z; default: its header line, else x y z first")] = None,
):
    """A LAS/LAZ file is stored as it is; a PLY, PCD, E57 or text (x y z) file is converted
    to LAZ (docs/inputs.md), and the LAZ is the block's file."""
    try:
        crs_epsg = parse_crs_option(crs)
    except ParameterError as exc:
        raise ParameterError(f"crs: {exc.message}") from None
    declared = request.headers.get("content-length", "")  # refused before the body is read; checked again after
    await run_in_threadpool(store.quotas.check_storage, tenant["id"], max(int(declared) - UPLOAD_SLACK if declared.isdigit() else 0, 1))
    part = await receive_upload(request, settings)
    block, created = await run_in_threadpool(
        accept_block,
        store,
        blocks_dir=settings.blocks_dir,
        tenant_id=tenant["id"],
        tmp_path=part.tmp_path,
        sha256=part.sha.hexdigest(),
        size_bytes=part.size,
        filename=part.filename,
        crs_epsg=crs_epsg,
        columns=columns,
    )
    response.status_code = 201 if created else 200
    response.headers["Location"] = f"/v1/blocks/{block['id']}"
    return block_out(block)


@router.get("/blocks", response_model=list[Block], tags=["blocks"])
def list_blocks(
    tenant: TenantDep,
    store: StoreDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
):
    return [block_out(b) for b in store.blocks.list(tenant["id"], limit=limit, offset=offset)]


@router.get("/blocks/{block_id}", response_model=Block, tags=["blocks"])
def get_block(block_id: str, tenant: TenantDep, store: StoreDep):
    return block_out(store.blocks.get(tenant["id"], block_id))
