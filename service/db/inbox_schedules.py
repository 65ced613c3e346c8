"""Schedules that scan an inbox folder (``schedules``), the captures they handled
(``schedule_files``) and the checksums of inbox files already read (``capture_hashes``)."""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Callable
from typing import Any

from pipeline.errors import ParameterError
from service.db.database import Database, new_id, record
from service.db.errors import NotFoundError
from service.db.orchard_blocks import insert_capture
from service.db.tenant_quotas import check_queue_in


#: the changes of `InboxSchedules.update`: the new values, or a function of the schedule as stored giving them
Changes = dict[str, Any] | Callable[[dict[str, Any]], dict[str, Any]]


def _found(rec: dict[str, Any] | None, schedule_id: str) -> dict[str, Any]:
    if rec is None:
        raise NotFoundError(f"no schedule {schedule_id!r}; ", hint="{list.schedules}")
    return rec


class InboxSchedules:
    """The ``schedules``, ``schedule_files`` and ``capture_hashes`` tables (a scheduled
    capture's job is queued with its record, in one transaction; a schedule that names an
    orchard block records each file as one more capture of it).

    A schedule's lookups take its tenant; the schedule clock, which serves every tenant,
    and the operator's command line use the ``*_any_tenant`` ones."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def create(
        self, *, tenant_id: str, inbox: str, cron: str, job: dict, next_run_at: float | None,
        orchard_block_id: str | None = None,
    ) -> dict[str, Any]:
        sid = new_id()
        with self.db.transaction() as con:
            if orchard_block_id is not None and con.execute(
                "SELECT 1 FROM orchard_blocks WHERE id = ? AND tenant_id = ?", (orchard_block_id, tenant_id)
            ).fetchone() is None:  # the tenant's own
                raise NotFoundError(f"no orchard block {orchard_block_id!r}; ", hint="{list.orchard_blocks}")
            # one schedule per inbox, checked inside the write transaction: requests at the
            # same moment cannot both pass (BEGIN IMMEDIATE serialises them)
            other = con.execute("SELECT id, tenant_id FROM schedules WHERE inbox = ?", (inbox,)).fetchone()
            if other is not None:
                whose = "this tenant's" if other[1] == tenant_id else "another tenant's"
                raise ParameterError(f"inbox {inbox!r} already has a schedule ({whose}); one schedule per inbox")
            con.execute(
                "INSERT INTO schedules (id, tenant_id, inbox, cron, job, created_at, next_run_at, orchard_block_id) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (sid, tenant_id, inbox, cron, json.dumps(job), time.time(), next_run_at, orchard_block_id),
            )
        return self.get(tenant_id, sid)

    def get(self, tenant_id: str, schedule_id: str) -> dict[str, Any]:
        """The tenant's schedule; NotFoundError if it has none of that id."""
        return _found(self.db.one("SELECT * FROM schedules WHERE id = ? AND tenant_id = ?", (schedule_id, tenant_id)), schedule_id)

    def get_any_tenant(self, schedule_id: str) -> dict[str, Any]:
        """The schedule of this id whoever's it is (the clock's and the operator's lookup)."""
        return _found(self.db.one("SELECT * FROM schedules WHERE id = ?", (schedule_id,)), schedule_id)

    def list(self, tenant_id: str) -> list[dict[str, Any]]:
        """The tenant's schedules, oldest first."""
        return self.db.rows("SELECT * FROM schedules WHERE tenant_id = ? ORDER BY created_at, id", (tenant_id,))

    def list_any_tenant(self) -> list[dict[str, Any]]:
        """Every tenant's schedules, oldest first (the clock's and the operator's listing)."""
        return self.db.rows("SELECT * FROM schedules ORDER BY created_at, id")

    def delete(self, tenant_id: str, schedule_id: str) -> None:
        with self.db.transaction() as con:
            n = con.execute("DELETE FROM schedules WHERE id = ? AND tenant_id = ?", (schedule_id, tenant_id)).rowcount
            if n == 0:
                raise NotFoundError(f"no schedule {schedule_id!r}; ", hint="{list.schedules}")
            con.execute("DELETE FROM schedule_files WHERE schedule_id = ?", (schedule_id,))
            # its webhooks would never be called again
            con.execute("DELETE FROM webhook_deliveries WHERE webhook_id IN (SELECT id FROM webhooks WHERE schedule_id = ?)", (schedule_id,))
            con.execute("DELETE FROM webhooks WHERE schedule_id = ?", (schedule_id,))

    def set_times(self, schedule_id: str, *, cron: str, last_run_at: float | None, next_run_at: float | None) -> None:
        """Record a run and the next one, computed from ``cron``: left alone if the
        schedule was paused or given another cron meanwhile (that change set its own)."""
        with self.db.transaction() as con:
            con.execute(
                "UPDATE schedules SET last_run_at = COALESCE(?, last_run_at), next_run_at = ? "
                "WHERE id = ? AND cron = ? AND paused = 0",
                (last_run_at, next_run_at, schedule_id, cron),
            )

    def bring_forward(self, schedule_id: str, at: float) -> None:
        """Run a schedule at ``at`` if its next run is later (or not set) and it is not paused."""
        with self.db.transaction() as con:
            con.execute(
                "UPDATE schedules SET next_run_at = ? WHERE id = ? AND paused = 0 AND (next_run_at IS NULL OR next_run_at > ?)",
                (at, schedule_id, at),
            )

    def update(self, tenant_id: str, schedule_id: str, changes: Changes) -> dict[str, Any]:
        """Change the tenant's schedule's ``cron``, ``job`` (its jobs' parameters), ``paused`` and
        ``next_run_at`` (the keys given) in one transaction. ``changes`` may be a function
        of the schedule as stored, called inside that transaction, so that what it checks
        (a tiling against the parameters) cannot be changed by another request meanwhile."""
        self._update("id = ? AND tenant_id = ?", [schedule_id, tenant_id], schedule_id, changes)
        return self.get(tenant_id, schedule_id)

    def update_any_tenant(self, schedule_id: str, changes: Changes) -> dict[str, Any]:
        """`update` of a schedule whoever's it is (the operator's command line)."""
        self._update("id = ?", [schedule_id], schedule_id, changes)
        return self.get_any_tenant(schedule_id)

    def _update(self, where: str, args: list[Any], schedule_id: str, changes: Changes) -> None:
        allowed = {"cron", "job", "paused", "next_run_at"}
        with self.db.transaction() as con:
            current = record(con.execute(f"SELECT * FROM schedules WHERE {where}", args).fetchone())
            if current is None:
                raise NotFoundError(f"no schedule {schedule_id!r}; ", hint="{list.schedules}")
            if callable(changes):
                changes = changes(current)
            if not changes.keys() <= allowed:
                raise ValueError(f"not a schedule setting: {sorted(changes.keys() - allowed)}")
            values = {k: (json.dumps(v) if k == "job" else v) for k, v in changes.items()}
            if "paused" in values:
                values["paused"] = int(bool(values["paused"]))
            if values:
                con.execute(f"UPDATE schedules SET {', '.join(f'{k} = ?' for k in values)} WHERE {where}",
                            [*values.values(), *args])

    def known_hash(self, path: str, state: tuple[int, int, int, int]) -> str | None:
        """The sha256 of an inbox file hashed before and unchanged since (``state``: size,
        mtime_ns, ctime_ns, inode), or None: scans re-read every capture left in an inbox
        every night."""
        row = self.db.one(
            "SELECT sha256 FROM capture_hashes WHERE path = ? AND size = ? AND mtime_ns = ? AND ctime_ns = ? AND inode = ?",
            (path, *state),
        )
        return None if row is None else row["sha256"]

    def remember_hash(self, path: str, state: tuple[int, int, int, int], sha256: str) -> None:
        with self.db.transaction() as con:
            con.execute(
                "INSERT OR REPLACE INTO capture_hashes (path, size, mtime_ns, ctime_ns, inode, sha256) VALUES (?, ?, ?, ?, ?, ?)",
                (path, *state, sha256),
            )

    def file_seen(self, schedule_id: str, sha256: str) -> bool:
        return self.db.one(
            "SELECT 1 AS seen FROM schedule_files WHERE schedule_id = ? AND sha256 = ?", (schedule_id, sha256)
        ) is not None

    def record_file(
        self, *, schedule_id: str, sha256: str, path: str, job_id: str | None, error: str | None
    ) -> bool:
        """Record that a capture was handled; False if it already was (another scan got there first)."""
        with self.db.transaction() as con:
            try:
                con.execute(
                    "INSERT INTO schedule_files (schedule_id, sha256, path, job_id, error, seen_at) VALUES (?, ?, ?, ?, ?, ?)",
                    (schedule_id, sha256, path, job_id, error, time.time()),
                )
            except sqlite3.IntegrityError:
                return False
        return True

    def create_job(
        self, *, schedule: dict[str, Any], block_id: str, sha256: str, path: str, capture: str | None = None
    ) -> dict[str, Any] | None:
        """Queue the job of a capture a schedule found and record the capture as handled,
        in one transaction; None (nothing queued) if the capture was handled already,
        e.g. by a scan of the same inbox running at the same moment in another process.
        ``capture`` is the file's name as shown to the farm (the block may be an earlier
        upload of the same bytes under another name). A schedule of an orchard block records
        the capture too (arrived now: dated today unless the file has a date)."""
        jid = new_id()
        with self.db.transaction() as con:
            try:
                con.execute(
                    "INSERT INTO schedule_files (schedule_id, sha256, path, job_id, error, seen_at) VALUES (?, ?, ?, ?, ?, ?)",
                    (schedule["id"], sha256, path, jid, None, time.time()),
                )
            except sqlite3.IntegrityError:
                return None
            check_queue_in(con, schedule["tenant_id"])  # rolls the capture's record back too
            con.execute(
                "INSERT INTO jobs (id, tenant_id, block_id, schedule_id, job, state, created_at, capture) "
                "VALUES (?, ?, ?, ?, ?, 'queued', ?, ?)",
                (jid, schedule["tenant_id"], block_id, schedule["id"], json.dumps(schedule["job"]), time.time(), capture),
            )
            if schedule.get("orchard_block_id"):  # the inbox of an orchard block: one more capture of it
                insert_capture(con, tenant_id=schedule["tenant_id"], orchard_block_id=schedule["orchard_block_id"],
                                     block_id=block_id, job_id=jid, captured_at=None, arrived_at=time.time())
        return self.db.one("SELECT * FROM jobs WHERE id = ?", (jid,))

    def capture_scheduled(self, tenant_id: str, sha256: str) -> bool:
        """Whether a schedule of this tenant (any, deleted ones too) already queued a job
        for the capture with this sha256."""
        return self.db.one(
            "SELECT 1 AS seen FROM jobs j JOIN blocks b ON b.id = j.block_id "
            "WHERE b.tenant_id = ? AND b.sha256 = ? AND j.schedule_id IS NOT NULL LIMIT 1",
            (tenant_id, sha256),
        ) is not None

    def files(self, schedule_id: str) -> list[dict[str, Any]]:
        """The captures a schedule (one already looked up) handled, oldest first."""
        return self.db.rows("SELECT * FROM schedule_files WHERE schedule_id = ? ORDER BY seen_at", (schedule_id,))

    def captures(self, schedule_id: str, *, limit: int) -> tuple[list[dict[str, Any]], dict[str, int]]:
        """The captures a schedule (one already looked up) handled, newest first (at most ``limit``), each with its
        job's state (``job_state``, None if rejected or the job was deleted), and how many
        it handled in all: ``{"processed": n, "rejected": n}``."""
        rows = self.db.rows(
            "SELECT f.sha256, f.path, f.job_id, f.error, f.seen_at, j.state AS job_state, j.error AS job_error, "
            "j.error_kind AS job_error_kind, j.error_fields AS job_error_fields "
            "FROM schedule_files f LEFT JOIN jobs j ON j.id = f.job_id "
            "WHERE f.schedule_id = ? ORDER BY f.seen_at DESC, f.path LIMIT ?",
            (schedule_id, int(limit)),
        )
        counts = self.db.one(
            "SELECT SUM(job_id IS NOT NULL) AS processed, SUM(job_id IS NULL) AS rejected FROM schedule_files WHERE schedule_id = ?",
            (schedule_id,),
        )
        return rows, {k: int(counts[k] or 0) for k in ("processed", "rejected")}
