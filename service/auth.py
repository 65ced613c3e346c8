"""Tenants (farms) and their bearer tokens.

A token is ``orch_`` followed by 43 url-safe random characters. Only its sha256 is
stored, so a copy of the store gives nobody access. Every ``/v1`` request carries
``Authorization: Bearer <token>``; the tenant it belongs to is the only one whose
blocks, jobs, schedules and reports the request can see.
"""

from __future__ import annotations

import hashlib
import secrets
from typing import Any

from service.errors import UnauthorizedError
from service.store import Store

TOKEN_PREFIX = "orch_"


def hash_token(token: str) -> str:
    """The stored form of a token (sha256, hex)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def create_token(store: Store, tenant: str) -> str:
    """A new token for ``tenant`` (created if it does not exist yet); returned once, stored hashed."""
    name = tenant.strip()
    if not name or len(name) > 100 or any(not c.isprintable() for c in name):
        raise ValueError("a tenant name is 1-100 printable characters")
    rec = store.ensure_tenant(name)
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    store.add_token(rec["id"], hash_token(token))
    return token


def authenticate(store: Store, authorization: str | None) -> dict[str, Any]:
    """The tenant of an ``Authorization`` header value; `UnauthorizedError` if missing or unknown."""
    if not authorization:
        raise UnauthorizedError("missing bearer token: send 'Authorization: Bearer <token>' (see `orchard tokens create`)")
    scheme, _, token = authorization.strip().partition(" ")
    token = token.strip()
    if scheme.lower() != "bearer" or not token:
        raise UnauthorizedError("the Authorization header must be 'Bearer <token>'")
    tenant = store.tenant_for_token(hash_token(token))
    if tenant is None:
        raise UnauthorizedError("unknown or revoked token; create one with `orchard tokens create --tenant NAME`")
    return tenant
