"""Request bodies as they arrive: the size limit of every body, and block uploads
streamed to a temporary file.

`BodyLimit` answers 413 for a body above its limit (an upload has its own, larger one).
`receive_upload` parses a multipart upload as it arrives, writing its ``file`` field to a
temporary file of this process (`service.tempfiles`) while hashing it; an upload that
stalls (nothing for ``upload_idle_s``), trickles (below ``upload_min_kbps`` on average,
or still arriving after ``upload_deadline_s``), is cut off, is malformed or grows past
the limit leaves no file behind.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import re
import uuid
from pathlib import Path

from fastapi import Request
from fastapi.responses import JSONResponse
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect

from pipeline.errors import InputError
from service import tempfiles
from service.errors import ShuttingDownError, StalledUploadError, TooLargeError
from service.permissions import FILE_MODE
from service.schedules import printable
from service.settings import Settings

UPLOAD_SLACK = 1 << 20  # multipart overhead allowed on top of the file size limit
_DRAIN_LIMIT = 64 << 20  # after a too-large upload, read at most this much more before answering
#: a capture sent to an orchard block is an upload too (`service.api.routes_orchard_blocks`)
_CAPTURE_UPLOAD = re.compile(r"^/v1/orchard-blocks/[^/]+/captures$")


class BodyLimit:
    """ASGI middleware: 413 for request bodies above the limit (uploads get their own, larger one)."""

    def __init__(self, app, *, default: int, upload: int, upload_mb: float, upload_path: str = "/v1/blocks") -> None:
        self.app = app
        self.upload_mb = upload_mb
        self.default = default
        self.upload = upload
        self.upload_path = upload_path

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "").rstrip("/")
        length, multipart = None, False
        for key, value in scope.get("headers", ()):
            if key == b"content-length":
                with contextlib.suppress(ValueError):
                    length = int(value)
            elif key == b"content-type":
                multipart = value.lower().startswith(b"multipart/")
        # a capture is an upload when it brings its file; as JSON it is a request like any other
        is_upload = scope.get("method") == "POST" and (
            path == self.upload_path or (multipart and _CAPTURE_UPLOAD.match(path) is not None))
        limit = self.upload if is_upload else self.default
        if length is not None and length > limit:
            if is_upload:
                detail = f"upload of {length} bytes is above the upload limit of {self.upload_mb:g} MB (ORCHARD_MAX_UPLOAD_MB)"
            else:
                detail = f"request body of {length} bytes is above the limit of {limit} bytes"
            resp = JSONResponse(
                {"detail": detail},
                status_code=413,
                headers={"Connection": "close"},
            )
            await resp(scope, receive, send)
            return
        total = 0

        async def limited_receive():
            nonlocal total
            message = await receive()
            if message["type"] == "http.request":
                total += len(message.get("body", b""))
                if total > limit:
                    raise TooLargeError(f"request body is above the limit of {limit} bytes")
            return message

        await self.app(scope, limited_receive, send)


def display_filename(name: str | None) -> str | None:
    """A client file name reduced to something safe to show (never used as a path)."""
    if not name:
        return None
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    base = printable(base).strip()
    return base[:200] or None



class FilePart:
    """Receives the multipart callbacks; writes the ``file`` field to a temporary file, hashing it."""

    def __init__(self, tmp_path: Path, limit: int) -> None:
        self.tmp_path = tmp_path
        self.limit = limit
        self.fh = None
        self.sha = hashlib.sha256()
        self.size = 0
        self.filename: str | None = None
        self.found = False
        self.complete = False  # the file's part ended at a boundary (not cut off)
        self.too_large = False
        self._in_file = False
        self._field = bytearray()
        self._value = bytearray()
        self._headers: dict[bytes, bytes] = {}

    def callbacks(self) -> dict:
        return {
            "on_part_begin": self._part_begin,
            "on_header_field": lambda d, s, e: self._field.extend(d[s:e]),
            "on_header_value": lambda d, s, e: self._value.extend(d[s:e]),
            "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished,
            "on_part_data": self._data,
            "on_part_end": self._part_end,
        }

    def _part_begin(self) -> None:
        self._headers = {}
        self._in_file = False

    def _header_end(self) -> None:
        self._headers[bytes(self._field).lower()] = bytes(self._value)
        self._field.clear()
        self._value.clear()

    def _headers_finished(self) -> None:
        _, opts = parse_options_header(self._headers.get(b"content-disposition", b""))
        if opts.get(b"name") == b"file" and not self.found:
            self.found = True
            self._in_file = True
            raw = opts.get(b"filename")
            self.filename = display_filename(raw.decode("utf-8", "replace")) if raw else None
            self.fh = open(self.tmp_path, "wb")
            os.fchmod(self.fh.fileno(), FILE_MODE)  # a farm's file, whatever the process umask

    def _data(self, data: bytes, start: int, end: int) -> None:
        if not self._in_file or self.too_large:
            return
        n = end - start
        self.size += n
        if self.size > self.limit:
            self.too_large = True
            return
        chunk = data[start:end]
        self.sha.update(chunk)
        self.fh.write(chunk)

    def _part_end(self) -> None:
        if self._in_file and self.fh is not None:
            self.fh.close()
            self.complete = True
        self._in_file = False

    @property
    def header_name(self) -> bytes:
        """The name of the part header being read (empty between headers)."""
        return bytes(self._field)

    def close(self) -> None:
        if self.fh is not None and not self.fh.closed:
            self.fh.close()


async def receive_upload(request: Request, settings: Settings) -> FilePart:
    """The upload's ``file`` field, written to a temporary file of this process as it arrives.

    Raises
    ------
    InputError
        The body is not multipart, is malformed or cut off, or has no ``file`` field.
    TooLargeError
        The file grows past ``settings.max_upload_bytes``.
    StalledUploadError
        The body stalls, trickles or is still arriving after the deadline.
    ShuttingDownError
        The server is told to stop while the body arrives.

    None of these leaves the temporary file behind.
    """
    part, parser = _file_parser(request, settings)
    stream = request.stream()
    stopping = getattr(request.app.state, "stopping", None)  # set when the server is told to stop
    stop = asyncio.ensure_future(stopping.wait()) if stopping is not None else None
    began = asyncio.get_running_loop().time()
    try:
        await _read_body(stream, stop, began, parser, part, settings)
        if part.too_large:
            await _drain(stream)
            raise TooLargeError(
                f"the file is larger than the upload limit of {settings.max_upload_mb:g} MB (ORCHARD_MAX_UPLOAD_MB)"
            )
        _finalize(parser, part)
    except BaseException:
        with contextlib.suppress(OSError):  # (its last write may fail again: a full disk)
            part.close()
        part.tmp_path.unlink(missing_ok=True)
        raise
    finally:
        if stop is not None:
            stop.cancel()
    part.close()
    if not part.found:
        part.tmp_path.unlink(missing_ok=True)
        raise InputError("no field 'file' in the upload; send the block as multipart field 'file' (curl -F file=@block.laz)")
    return part


def _file_parser(request: Request, settings: Settings) -> tuple[FilePart, MultipartParser]:
    """The part that receives the file and the multipart parser that feeds it; InputError
    unless the request's content type is multipart with a valid boundary."""
    ctype, opts = parse_options_header(request.headers.get("content-type", "").encode("latin-1", "replace"))
    boundary = opts.get(b"boundary")
    if ctype != b"multipart/form-data" or not boundary:
        raise InputError("send the block as multipart/form-data with the file in the field 'file' (curl -F file=@block.laz)")
    part = FilePart(tempfiles.process_dir(settings.tmp_dir) / f"upload-{uuid.uuid4().hex}.part", settings.max_upload_bytes)
    try:
        parser = MultipartParser(boundary, part.callbacks())
    except Exception:
        raise InputError("the multipart boundary is invalid") from None
    return part, parser


async def _read_body(stream, stop, began: float, parser: MultipartParser, part: FilePart, settings: Settings) -> None:
    """Feed the body to ``parser`` until it ends or the file grows past the limit."""
    loop = asyncio.get_running_loop()
    received = 0
    while True:
        chunk = await _next_chunk(stream, stop, loop, began, settings)
        if chunk is None:
            break
        received += len(chunk)
        _check_pace(received, loop.time() - began, settings)
        _feed(parser, part, chunk)
        if part.too_large:
            break


async def _next_chunk(stream, stop, loop, began: float, settings: Settings) -> bytes | None:
    """The body's next chunk (None at its end), unless the idle limit, the overall deadline
    or the server stopping comes first (StalledUploadError, ShuttingDownError)."""
    # a client that stops sending, or trickles, would hold the request and its partial
    # file for good, and delay a shutdown
    left = settings.upload_deadline_s - (loop.time() - began)
    nxt = asyncio.ensure_future(anext(stream))
    done, _ = await asyncio.wait({nxt} | ({stop} if stop else set()), timeout=max(0.0, min(settings.upload_idle_s, left)),
                                 return_when=asyncio.FIRST_COMPLETED)
    if nxt not in done:
        nxt.cancel()
        if stop is not None and stop in done:
            raise ShuttingDownError("the server is stopping and cannot take this upload; send it again "
                                    "once it is back (nothing of it was kept)")
        if loop.time() - began >= settings.upload_deadline_s:
            raise StalledUploadError(_late(settings))
        raise StalledUploadError(
            f"the upload sent nothing for {settings.upload_idle_s:g} s (ORCHARD_UPLOAD_IDLE_S); send it again"
        )
    try:
        return nxt.result()
    except StopAsyncIteration:
        return None


def _check_pace(received: int, elapsed: float, settings: Settings) -> None:
    """StalledUploadError when ``received`` bytes after ``elapsed`` seconds are past the
    deadline or below the minimum average rate."""
    if elapsed >= settings.upload_deadline_s:
        raise StalledUploadError(_late(settings))
    if settings.upload_min_kbps and elapsed >= settings.upload_idle_s \
            and received < settings.upload_min_kbps * 1024 * elapsed:
        raise StalledUploadError(
            f"the upload averaged {received / 1024 / elapsed:.2f} kB/s over {elapsed:.0f} s, below the "
            f"minimum of {settings.upload_min_kbps:g} kB/s (ORCHARD_UPLOAD_MIN_KBPS); send it again over a faster link"
        )


def _feed(parser: MultipartParser, part: FilePart, chunk: bytes) -> None:
    """One chunk into the parser; InputError for a malformed body."""
    try:
        parser.write(chunk)
    except OSError:  # writing the file (a full disk): the server's fault, not the body's
        raise
    except Exception:
        if part.header_name.lower() == b"content-disposition":  # (python-multipart's 4,224-byte line limit)
            raise InputError("the file name of the upload is too long; rename the file (a name is kept "
                             "to 200 characters) and send it again") from None
        raise InputError("the multipart body is malformed; send the file as field 'file'") from None


async def _drain(stream) -> None:
    """Read (and drop) what is left of a too-large body, up to ``_DRAIN_LIMIT``, before the
    413 is sent: a client still sending when the connection closes may see a reset, not the answer."""
    drained = 0
    with contextlib.suppress(TooLargeError, ClientDisconnect):
        async for chunk in stream:
            drained += len(chunk)
            if drained > _DRAIN_LIMIT:
                break


def _finalize(parser: MultipartParser, part: FilePart) -> None:
    """The parser finished; InputError when the body ended before the file's part did."""
    try:
        parser.finalize()  # (it does not check that the body ended at a boundary)
    except OSError:  # closing the file (a full disk)
        raise
    except Exception:
        raise InputError("the multipart body is incomplete") from None
    if part.found and not part.complete:
        raise InputError("the multipart body is incomplete: the file's part has no closing boundary (upload cut off?)")


def _late(settings: Settings) -> str:
    return (f"the upload did not arrive within {settings.upload_deadline_s:g} s (ORCHARD_UPLOAD_DEADLINE_S); "
            "send it again over a faster link")


#: the upload route's request body in the API document (the route reads the stream itself)
UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {"file": {"type": "string", "format": "binary", "description": "a LAS, LAZ, PLY, PCD, E57 or text (x y z) point file"}},
                }
            }
        },
    }
}
