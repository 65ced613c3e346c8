"""Security headers on every response of the service: pages, JSON, files, errors.

`SecurityHeaders` (ASGI middleware) adds them unless a route set its own (the served
``report.html`` names its inlined scripts by hash, see `report_policy`):

- ``Content-Security-Policy`` (`POLICY`): scripts only from this server's files, never
  inline ones or ``eval``; nothing is fetched from elsewhere; no page may be framed
  (``frame-ancestors 'none'``, and ``X-Frame-Options: DENY`` for older browsers).
  Styles may be inline: ReDoc and Leaflet set them at run time.
- ``X-Content-Type-Options: nosniff``: a download is never run as a script or a page.
- ``Referrer-Policy: same-origin``: the service's URLs (job ids) are not sent to
  other sites, while its own forms still say where they come from.
- ``Cross-Origin-Opener-Policy: same-origin``: another site's window keeps no handle
  on a page of the service.
"""

from __future__ import annotations

import base64
import hashlib
import re

_COMMON = (
    "default-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
    "connect-src 'self'; worker-src 'self' blob:; object-src 'none'; base-uri 'none'; form-action 'self'; "
    "frame-ancestors 'none'"
)
#: The policy of every response but the served report.
POLICY = f"script-src 'self'; {_COMMON}"

HEADERS = {
    "content-security-policy": POLICY,
    "x-frame-options": "DENY",
    "x-content-type-options": "nosniff",
    "referrer-policy": "same-origin",
    "cross-origin-opener-policy": "same-origin",
}
_ENCODED = [(k.encode("latin-1"), v.encode("latin-1")) for k, v in HEADERS.items()]

# a script element without a type (or src): what a browser runs; JSON data elements are not scripts
_INLINE_SCRIPT = re.compile(r"<script>(.*?)</script>", re.S)


def report_policy(html: str) -> str:
    """The policy of a served ``report.html``: that file runs its own inlined scripts (it
    opens from disk offline), named here by their sha256, and nothing else inline."""
    hashes = sorted({"'sha256-" + base64.b64encode(hashlib.sha256(m.group(1).encode("utf-8")).digest()).decode() + "'"
                     for m in _INLINE_SCRIPT.finditer(html)})
    return f"script-src {' '.join(hashes) or chr(39) + 'none' + chr(39)}; {_COMMON}"


class SecurityHeaders:
    """ASGI middleware: `HEADERS` on every HTTP response that has not set them itself."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", ()))
                present = {k.lower() for k, _ in headers}
                headers.extend((k, v) for k, v in _ENCODED if k not in present)
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)
