"""The browser's routes: sign-in and sign-out, the pages (``/`` leads to them), the map data, the offline API docs.

Pages need a session (else they send the browser to ``/signin``); the map data, like
the ``/v1`` API, takes either a session or a bearer token. Another farm's job is a 404,
as in the API.
"""

from __future__ import annotations

import functools
import gzip
import html
import threading
from typing import Annotated
from urllib.parse import quote

from fastapi import APIRouter, Form, Request
from fastapi.openapi.docs import get_redoc_html
from fastapi.responses import HTMLResponse, RedirectResponse, Response

from service import sessions
from service.auth import UnauthorizedError
from service.db.errors import NotFoundError
from service.jobfolders import job_dir
from service.reports import mapdata
from service.reports.outputs import job_output, require_output
from service.reports.report import atomic_write
from service import pages

router = APIRouter(include_in_schema=False)
_map_lock = threading.Lock()  # one footprint computation at a time (it reads the whole block)

# pages name the farm and carry its CSRF token: not cached (nor framed: service.headers says that for every response)
_NO_STORE = {"Cache-Control": "no-store"}


def _store(request: Request):
    return request.app.state.store


def _page_session(request: Request):
    """(session, tenant) of a page request, or None (the caller sends it to sign in)."""
    return sessions.current_session(request, _store(request))


def _to_signin(request: Request) -> RedirectResponse:
    return RedirectResponse(f"/signin?next={quote(request.url.path)}", status_code=303)


def _safe_next(path: str | None) -> str:
    # only a path on this server: "//evil.example" or "https://..." would send the farm away
    if not path or not path.startswith("/") or path.startswith("//") or "\\" in path:
        return "/blocks"
    return path


@router.get("/")
def root() -> RedirectResponse:
    return RedirectResponse("/blocks")


@router.get("/signin")
def signin_form(request: Request, next: str = "/blocks") -> HTMLResponse:
    if _page_session(request) is not None:
        return RedirectResponse(_safe_next(next), status_code=303)
    return HTMLResponse(pages.signin_page(next_path=_safe_next(next)), headers=_NO_STORE)


@router.post("/signin")
def signin(request: Request, token: Annotated[str, Form(max_length=500)] = "",
           next: Annotated[str, Form(max_length=2000)] = "/blocks") -> Response:
    if not sessions.same_origin(request):  # another site signing this browser in as someone else
        return HTMLResponse(pages.signin_page(error="sign in from this server's own page"), status_code=403, headers=_NO_STORE)
    try:
        sid, sess, _ = sessions.sign_in(request, _store(request), token)
    except UnauthorizedError:
        page = pages.signin_page(error="That token is not known here, or has expired or been revoked. Check it and try again.",
                                  next_path=_safe_next(next))
        return HTMLResponse(page, status_code=401, headers=_NO_STORE)
    resp = RedirectResponse(_safe_next(next), status_code=303)
    resp.set_cookie(sessions.COOKIE, sid, max_age=sessions.SESSION_SECONDS, httponly=True, samesite="strict",
                    secure=request.url.scheme == "https", path="/")
    return resp


@router.post("/signout")
def signout(request: Request, csrf: Annotated[str, Form(max_length=200)] = "") -> Response:
    found = _page_session(request)
    if found is not None:
        sessions.check_csrf(request, found[0], csrf)
        sessions.sessions_of(request).close_session(request.cookies[sessions.COOKIE])
    resp = RedirectResponse("/signin", status_code=303)
    resp.delete_cookie(sessions.COOKIE, path="/", httponly=True, samesite="strict")
    return resp


@router.get("/blocks")
def blocks(request: Request) -> Response:
    found = _page_session(request)
    if found is None:
        return _to_signin(request)
    sess, tenant = found
    return HTMLResponse(pages.blocks_page(tenant_name=tenant["name"], csrf=sess.csrf), headers=_NO_STORE)


@router.get("/jobs/{job_id}")
def job(job_id: str, request: Request) -> Response:
    found = _page_session(request)
    if found is None:
        return _to_signin(request)
    sess, tenant = found
    try:
        _store(request).jobs.get(tenant["id"], job_id)
    except NotFoundError:
        page = pages.message_page(title="No such job", message=f"This farm has no job {job_id}.",
                                   tenant_name=tenant["name"], csrf=sess.csrf)
        return HTMLResponse(page, status_code=404, headers=_NO_STORE)
    return HTMLResponse(pages.job_page(job_id=job_id, tenant_name=tenant["name"], csrf=sess.csrf), headers=_NO_STORE)


@router.get("/web/jobs/{job_id}/map.json")
def job_map_data(job_id: str, request: Request) -> Response:
    """What the job page's map draws (see `service.reports.mapdata`); computed once, kept
    gzipped as ``map.json.gz`` beside the job's outputs."""
    store, settings = _store(request), request.app.state.settings
    tenant = sessions.request_tenant(request, store)
    job_rec, trees = job_output(store, settings, tenant, job_id, "trees.parquet")
    trees = require_output(trees, "trees.parquet")
    cached = job_dir(settings, job_id) / "map.json"
    packed = cached.with_name("map.json.gz")  # a quarter of the bytes over a farm's slow link
    with _map_lock:
        if not packed.exists() or packed.stat().st_mtime < trees.stat().st_mtime:
            _, points = job_output(store, settings, tenant, job_id, "points.parquet")
            block = store.blocks.get(job_rec["tenant_id"], job_rec["block_id"])
            data = mapdata.build_map_data(trees, block_path=block.get("path"), points_parquet=points)
            cached.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(packed, gzip.compress(mapdata.to_json(data).encode("utf-8"), compresslevel=6, mtime=0))
    headers = {"Cache-Control": "private, max-age=60", "Vary": "Accept-Encoding"}
    body = packed.read_bytes()
    if "gzip" in request.headers.get("accept-encoding", ""):
        return Response(body, media_type="application/json", headers={**headers, "Content-Encoding": "gzip"})
    return Response(gzip.decompress(body), media_type="application/json", headers=headers)


@router.get("/docs")
def swagger(request: Request) -> HTMLResponse:
    # FastAPI's own page starts Swagger UI with an inline script, which the CSP refuses
    title = html.escape(f"{request.app.title} — API")
    static = pages.STATIC_URL
    return HTMLResponse(
        '<!doctype html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f'<title>{title}</title><link rel="icon" href="{pages.FAVICON}" type="image/svg+xml">'
        f'<link rel="stylesheet" href="{static}/vendor/swagger-ui/swagger-ui.css"></head>\n'
        f'<body><div id="swagger-ui" data-openapi-url="{html.escape(request.app.openapi_url)}"></div>\n'
        f'<script src="{static}/vendor/swagger-ui/swagger-ui-bundle.js"></script>\n'
        f'<script src="{static}/swagger-init.js"></script>\n</body></html>\n'
    )


#: ReDoc's sidebar footer draws its maker's logo from the internet; the page draws ours instead
_REDOC_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"


@functools.cache
def _redoc_script() -> bytes:
    text = (pages.STATIC_DIR / "vendor" / "redoc" / "redoc.standalone.js").read_text(encoding="utf-8")
    return text.replace(_REDOC_LOGO, pages.FAVICON).encode("utf-8")


@router.get("/redoc/redoc.standalone.js")
def redoc_script() -> Response:
    return Response(_redoc_script(), media_type="text/javascript", headers={"Cache-Control": "public, max-age=3600"})


@router.get("/redoc")
def redoc(request: Request) -> HTMLResponse:
    return get_redoc_html(
        openapi_url=request.app.openapi_url,
        title=f"{request.app.title} — API",
        redoc_js_url="/redoc/redoc.standalone.js",
        redoc_favicon_url=pages.FAVICON,
        with_google_fonts=False,
    )

