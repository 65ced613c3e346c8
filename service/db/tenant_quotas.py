"""Each tenant's quota limits (``tenant_quotas``) and what it uses of them, checked
inside the transaction that would go past a limit (see :mod:`service.quotas`)."""

from __future__ import annotations

import sqlite3
import time
from typing import Any

from service.db.database import Database
from service.quotas import QueueQuotaExceeded, StorageQuotaExceeded

QUOTAS = ("storage_bytes", "queued_jobs")


def _stored_bytes(con: sqlite3.Connection, tenant_id: str) -> int:
    return int(con.execute("SELECT COALESCE(SUM(size_bytes), 0) FROM blocks WHERE tenant_id = ?", (tenant_id,)).fetchone()[0])


def _queued_jobs(con: sqlite3.Connection, tenant_id: str) -> int:
    return int(con.execute("SELECT COUNT(*) FROM jobs WHERE tenant_id = ? AND state = 'queued'", (tenant_id,)).fetchone()[0])


def _limit(con: sqlite3.Connection, tenant_id: str, column: str) -> tuple[int | None, str]:
    row = con.execute(
        f"SELECT q.{column} AS lim, t.name FROM tenants t LEFT JOIN tenant_quotas q ON q.tenant_id = t.id WHERE t.id = ?",
        (tenant_id,),
    ).fetchone()
    return (None, "") if row is None else (row["lim"], row["name"])


def check_storage_in(con: sqlite3.Connection, tenant_id: str, size_bytes: int) -> None:
    """StorageQuotaExceeded if a new block of ``size_bytes`` would not fit the tenant's
    storage quota, read in ``con``'s transaction (the one that would record the block)."""
    limit, name = _limit(con, tenant_id, "storage_bytes")
    if limit is not None:
        used = _stored_bytes(con, tenant_id)
        if used + size_bytes > limit:
            raise StorageQuotaExceeded(tenant=name, limit=limit, used=used, requested=size_bytes)


def check_queue_in(con: sqlite3.Connection, tenant_id: str) -> None:
    """QueueQuotaExceeded if one more queued job would not fit the tenant's queue quota,
    read in ``con``'s transaction (the one that would queue the job)."""
    limit, name = _limit(con, tenant_id, "queued_jobs")
    if limit is not None:
        used = _queued_jobs(con, tenant_id)
        if used + 1 > limit:
            raise QueueQuotaExceeded(tenant=name, limit=limit, used=used)


class TenantQuotas:
    """The ``tenant_quotas`` table, and the use of ``blocks`` and ``jobs`` it limits."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def set_limits(self, tenant_id: str, **limits: int | None) -> dict[str, Any]:
        """Set a tenant's ``storage_bytes`` and/or ``queued_jobs`` limit (the keys given;
        None = unlimited); returns `get`. What the tenant holds already is kept."""
        if not limits.keys() <= set(QUOTAS):
            raise ValueError(f"not a quota: {sorted(limits.keys() - set(QUOTAS))}")
        with self.db.transaction() as con:
            con.execute("INSERT OR IGNORE INTO tenant_quotas (tenant_id, updated_at) VALUES (?, ?)", (tenant_id, time.time()))
            for key, value in limits.items():
                con.execute(f"UPDATE tenant_quotas SET {key} = ?, updated_at = ? WHERE tenant_id = ?",
                            (None if value is None else int(value), time.time(), tenant_id))
        return self.get(tenant_id)

    def get(self, tenant_id: str) -> dict[str, Any]:
        """A tenant's limits and use: ``{"storage_bytes", "queued_jobs"}`` (limits, None =
        unlimited) and ``{"used_storage_bytes", "used_queued_jobs"}``."""
        con = self.db.connection()
        row = con.execute("SELECT storage_bytes, queued_jobs FROM tenant_quotas WHERE tenant_id = ?", (tenant_id,)).fetchone()
        return {
            "storage_bytes": None if row is None else row["storage_bytes"],
            "queued_jobs": None if row is None else row["queued_jobs"],
            "used_storage_bytes": _stored_bytes(con, tenant_id),
            "used_queued_jobs": _queued_jobs(con, tenant_id),
        }

    def check_storage(self, tenant_id: str, size_bytes: int) -> None:
        """StorageQuotaExceeded if a new block of ``size_bytes`` would not fit the
        tenant's storage quota now: asked before a file is copied or landed, so a refused
        one costs nothing (`Blocks.insert` checks again when it records the block)."""
        check_storage_in(self.db.connection(), tenant_id, size_bytes)
