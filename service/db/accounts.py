"""Tenants (farms) and their API tokens (only a token's hash is stored)."""

from __future__ import annotations

import time
from typing import Any

from service.db.database import Database, new_id, new_token_id, record
from service.db.errors import NotFoundError


#: a token as listed: never its hash, with its tenant's name
_TOKENS = ("SELECT k.id, k.tenant_id, t.name AS tenant, k.prefix, k.created_at, k.last_used_at, k.expires_at "
           "FROM tokens k JOIN tenants t ON t.id = k.tenant_id")


class Accounts:
    """The ``tenants`` and ``tokens`` tables."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def ensure_tenant(self, name: str) -> dict[str, Any]:
        """The tenant called ``name``, created if it does not exist."""
        with self.db.transaction() as con:
            row = con.execute("SELECT * FROM tenants WHERE name = ?", (name,)).fetchone()
            if row is None:
                con.execute("INSERT INTO tenants (id, name, created_at) VALUES (?, ?, ?)", (new_id(), name, time.time()))
                row = con.execute("SELECT * FROM tenants WHERE name = ?", (name,)).fetchone()
        return record(row)

    def tenant_by_name(self, name: str) -> dict[str, Any]:
        rec = self.db.one("SELECT * FROM tenants WHERE name = ?", (name,))
        if rec is None:
            raise NotFoundError(f"no tenant called {name!r} (a tenant is made with its first token)")
        return rec

    def list_tenants(self) -> list[dict[str, Any]]:
        return self.db.rows(
            "SELECT t.*, (SELECT COUNT(*) FROM tokens k WHERE k.tenant_id = t.id) AS n_tokens FROM tenants t ORDER BY name"
        )

    def add_token(
        self, tenant_id: str, token_hash: str, *, prefix: str | None = None, expires_at: float | None = None
    ) -> dict[str, Any]:
        """Store a token's hash for ``tenant_id``; returns its record (``id``, ``prefix``,
        ``created_at``, ``expires_at`` [s since the epoch] ...)."""
        token_id = new_token_id()
        with self.db.transaction() as con:
            con.execute(
                "INSERT INTO tokens (hash, tenant_id, created_at, id, prefix, expires_at) VALUES (?, ?, ?, ?, ?, ?)",
                (token_hash, tenant_id, time.time(), token_id, prefix, expires_at),
            )
        return self.db.one("SELECT id, tenant_id, prefix, created_at, last_used_at, expires_at FROM tokens WHERE id = ?", (token_id,))

    def list_tokens(self, tenant_id: str) -> list[dict[str, Any]]:
        """A tenant's tokens (never their hashes) with its name, oldest first."""
        return self.db.rows(_TOKENS + " WHERE k.tenant_id = ? ORDER BY k.created_at, k.id", (tenant_id,))

    def list_tokens_any_tenant(self) -> list[dict[str, Any]]:
        """Every tenant's tokens as `list_tokens`, by tenant (the operator's listing)."""
        return self.db.rows(_TOKENS + " ORDER BY t.name, k.created_at, k.id")

    def revoke_token(self, token_hash: str) -> bool:
        with self.db.transaction() as con:
            return con.execute("DELETE FROM tokens WHERE hash = ?", (token_hash,)).rowcount > 0

    def revoke_token_id(self, token_id: str) -> bool:
        """Delete the token with this id; False if there is none."""
        with self.db.transaction() as con:
            return con.execute("DELETE FROM tokens WHERE id = ?", (token_id,)).rowcount > 0

    def tenant_for_token(self, token_hash: str) -> dict[str, Any] | None:
        return self.db.one(
            "SELECT t.* FROM tokens k JOIN tenants t ON t.id = k.tenant_id WHERE k.hash = ?", (token_hash,)
        )

    def token_by_hash(self, token_hash: str) -> dict[str, Any] | None:
        """The token record (``id``, ``prefix``, ``expires_at``, ``last_used_at``) with its
        tenant as ``tenant`` (a tenant record), or None."""
        rec = self.db.one(
            "SELECT k.id, k.prefix, k.created_at, k.last_used_at, k.expires_at, k.tenant_id FROM tokens k WHERE k.hash = ?",
            (token_hash,),
        )
        if rec is not None:
            rec["tenant"] = self.db.one("SELECT * FROM tenants WHERE id = ?", (rec["tenant_id"],))
        return rec

    def touch_token(self, token_id: str, at: float) -> None:
        """Record a use of the token at ``at`` [s since the epoch]."""
        with self.db.transaction() as con:
            con.execute("UPDATE tokens SET last_used_at = ? WHERE id = ?", (at, token_id))
