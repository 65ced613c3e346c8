"""Tenants (farms) and their bearer tokens.

A token is ``orch_<8 characters>_<43 url-safe random characters>``. Its first part,
``orch_<8 characters>``, is its visible prefix: kept in the store and shown in
listings, so that an operator can tell tokens apart without seeing them. Only the
token's sha256 is stored, so a copy of the store gives nobody access. Each token has an
id (to list and revoke it), a creation time, the time it was last used and an optional
expiry. Every ``/v1`` request carries ``Authorization: Bearer <token>``; the tenant it
belongs to is the only one whose blocks, jobs, schedules and reports the request can see.
"""

from __future__ import annotations

import hashlib
import secrets
import sqlite3
import string
import time
from datetime import datetime, timezone
from typing import Any

from pipeline.errors import OrchardError
from service.db.jobstore import Store

TOKEN_PREFIX = "orch_"
_PREFIX_CHARS = string.ascii_lowercase + string.digits
#: a token's last use is written at most this often [s]: not one write transaction per request
TOUCH_INTERVAL_S = 60.0

#: the 401 of a token this store does not know: the usual cause is a token made for
#: another data folder than the server's (named in the server's log at start)
UNKNOWN_TOKEN = ("unknown or revoked token; create one with `orchard tokens create --tenant NAME --data-dir DIR` "
                 "on the server, DIR being the data folder the server uses (its log names it at start)")


class UnauthorizedError(OrchardError):
    """No bearer token, or one the store does not know (a 401 at the API)."""


def hash_token(token: str) -> str:
    """The stored form of a token (sha256, hex)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def issue_token(store: Store, tenant: str, *, expires_in_s: float | None = None) -> tuple[str, dict[str, Any]]:
    """A new token for ``tenant`` (created if it does not exist yet) and its record
    (``id``, ``prefix``, ``created_at``, ``expires_at``); the token is returned once and
    stored hashed. ``expires_in_s``: it is refused this many seconds from now (None: never)."""
    name = tenant.strip()
    if not name or len(name) > 100 or any(not c.isprintable() for c in name):
        raise ValueError("a tenant name is 1-100 printable characters")
    if expires_in_s is not None and not expires_in_s > 0:
        raise ValueError("a token's lifetime must be positive")
    rec = store.accounts.ensure_tenant(name)
    prefix = TOKEN_PREFIX + "".join(secrets.choice(_PREFIX_CHARS) for _ in range(8))
    token = f"{prefix}_{secrets.token_urlsafe(32)}"
    expires_at = None if expires_in_s is None else time.time() + expires_in_s
    token_rec = store.accounts.add_token(rec["id"], hash_token(token), prefix=prefix, expires_at=expires_at)
    return token, {**token_rec, "tenant": rec["name"]}


def create_token(store: Store, tenant: str, *, expires_in_s: float | None = None) -> str:
    """A new token for ``tenant`` (created if it does not exist yet); returned once, stored hashed."""
    return issue_token(store, tenant, expires_in_s=expires_in_s)[0]


def iso_time(ts: float | None) -> str | None:
    """A stored time [s since the epoch] as ISO 8601 UTC, to the second."""
    if ts is None:
        return None
    return datetime.fromtimestamp(ts, timezone.utc).replace(microsecond=0).isoformat()


def authenticate(store: Store, authorization: str | None, *, now: float | None = None) -> dict[str, Any]:
    """The tenant of an ``Authorization`` header value; `UnauthorizedError` if missing,
    unknown, revoked or expired. Records the token's use (at most every `TOUCH_INTERVAL_S`)."""
    if not authorization:
        raise UnauthorizedError("missing bearer token: send 'Authorization: Bearer <token>' (see `orchard tokens create`)")
    scheme, _, token = authorization.strip().partition(" ")
    token = token.strip()
    if scheme.lower() != "bearer" or not token:
        raise UnauthorizedError("the Authorization header must be 'Bearer <token>'")
    rec = store.accounts.token_by_hash(hash_token(token))
    if rec is None or rec["tenant"] is None:
        raise UnauthorizedError(UNKNOWN_TOKEN)
    now = time.time() if now is None else now
    if rec["expires_at"] is not None and rec["expires_at"] <= now:
        raise UnauthorizedError(
            f"token {rec['prefix'] or rec['id']} expired at {iso_time(rec['expires_at'])}; ask the operator for a new "
            "one (`orchard tokens create --tenant NAME [--expires-in 90d]` on the server)"
        )
    if rec["last_used_at"] is None or now - rec["last_used_at"] >= TOUCH_INTERVAL_S:
        try:
            store.accounts.touch_token(rec["id"], now)
        except sqlite3.OperationalError:  # a busy or full store: the last use is a hint, the request goes on
            pass
    return rec["tenant"]
