"""The records of uploaded and captured blocks (``blocks``); their files are landed
by :mod:`service.db.block_files`."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from service.db.database import Database, new_id, record
from service.db.errors import NotFoundError
from service.db.tenant_quotas import check_storage_in


class Blocks:
    """The ``blocks`` table (a block is recorded within its tenant's storage quota)."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def _located(self, rec: dict[str, Any] | None) -> dict[str, Any] | None:
        """A block record whose ``path`` is where its file is now: a path recorded
        relative to some process's folder (before paths were made absolute), or under a
        data folder since moved or mounted elsewhere, is looked up in this store's own
        ``blocks/`` folder, where every block file lives under its checksum name."""
        if rec is None:
            return None
        path = Path(rec["path"])
        if not path.is_absolute() or not path.exists():
            here = self.db.path.parent / "blocks" / path.name
            if here.exists() or not path.is_absolute():
                rec["path"] = str(here.absolute())
        return rec

    def file_used_any_tenant(self, path: str) -> bool:
        """Whether any tenant's block is recorded at ``path``."""
        return self.db.one("SELECT 1 AS used FROM blocks WHERE path = ?", (path,)) is not None

    def by_sha(self, tenant_id: str, sha256: str) -> dict[str, Any] | None:
        """The tenant's block of this content (sha256), or None."""
        return self._located(self.db.one("SELECT * FROM blocks WHERE tenant_id = ? AND sha256 = ?", (tenant_id, sha256)))

    def insert(
        self, *, tenant_id: str, sha256: str, path: str, filename: str | None, size_bytes: int, info: dict
    ) -> tuple[dict[str, Any], bool]:
        """Insert a block; if the tenant already has this file (same sha256), return that one.

        Returns ``(block, created)``.
        """
        with self.db.transaction() as con:
            row = con.execute("SELECT * FROM blocks WHERE tenant_id = ? AND sha256 = ?", (tenant_id, sha256)).fetchone()
            if row is not None:
                if row["path"] != path and not Path(row["path"]).exists():  # its file was landed again
                    con.execute("UPDATE blocks SET path = ? WHERE id = ?", (path, row["id"]))
                    row = con.execute("SELECT * FROM blocks WHERE id = ?", (row["id"],)).fetchone()
                return self._located(record(row)), False
            check_storage_in(con, tenant_id, size_bytes)
            bid = new_id()
            con.execute(
                "INSERT INTO blocks (id, tenant_id, sha256, path, filename, size_bytes, info, created_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (bid, tenant_id, sha256, path, filename, size_bytes, json.dumps(info), time.time()),
            )
            row = con.execute("SELECT * FROM blocks WHERE id = ?", (bid,)).fetchone()
        return self._located(record(row)), True

    def get(self, tenant_id: str, block_id: str) -> dict[str, Any]:
        """The tenant's block; NotFoundError if it has none of that id."""
        rec = self.db.one("SELECT * FROM blocks WHERE id = ? AND tenant_id = ?", (block_id, tenant_id))
        if rec is None:
            raise NotFoundError(f"no block {block_id!r}; ", hint="{list.blocks}")
        return self._located(rec)

    def list(self, tenant_id: str, *, limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        """The tenant's blocks, newest first."""
        return [self._located(rec) for rec in self.db.rows(
            "SELECT * FROM blocks WHERE tenant_id = ? ORDER BY created_at DESC, id DESC LIMIT ? OFFSET ?", (tenant_id, limit, offset)
        )]
