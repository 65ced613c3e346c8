"""Orchard blocks and their captures (``orchard_blocks``, ``captures``).

An orchard block is a named piece of a farm that is scanned again and again; each
capture of it is an uploaded file (a row of ``blocks``) processed by one job, in the
order the captures arrived (``seq``). A capture's state is its job's state; its date is
the one its job's outputs say (``record``, from `workers.seasons.capture_record`), and
until then the date given with it, else the day its file arrived.
"""

from __future__ import annotations

import json
import sqlite3
import time
from datetime import datetime
from typing import Any

from service.db.database import Database, new_id
from service.db.errors import ConflictError, NotFoundError
from service.db.tenant_quotas import check_queue_in

#: a capture as read: its row with its job's state and error
_CAPTURE_SELECT = (
    "SELECT c.*, j.state AS state, j.error AS error, j.error_kind AS error_kind, j.error_fields AS error_fields, "
    "j.finished_at AS finished_at, ob.name AS orchard_block_name "
    "FROM captures c JOIN jobs j ON j.id = c.job_id JOIN orchard_blocks ob ON ob.id = c.orchard_block_id"
)

def arrival_date(ts: float) -> str:
    """The server's local date (ISO ``YYYY-MM-DD``) of a moment [s since the epoch]: a
    capture's date when neither its file nor its sender gives one."""
    return datetime.fromtimestamp(ts).date().isoformat()


def insert_capture(
    con: sqlite3.Connection, *, tenant_id: str, orchard_block_id: str, block_id: str, job_id: str,
    captured_at: str | None, arrived_at: float,
) -> str:
    """Record a capture of a job just inserted in ``con``'s transaction (by
    `OrchardBlocks.create_capture` or a schedule of the orchard block); the next in its
    block's order. Returns its id."""
    owner = con.execute("SELECT tenant_id FROM orchard_blocks WHERE id = ?", (orchard_block_id,)).fetchone()
    if owner is None or owner["tenant_id"] != tenant_id:
        raise NotFoundError(f"no orchard block {orchard_block_id!r}; ", hint="{list.orchard_blocks}")
    (seq,) = con.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM captures WHERE orchard_block_id = ?",
                         (orchard_block_id,)).fetchone()
    cid = new_id()
    con.execute(
        "INSERT INTO captures (id, tenant_id, orchard_block_id, seq, block_id, job_id, captured_at, "
        "captured_at_source, given_captured_at, arrived_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        (cid, tenant_id, orchard_block_id, seq, block_id, job_id, captured_at or arrival_date(arrived_at),
         "given" if captured_at else "upload", captured_at, arrived_at),
    )
    return cid


class OrchardBlocks:
    """The ``orchard_blocks`` and ``captures`` tables (a capture's job is queued with its
    record, in one transaction)."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def create(self, tenant_id: str, name: str) -> dict[str, Any]:
        """A new orchard block of the tenant; ConflictError if it has one of that name."""
        obid = new_id()
        with self.db.transaction() as con:
            try:
                con.execute("INSERT INTO orchard_blocks (id, tenant_id, name, created_at) VALUES (?, ?, ?, ?)",
                            (obid, tenant_id, name, time.time()))
            except sqlite3.IntegrityError:
                raise ConflictError(f"this farm already has an orchard block called {name!r}; "
                                    "add captures to that one, or choose another name") from None
        return self.get(tenant_id, obid)

    def get(self, tenant_id: str, orchard_block_id: str) -> dict[str, Any]:
        """One orchard block with its capture counts; NotFoundError if it is not the tenant's."""
        rec = self.db.one(f"{_BLOCK_SELECT} WHERE ob.id = ? AND ob.tenant_id = ? GROUP BY ob.id", (orchard_block_id, tenant_id))
        if rec is None:
            raise NotFoundError(f"no orchard block {orchard_block_id!r}; ", hint="{list.orchard_blocks}")
        return rec

    def by_name(self, tenant_id: str, name: str) -> dict[str, Any]:
        """The tenant's orchard block called ``name``; NotFoundError if it has none."""
        row = self.db.one("SELECT id FROM orchard_blocks WHERE tenant_id = ? AND name = ?", (tenant_id, name))
        if row is None:
            raise NotFoundError(f"no orchard block called {name!r}; ", hint="{list.orchard_blocks}")
        return self.get(tenant_id, row["id"])

    def list(self, tenant_id: str) -> list[dict[str, Any]]:
        """The tenant's orchard blocks by name."""
        return self.db.rows(f"{_BLOCK_SELECT} WHERE ob.tenant_id = ? GROUP BY ob.id ORDER BY ob.name, ob.id", (tenant_id,))

    def list_any_tenant(self) -> list[dict[str, Any]]:
        """Every tenant's orchard blocks by name (the operator's listing)."""
        return self.db.rows(f"{_BLOCK_SELECT} GROUP BY ob.id ORDER BY ob.name, ob.id")

    # -- captures --------------------------------------------------------------------------

    def create_capture(
        self, *, tenant_id: str, orchard_block_id: str, block_id: str, job: dict,
        captured_at: str | None = None,
    ) -> dict[str, Any]:
        """Queue the job of a new capture of an orchard block, and record the capture, in
        one transaction (the tenant's queue quota holds). ``captured_at`` is the date the
        sender gave (ISO ``YYYY-MM-DD``); the file's own date wins when it has one.
        NotFoundError if the orchard block or the uploaded block is not the tenant's."""
        jid = new_id()
        with self.db.transaction() as con:
            block = con.execute("SELECT id, created_at FROM blocks WHERE id = ? AND tenant_id = ?", (block_id, tenant_id)).fetchone()
            if block is None:
                raise NotFoundError(f"no block {block_id!r}; ", hint="{list.blocks}")
            check_queue_in(con, tenant_id)
            now = time.time()
            con.execute(
                "INSERT INTO jobs (id, tenant_id, block_id, job, state, created_at) VALUES (?, ?, ?, ?, 'queued', ?)",
                (jid, tenant_id, block["id"], json.dumps(job), now),
            )
            cid = insert_capture(con, tenant_id=tenant_id, orchard_block_id=orchard_block_id, block_id=block["id"],
                                       job_id=jid, captured_at=captured_at, arrived_at=block["created_at"] or now)
        return self.get_capture(tenant_id, cid)

    def get_capture(self, tenant_id: str, capture_id: str) -> dict[str, Any]:
        """The tenant's capture; NotFoundError if it has none of that id."""
        rec = self.db.one(f"{_CAPTURE_SELECT} WHERE c.id = ? AND c.tenant_id = ?", (capture_id, tenant_id))
        if rec is None:
            raise NotFoundError(f"no capture {capture_id!r}")
        return rec

    def capture_of_job(self, tenant_id: str, job_id: str) -> dict[str, Any] | None:
        """The capture the tenant's job processes (None: the job is no capture of an
        orchard block, or not the tenant's)."""
        return self.db.one(f"{_CAPTURE_SELECT} WHERE c.job_id = ? AND c.tenant_id = ?", (job_id, tenant_id))

    def list_captures(self, tenant_id: str, orchard_block_id: str) -> list[dict[str, Any]]:
        """An orchard block's captures in arrival order; NotFoundError if it is not the tenant's."""
        self.get(tenant_id, orchard_block_id)
        return self.db.rows(f"{_CAPTURE_SELECT} WHERE c.orchard_block_id = ? AND c.tenant_id = ? ORDER BY c.seq",
                              (orchard_block_id, tenant_id))

    def latest_done_capture(self, tenant_id: str, orchard_block_id: str, *, before_seq: int | None = None) -> dict[str, Any] | None:
        """The tenant's block's latest capture (in arrival order) whose job is done, before
        ``before_seq`` if given; None if there is none. Its outputs hold the block's history."""
        where, args = "c.orchard_block_id = ? AND c.tenant_id = ? AND j.state = 'done'", [orchard_block_id, tenant_id]
        if before_seq is not None:
            where += " AND c.seq < ?"
            args.append(before_seq)
        return self.db.one(f"{_CAPTURE_SELECT} WHERE {where} ORDER BY c.seq DESC LIMIT 1", tuple(args))

    def set_capture_record(self, job_id: str, rec: dict[str, Any] | None) -> None:
        """Keep a finished capture job's record (``orchard:capture``: date and its source,
        previous capture, registration, counts); its date becomes the capture's."""
        rec = rec or {}
        with self.db.transaction() as con:
            con.execute(
                "UPDATE captures SET record = ?, captured_at = COALESCE(?, captured_at), "
                "captured_at_source = COALESCE(?, captured_at_source) WHERE job_id = ?",
                (json.dumps(rec) if rec else None, rec.get("captured_at"), rec.get("captured_at_source"), job_id),
            )


#: an orchard block as read: its row with its captures counted (all, and done)
_BLOCK_SELECT = (
    "SELECT ob.*, COUNT(c.id) AS n_captures, COALESCE(SUM(j.state = 'done'), 0) AS n_done, "
    "MAX(CASE WHEN j.state = 'done' THEN c.captured_at END) AS last_captured_at "
    "FROM orchard_blocks ob LEFT JOIN captures c ON c.orchard_block_id = ob.id LEFT JOIN jobs j ON j.id = c.job_id"
)
