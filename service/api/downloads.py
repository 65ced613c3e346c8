"""Result downloads: files with byte ranges, whose range errors are the API's JSON errors.

Starlette's `FileResponse` serves ``Range`` requests but answers a range it cannot use
in plain text. Here, as RFC 9110 says: a range unit other than ``bytes`` is ignored
(section 14.2: the whole file, 200); a range that starts past the end of the file is
416 with ``Content-Range: bytes */<size>`` (section 15.5.17); a malformed ``bytes``
range is 400. Both errors are JSON ``{"detail": ...}``, like every other error.
"""

from __future__ import annotations

import os

from starlette.datastructures import Headers
from starlette.responses import FileResponse, MalformedRangeHeader, RangeNotSatisfiable
from starlette.types import Receive, Scope, Send

from service.errors import error_response

_RANGE_FORMAT = "bytes=START-END, bytes=START- or bytes=-SUFFIX_LENGTH, END included"


class DownloadResponse(FileResponse):
    """A `FileResponse` whose range errors are JSON (see the module's docstring)."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"].upper() in ("GET", "HEAD") and self.status_code == 200:
            headers = Headers(scope=scope)
            http_range = headers.get("range")
            if http_range is not None:
                if self.stat_result is None:
                    self.stat_result = os.stat(self.path)
                    self.set_stat_headers(self.stat_result)
                if_range = headers.get("if-range")
                if if_range is None or self._should_use_range(if_range):
                    error = self._range_error(http_range, self.stat_result.st_size)
                    if error == "ignore":
                        scope = {**scope, "headers": [(k, v) for k, v in scope["headers"] if k.lower() != b"range"]}
                    elif error is not None:
                        await error(scope, receive, send)
                        return
        await super().__call__(scope, receive, send)

    def _range_error(self, http_range: str, size: int):
        """None if starlette can serve ``http_range``; "ignore" to serve the whole file; else
        the JSON error response."""
        unit = http_range.split("=", 1)[0].strip().lower() if "=" in http_range else None
        if unit is not None and unit != "bytes":
            return "ignore"
        try:
            self._parse_range_header(http_range, size)
        except RangeNotSatisfiable:
            resp = error_response(416, f"the Range {http_range[:100]!r} starts at or past the end of the file "
                                       f"({size} bytes); ask for bytes 0-{max(size - 1, 0)}")
            resp.headers["Content-Range"] = f"bytes */{size}"
            return resp
        except MalformedRangeHeader:
            return error_response(400, f"the Range header {http_range[:100]!r} is malformed; send {_RANGE_FORMAT}, "
                                       "or no Range for the whole file")
        return None
