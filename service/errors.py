"""The one place where errors become HTTP responses.

Domain errors (`pipeline.errors`) carry no status code; `STATUS` maps them here, and
`service.wording` words them (a parameter as its request field; ``errors`` gives its
location in the body). Every error response is JSON ``{"detail": "<one line saying what was wrong and what to do>"}``
(validation errors add ``errors``, the list of fields). An unexpected exception becomes
a 500 with a short message: clients never see a traceback (it goes to the server log).
"""

from __future__ import annotations

import logging
import sqlite3

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from pipeline.errors import InputError, NoTreesError, OrchardError, ParameterError
from service.auth import UnauthorizedError
from service.db.errors import ConflictError, NotFoundError
from service.quotas import QueueQuotaExceeded, StorageQuotaExceeded
from service.wording import api_errors, api_words, disk_full

log = logging.getLogger("orchard.service")


class TooLargeError(StarletteHTTPException):
    """A request body above the configured limit (413)."""

    def __init__(self, detail: str) -> None:
        super().__init__(status_code=413, detail=detail)


class StalledUploadError(StarletteHTTPException):
    """An upload whose body stopped arriving, trickled, or outlasted its deadline (408);
    the connection is closed with it (the rest of the body is not read)."""

    def __init__(self, detail: str) -> None:
        super().__init__(status_code=408, detail=detail, headers={"Connection": "close"})


class ShuttingDownError(StarletteHTTPException):
    """A request the server cannot finish because it is stopping (503)."""

    def __init__(self, detail: str) -> None:
        super().__init__(status_code=503, detail=detail)


DISK_FULL_DETAIL = ("the server has no disk space left for this request; nothing of it was kept: try again "
                    "later (the operator has been told in the service log)")


STATUS: dict[type[Exception], int] = {
    UnauthorizedError: 401,
    NotFoundError: 404,
    ConflictError: 409,
    InputError: 422,
    ParameterError: 422,
    NoTreesError: 422,
    QueueQuotaExceeded: 429,
    StorageQuotaExceeded: 507,  # a quota is "insufficient storage" in WebDAV's quota extension (RFC 4331)
    OrchardError: 400,
}


def status_for(exc: Exception) -> int:
    """HTTP status of a domain error (most specific class wins)."""
    for cls in type(exc).__mro__:
        if cls in STATUS:
            return STATUS[cls]
    return 500


def validation_message(errors: list[dict]) -> str:
    """One readable line from pydantic/FastAPI validation errors."""
    parts = []
    for e in errors[:10]:
        loc = ".".join(str(p) for p in e.get("loc", ()) if p not in ("__root__",))
        msg = str(e.get("msg", "invalid value"))
        parts.append(f"{loc}: {msg}" if loc else msg)
    if len(errors) > 10:
        parts.append(f"... and {len(errors) - 10} more")
    return "invalid request: " + "; ".join(parts)


def body_problem(content_type: str | None, errors: list[dict]) -> tuple[int, str] | None:
    """Status and message of a request whose body is not a JSON object (sent without the
    JSON content type, not JSON at all, or missing), in words a client can act on; None
    when the errors are about the body's fields."""
    body = [e for e in errors if tuple(e.get("loc", ()))[:1] == ("body",)]
    if not body:
        return None
    media = (content_type or "").split(";", 1)[0].strip().lower()
    if media != "application/json" and not media.endswith("+json"):
        had = f"Content-Type {media!r}" if media else "no Content-Type"
        return 415, f"send the request body as JSON with the header 'Content-Type: application/json' (this request had {had})"
    for e in body:
        loc = tuple(e.get("loc", ()))
        if e.get("type") == "json_invalid":
            where = f" at character {loc[1]}" if len(loc) > 1 else ""
            return 422, f"the request body is not valid JSON ({(e.get('ctx') or {}).get('error', 'decode error')}{where})"
        if loc == ("body",) and e.get("type") == "missing":
            return 422, "the request has no body; send a JSON object (the fields are in the API document at /docs)"
        if loc == ("body",) and e.get("type") in ("model_attributes_type", "dict_type", "model_type"):
            return 422, "the request body must be a JSON object (the fields are in the API document at /docs)"
    return None


def _json_safe_errors(errors) -> list[dict]:
    out = []
    for e in list(errors)[:50]:
        out.append({"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))})
    return out


def error_response(status: int, detail: str, **extra) -> JSONResponse:
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    return JSONResponse({"detail": detail, **extra}, status_code=status, headers=headers)


def install_error_handlers(app: FastAPI) -> None:
    """Register the mapping on ``app``."""

    @app.exception_handler(OrchardError)
    async def _domain(request: Request, exc: OrchardError) -> JSONResponse:
        errors = api_errors(exc)
        extra = {} if errors is None else {"errors": errors}
        return error_response(status_for(exc), api_words(exc) or type(exc).__name__, **extra)

    @app.exception_handler(RequestValidationError)
    async def _request_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = list(exc.errors())
        problem = body_problem(request.headers.get("content-type"), errors)
        if problem is not None:
            return error_response(problem[0], problem[1])
        return error_response(422, validation_message(errors), errors=_json_safe_errors(errors))

    @app.exception_handler(ValidationError)
    async def _model_validation(request: Request, exc: ValidationError) -> JSONResponse:
        errors = exc.errors()
        return error_response(422, validation_message(errors), errors=_json_safe_errors(errors))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        resp = error_response(exc.status_code, detail)
        if exc.headers:
            resp.headers.update(exc.headers)
        return resp

    @app.exception_handler(ClientDisconnect)
    async def _gone(request: Request, exc: ClientDisconnect) -> JSONResponse:
        # the client hung up mid-request (an upload cut short): nothing went wrong here, and
        # the upload's temporary file is already gone; nobody reads the answer
        log.info("client disconnected during %s %s", request.method, request.url.path)
        return error_response(400, "the client disconnected before the request was complete")

    @app.exception_handler(OSError)
    async def _os(request: Request, exc: OSError) -> JSONResponse:
        if disk_full(exc):
            log.error("%s %s: the data folder's disk is full (%s)", request.method, request.url.path, exc)
            return error_response(507, DISK_FULL_DETAIL)
        log.error("unexpected error on %s %s", request.method, request.url.path, exc_info=exc)
        return error_response(500, f"internal error ({type(exc).__name__}); the server log has the details")

    @app.exception_handler(sqlite3.OperationalError)
    async def _store_busy(request: Request, exc: sqlite3.OperationalError) -> JSONResponse:
        if disk_full(exc):
            log.error("%s %s: the job store's disk is full (%s)", request.method, request.url.path, exc)
            return error_response(507, DISK_FULL_DETAIL)
        if "locked" in str(exc) or "busy" in str(exc):
            log.warning("%s %s: the job store stayed locked (%s)", request.method, request.url.path, exc)
            resp = error_response(503, "the job store is busy; try again in a few seconds")
            resp.headers["Retry-After"] = "5"
            return resp
        log.error("unexpected error on %s %s", request.method, request.url.path, exc_info=exc)
        return error_response(500, f"internal error ({type(exc).__name__}); the server log has the details")

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        # one line: Starlette re-raises what reaches this last handler, and the server logs
        # its traceback (logging it here too printed every traceback twice)
        log.error("unexpected error on %s %s: %s: %s", request.method, request.url.path, type(exc).__name__, exc)
        return error_response(500, f"internal error ({type(exc).__name__}); the server log has the details")
