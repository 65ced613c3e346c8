"""``/v1/jobs/{job_id}/...``: a finished job's results (trees as JSON pages, Parquet and CSV
downloads with byte ranges, the HTML report and its map)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, HTMLResponse

from service.api.deps import SettingsDep, StoreDep, TenantDep
from service.api.downloads import DownloadResponse
from service.api.schemas import UNFINISHED, TreesPage
from service.headers import report_policy
from service.jobfolders import job_dir
from service.reports import report as reports
from service.reports.outputs import ensure_report, job_output, require_output

router = APIRouter()


@router.get("/jobs/{job_id}/trees", response_model=TreesPage, tags=["results"], responses=UNFINISHED)
def job_trees(
    job_id: str,
    tenant: TenantDep,
    store: StoreDep,
    settings: SettingsDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
    row: Annotated[int | None, Query(ge=1, le=1_000_000, description="only the trees of this row")] = None,
    position_min: Annotated[int | None, Query(ge=1, le=1_000_000, description="only trees at this position or later")] = None,
    position_max: Annotated[int | None, Query(ge=1, le=1_000_000, description="only trees at this position or earlier")] = None,
    young: Annotated[bool | None, Query(description="only young trees (true) or only the others (false)")] = None,
):
    """The job's trees as JSON pages, in address order, optionally filtered by row,
    position range and young; ``total`` counts the trees that pass the filters."""
    _, path = job_output(store, settings, tenant, job_id, "trees.parquet")
    rows = [t for t in reports.trees_records(require_output(path, "trees.parquet"))
            if _wanted(t, row=row, position_min=position_min, position_max=position_max, young=young)]
    return TreesPage(items=rows[offset : offset + limit], total=len(rows), limit=limit, offset=offset)


def _wanted(tree: dict, *, row, position_min, position_max, young) -> bool:
    """Whether a tree passes the filters (a block without rows has no address: an
    address filter then keeps no tree)."""
    pos = tree.get("position")
    return ((row is None or tree.get("row") == row)
            and (position_min is None or (pos is not None and pos >= position_min))
            and (position_max is None or (pos is not None and pos <= position_max))
            and (young is None or bool(tree.get("young")) == young))


def _file(path: Path, media_type: str, filename: str) -> FileResponse:
    return DownloadResponse(path, media_type=media_type, filename=filename)


_PARQUET = {200: {"content": {"application/vnd.apache.parquet": {}}, "description": "GeoParquet / Parquet file"}}


@router.api_route("/jobs/{job_id}/trees.parquet", methods=["GET", "HEAD"], tags=["results"], responses={**_PARQUET, **UNFINISHED}, response_class=FileResponse)
def job_trees_parquet(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    _, path = job_output(store, settings, tenant, job_id, "trees.parquet")
    return _file(require_output(path, "trees.parquet"), "application/vnd.apache.parquet", f"trees-{job_id}.parquet")


@router.api_route("/jobs/{job_id}/rows.parquet", methods=["GET", "HEAD"], tags=["results"], responses={**_PARQUET, **UNFINISHED}, response_class=FileResponse)
def job_rows_parquet(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    """The orchard rows found in the block: one row per orchard row with its line (GeoParquet)."""
    _, path = job_output(store, settings, tenant, job_id, "rows.parquet")
    return _file(require_output(path, "rows.parquet"), "application/vnd.apache.parquet", f"rows-{job_id}.parquet")


@router.api_route("/jobs/{job_id}/gaps.parquet", methods=["GET", "HEAD"], tags=["results"], responses={**_PARQUET, **UNFINISHED}, response_class=FileResponse)
def job_gaps_parquet(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    """The empty planting slots between two trees of a row (GeoParquet points)."""
    _, path = job_output(store, settings, tenant, job_id, "gaps.parquet")
    return _file(require_output(path, "gaps.parquet"), "application/vnd.apache.parquet", f"gaps-{job_id}.parquet")


@router.api_route("/jobs/{job_id}/history.parquet", methods=["GET", "HEAD"], tags=["results"], responses={**_PARQUET, **UNFINISHED}, response_class=FileResponse)
def job_history_parquet(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    """A capture's orchard block history up to this capture: one row per tree per capture (Parquet)."""
    _, path = job_output(store, settings, tenant, job_id, "history.parquet")
    return _file(require_output(path, "history.parquet"), "application/vnd.apache.parquet", f"history-{job_id}.parquet")


@router.api_route("/jobs/{job_id}/points.parquet", methods=["GET", "HEAD"], tags=["results"], responses={**_PARQUET, **UNFINISHED}, response_class=FileResponse)
def job_points_parquet(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    _, path = job_output(store, settings, tenant, job_id, "points.parquet")
    return _file(require_output(path, "points.parquet"), "application/vnd.apache.parquet", f"points-{job_id}.parquet")


@router.api_route(
    "/jobs/{job_id}/trees.csv",
    methods=["GET", "HEAD"],
    tags=["results"],
    responses={200: {"content": {"text/csv": {}}, "description": "one row per tree"}, **UNFINISHED},
    response_class=FileResponse,
)
def job_trees_csv(job_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    _, trees = job_output(store, settings, tenant, job_id, "trees.parquet")
    csv_path = job_dir(settings, job_id) / "trees.csv"
    if not csv_path.exists():
        reports.write_trees_csv(require_output(trees, "trees.parquet"), csv_path)
    return _file(csv_path, "text/csv", f"trees-{job_id}.csv")


@router.get(
    "/jobs/{job_id}/report",
    tags=["results"],
    response_class=HTMLResponse,
    responses={200: {"content": {"text/html": {}}, "description": "per-tree report with a map"}, **UNFINISHED},
)
def job_report(job_id: str, request: Request, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    job, _ = job_output(store, settings, tenant, job_id, "trees.parquet")
    with request.app.state.report_lock:
        path = ensure_report(store, settings, job)
    text = path.read_text(encoding="utf-8")
    # its scripts are inlined (it opens from disk offline): the policy names them by hash
    return HTMLResponse(text, headers={"Content-Security-Policy": report_policy(text)})


@router.api_route(
    "/jobs/{job_id}/map.png",
    methods=["GET", "HEAD"],
    tags=["results"],
    response_class=FileResponse,
    responses={200: {"content": {"image/png": {}}, "description": "map of the block with numbered trees"}, **UNFINISHED},
)
def job_map(job_id: str, request: Request, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    job, _ = job_output(store, settings, tenant, job_id, "trees.parquet")
    with request.app.state.report_lock:
        ensure_report(store, settings, job)
    return _file(require_output(job_dir(settings, job_id) / "map.png", "map"), "image/png", f"map-{job_id}.png")
