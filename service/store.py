"""The job store: tenants, tokens, blocks, jobs and schedules in SQLite (WAL mode).

One connection per thread, every state change in one ``BEGIN IMMEDIATE`` transaction,
so the HTTP threads, the job runner and the schedule clock (and a second process such
as ``orchard tokens create``) can share the file. Uploaded blocks are content-addressed
files under ``data_dir/blocks/<sha256>.las|laz``, landed by :func:`accept_block` with a
temporary name, fsync and rename, so an accepted upload is never lost; job results live
under ``data_dir/jobs/<job id>/``.

Records are returned as plain dicts with JSON columns decoded. Lookups that take a
tenant never return another tenant's record: they raise `NotFoundError` instead.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, Iterator

from pipeline.errors import ConflictError, InputError, NotFoundError, ParameterError
from service.permissions import FILE_MODE, private_dir, private_file
from service.quotas import QueueQuotaExceeded, StorageQuotaExceeded

log = logging.getLogger("orchard.store")

JOB_STATES = ("queued", "running", "done", "failed", "cancelled")
FINAL_STATES = ("done", "failed", "cancelled")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS tenants (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL UNIQUE,
    created_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS tokens (
    hash TEXT PRIMARY KEY,
    tenant_id TEXT NOT NULL REFERENCES tenants(id),
    created_at REAL NOT NULL,
    id TEXT,
    prefix TEXT,
    last_used_at REAL,
    expires_at REAL
);
CREATE TABLE IF NOT EXISTS blocks (
    id TEXT PRIMARY KEY,
    tenant_id TEXT NOT NULL REFERENCES tenants(id),
    sha256 TEXT NOT NULL,
    path TEXT NOT NULL,
    filename TEXT,
    size_bytes INTEGER NOT NULL,
    info TEXT NOT NULL,
    created_at REAL NOT NULL,
    UNIQUE (tenant_id, sha256)
);
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    tenant_id TEXT NOT NULL REFERENCES tenants(id),
    block_id TEXT NOT NULL REFERENCES blocks(id),
    schedule_id TEXT,
    params TEXT NOT NULL,
    tiling TEXT,
    state TEXT NOT NULL,
    tiles_done INTEGER NOT NULL DEFAULT 0,
    tiles_total INTEGER NOT NULL DEFAULT 0,
    timings TEXT NOT NULL DEFAULT '{}',
    outcome TEXT,
    error TEXT,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    attempts INTEGER NOT NULL DEFAULT 0,
    crashes INTEGER NOT NULL DEFAULT 0,
    retry_at REAL,
    created_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    capture TEXT
);
CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs(state, created_at);
CREATE INDEX IF NOT EXISTS jobs_by_tenant ON jobs(tenant_id, created_at);
CREATE INDEX IF NOT EXISTS jobs_by_block ON jobs(block_id);
CREATE INDEX IF NOT EXISTS jobs_by_tenant_started ON jobs(tenant_id, started_at);
CREATE INDEX IF NOT EXISTS jobs_by_tenant_state ON jobs(tenant_id, state, created_at);
CREATE TABLE IF NOT EXISTS tenant_quotas (
    tenant_id TEXT PRIMARY KEY REFERENCES tenants(id),
    storage_bytes INTEGER,
    queued_jobs INTEGER,
    updated_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS schedules (
    id TEXT PRIMARY KEY,
    tenant_id TEXT NOT NULL REFERENCES tenants(id),
    inbox TEXT NOT NULL,
    cron TEXT NOT NULL,
    params TEXT NOT NULL,
    tiling TEXT,
    created_at REAL NOT NULL,
    last_run_at REAL,
    next_run_at REAL,
    paused INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS schedule_files (
    schedule_id TEXT NOT NULL,
    sha256 TEXT NOT NULL,
    path TEXT NOT NULL,
    job_id TEXT,
    error TEXT,
    seen_at REAL NOT NULL,
    PRIMARY KEY (schedule_id, sha256)
);
CREATE TABLE IF NOT EXISTS capture_hashes (
    path TEXT PRIMARY KEY,
    size INTEGER NOT NULL,
    mtime_ns INTEGER NOT NULL,
    ctime_ns INTEGER NOT NULL,
    inode INTEGER NOT NULL,
    sha256 TEXT NOT NULL
);
"""

_JSON_COLUMNS = ("info", "params", "tiling", "timings", "outcome")


def new_id() -> str:
    """A random, unguessable resource id (32 hex digits)."""
    return uuid.uuid4().hex


def new_token_id() -> str:
    """A token's id: 12 hex digits, shown in listings and used to revoke it (not a secret)."""
    return uuid.uuid4().hex[:12]


def _record(row: sqlite3.Row | None) -> dict[str, Any] | None:
    if row is None:
        return None
    rec = dict(row)
    for key in _JSON_COLUMNS:
        if key in rec and rec[key] is not None:
            rec[key] = json.loads(rec[key])
    return rec


class Store:
    """SQLite job store under ``path`` (created if missing)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        private_dir(self.path.parent)
        private_file(self.path)  # before SQLite opens it: its -wal and -shm files take this file's mode
        self._local = threading.local()
        self._all: list[sqlite3.Connection] = []
        self._all_lock = threading.Lock()
        self._con().executescript(_SCHEMA)
        self._migrate()

    def _migrate(self) -> None:
        """Bring a store written by an earlier version up to the schema (added columns)."""
        self._add_column("jobs", "retry_at", "REAL")
        self._add_column("jobs", "capture", "TEXT")
        self._add_column("jobs", "crashes", "INTEGER NOT NULL DEFAULT 0")
        self._add_column("schedules", "paused", "INTEGER NOT NULL DEFAULT 0")
        self._migrate_tokens()

    def _add_column(self, table: str, column: str, decl: str) -> None:
        def present() -> bool:
            return any(r["name"] == column for r in self._con().execute(f"PRAGMA table_info({table})"))

        if not present():
            try:
                self._con().execute(f"ALTER TABLE {table} ADD COLUMN {column} {decl}")
            except sqlite3.OperationalError:  # another process added it meanwhile
                if not present():
                    raise

    # -- connections and transactions ------------------------------------------------

    def _con(self) -> sqlite3.Connection:
        con = getattr(self._local, "con", None)
        if con is None:
            con = sqlite3.connect(self.path, timeout=30.0, isolation_level=None, check_same_thread=False)
            con.row_factory = sqlite3.Row
            con.execute("PRAGMA journal_mode=WAL")
            con.execute("PRAGMA synchronous=FULL")
            con.execute("PRAGMA foreign_keys=ON")
            con.execute("PRAGMA busy_timeout=30000")
            self._local.con = con
            with self._all_lock:
                self._all.append(con)
        return con

    @contextlib.contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (``BEGIN IMMEDIATE`` … ``COMMIT``, rolled back on error)."""
        con = self._con()
        con.execute("BEGIN IMMEDIATE")
        try:
            yield con
        except BaseException:
            con.execute("ROLLBACK")
            raise
        con.execute("COMMIT")

    def _one(self, sql: str, params: tuple = ()) -> dict[str, Any] | None:
        return _record(self._con().execute(sql, params).fetchone())

    def _all_rows(self, sql: str, params: tuple = ()) -> list[dict[str, Any]]:
        return [_record(r) for r in self._con().execute(sql, params).fetchall()]

    def close(self) -> None:
        with self._all_lock:
            for con in self._all:
                with contextlib.suppress(sqlite3.Error):
                    con.close()
            self._all.clear()
        self._local = threading.local()

    # -- tenants and tokens -----------------------------------------------------------

    def ensure_tenant(self, name: str) -> dict[str, Any]:
        """The tenant called ``name``, created if it does not exist."""
        with self._tx() as con:
            row = con.execute("SELECT * FROM tenants WHERE name = ?", (name,)).fetchone()
            if row is None:
                con.execute("INSERT INTO tenants (id, name, created_at) VALUES (?, ?, ?)", (new_id(), name, time.time()))
                row = con.execute("SELECT * FROM tenants WHERE name = ?", (name,)).fetchone()
        return _record(row)

    def tenant_by_name(self, name: str) -> dict[str, Any]:
        rec = self._one("SELECT * FROM tenants WHERE name = ?", (name,))
        if rec is None:
            raise NotFoundError(f"no tenant called {name!r}; create one with `orchard tokens create --tenant {name}`")
        return rec

    def list_tenants(self) -> list[dict[str, Any]]:
        return self._all_rows(
            "SELECT t.*, (SELECT COUNT(*) FROM tokens k WHERE k.tenant_id = t.id) AS n_tokens FROM tenants t ORDER BY name"
        )

    def _migrate_tokens(self) -> None:
        """Tokens stored before they had ids get one; their visible prefix stays unknown
        (only their hash was kept), and they never expire."""
        for column, decl in (("id", "TEXT"), ("prefix", "TEXT"), ("last_used_at", "REAL"), ("expires_at", "REAL")):
            self._add_column("tokens", column, decl)
        if self._one("SELECT 1 AS x FROM tokens WHERE id IS NULL LIMIT 1") is not None:
            with self._tx() as con:
                for row in con.execute("SELECT hash FROM tokens WHERE id IS NULL").fetchall():
                    con.execute("UPDATE tokens SET id = ? WHERE hash = ?", (new_token_id(), row["hash"]))
        self._con().execute("CREATE UNIQUE INDEX IF NOT EXISTS tokens_by_id ON tokens(id)")

    def add_token(
        self, tenant_id: str, token_hash: str, *, prefix: str | None = None, expires_at: float | None = None
    ) -> dict[str, Any]:
        """Store a token's hash for ``tenant_id``; returns its record (``id``, ``prefix``,
        ``created_at``, ``expires_at`` [s since the epoch] ...)."""
        token_id = new_token_id()
        with self._tx() as con:
            con.execute(
                "INSERT INTO tokens (hash, tenant_id, created_at, id, prefix, expires_at) VALUES (?, ?, ?, ?, ?, ?)",
                (token_hash, tenant_id, time.time(), token_id, prefix, expires_at),
            )
        return self._one("SELECT id, tenant_id, prefix, created_at, last_used_at, expires_at FROM tokens WHERE id = ?", (token_id,))

    def list_tokens(self, tenant_id: str | None = None) -> list[dict[str, Any]]:
        """Tokens (never their hashes) with their tenant's name, by tenant, oldest first."""
        sql = ("SELECT k.id, k.tenant_id, t.name AS tenant, k.prefix, k.created_at, k.last_used_at, k.expires_at "
               "FROM tokens k JOIN tenants t ON t.id = k.tenant_id")
        if tenant_id is None:
            return self._all_rows(sql + " ORDER BY t.name, k.created_at, k.id")
        return self._all_rows(sql + " WHERE k.tenant_id = ? ORDER BY k.created_at, k.id", (tenant_id,))

    def revoke_token(self, token_hash: str) -> bool:
        with self._tx() as con:
            return con.execute("DELETE FROM tokens WHERE hash = ?", (token_hash,)).rowcount > 0

    def revoke_token_id(self, token_id: str) -> bool:
        """Delete the token with this id; False if there is none."""
        with self._tx() as con:
            return con.execute("DELETE FROM tokens WHERE id = ?", (token_id,)).rowcount > 0

    def tenant_for_token(self, token_hash: str) -> dict[str, Any] | None:
        return self._one(
            "SELECT t.* FROM tokens k JOIN tenants t ON t.id = k.tenant_id WHERE k.hash = ?", (token_hash,)
        )

    def token_by_hash(self, token_hash: str) -> dict[str, Any] | None:
        """The token record (``id``, ``prefix``, ``expires_at``, ``last_used_at``) with its
        tenant as ``tenant`` (a tenant record), or None."""
        rec = self._one(
            "SELECT k.id, k.prefix, k.created_at, k.last_used_at, k.expires_at, k.tenant_id FROM tokens k WHERE k.hash = ?",
            (token_hash,),
        )
        if rec is not None:
            rec["tenant"] = self._one("SELECT * FROM tenants WHERE id = ?", (rec["tenant_id"],))
        return rec

    def touch_token(self, token_id: str, at: float) -> None:
        """Record a use of the token at ``at`` [s since the epoch]."""
        with self._tx() as con:
            con.execute("UPDATE tokens SET last_used_at = ? WHERE id = ?", (at, token_id))

    # -- blocks -----------------------------------------------------------------------

    def _located(self, rec: dict[str, Any] | None) -> dict[str, Any] | None:
        """A block record whose ``path`` is where its file is now: a path recorded
        relative to some process's folder (before paths were made absolute), or under a
        data folder since moved or mounted elsewhere, is looked up in this store's own
        ``blocks/`` folder, where every block file lives under its checksum name."""
        if rec is None:
            return None
        path = Path(rec["path"])
        if not path.is_absolute() or not path.exists():
            here = self.path.parent / "blocks" / path.name
            if here.exists() or not path.is_absolute():
                rec["path"] = str(here.absolute())
        return rec

    def block_file_used(self, path: str) -> bool:
        """Whether any tenant's block is recorded at ``path``."""
        return self._one("SELECT 1 AS used FROM blocks WHERE path = ?", (path,)) is not None

    def block_by_sha(self, tenant_id: str, sha256: str) -> dict[str, Any] | None:
        return self._located(self._one("SELECT * FROM blocks WHERE tenant_id = ? AND sha256 = ?", (tenant_id, sha256)))

    def insert_block(
        self, *, tenant_id: str, sha256: str, path: str, filename: str | None, size_bytes: int, info: dict
    ) -> tuple[dict[str, Any], bool]:
        """Insert a block; if the tenant already has this file (same sha256), return that one.

        Returns ``(block, created)``.
        """
        with self._tx() as con:
            row = con.execute("SELECT * FROM blocks WHERE tenant_id = ? AND sha256 = ?", (tenant_id, sha256)).fetchone()
            if row is not None:
                if row["path"] != path and not Path(row["path"]).exists():  # its file was landed again
                    con.execute("UPDATE blocks SET path = ? WHERE id = ?", (path, row["id"]))
                    row = con.execute("SELECT * FROM blocks WHERE id = ?", (row["id"],)).fetchone()
                return self._located(_record(row)), False
            self._check_storage(con, tenant_id, size_bytes)
            bid = new_id()
            con.execute(
                "INSERT INTO blocks (id, tenant_id, sha256, path, filename, size_bytes, info, created_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (bid, tenant_id, sha256, path, filename, size_bytes, json.dumps(info), time.time()),
            )
            row = con.execute("SELECT * FROM blocks WHERE id = ?", (bid,)).fetchone()
        return self._located(_record(row)), True

    def get_block(self, tenant_id: str | None, block_id: str) -> dict[str, Any]:
        if tenant_id is None:
            rec = self._one("SELECT * FROM blocks WHERE id = ?", (block_id,))
        else:
            rec = self._one("SELECT * FROM blocks WHERE id = ? AND tenant_id = ?", (block_id, tenant_id))
        if rec is None:
            raise NotFoundError(f"no block {block_id!r}; list yours with GET /v1/blocks")
        return self._located(rec)

    def list_blocks(self, tenant_id: str, *, limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        return [self._located(rec) for rec in self._all_rows(
            "SELECT * FROM blocks WHERE tenant_id = ? ORDER BY created_at DESC, id DESC LIMIT ? OFFSET ?", (tenant_id, limit, offset)
        )]

    # -- jobs -------------------------------------------------------------------------

    def create_job(
        self, *, tenant_id: str, block_id: str, params: dict, tiling: dict | None, schedule_id: str | None = None
    ) -> dict[str, Any]:
        jid = new_id()
        with self._tx() as con:
            self._check_queue(con, tenant_id)
            con.execute(
                "INSERT INTO jobs (id, tenant_id, block_id, schedule_id, params, tiling, state, created_at) "
                "VALUES (?, ?, ?, ?, ?, ?, 'queued', ?)",
                (jid, tenant_id, block_id, schedule_id, json.dumps(params), json.dumps(tiling) if tiling else None, time.time()),
            )
        return self.get_job(None, jid)

    def get_job(self, tenant_id: str | None, job_id: str) -> dict[str, Any]:
        if tenant_id is None:
            rec = self._one("SELECT * FROM jobs WHERE id = ?", (job_id,))
        else:
            rec = self._one("SELECT * FROM jobs WHERE id = ? AND tenant_id = ?", (job_id, tenant_id))
        if rec is None:
            raise NotFoundError(f"no job {job_id!r}; list yours with GET /v1/jobs")
        return rec

    def list_jobs(
        self,
        tenant_id: str,
        *,
        state: str | None = None,
        block_id: str | None = None,
        schedule_id: str | None = None,
        limit: int = 100,
        offset: int = 0,
    ) -> list[dict[str, Any]]:
        sql = "SELECT * FROM jobs WHERE tenant_id = ?"
        params: list[Any] = [tenant_id]
        for column, value in (("state", state), ("block_id", block_id), ("schedule_id", schedule_id)):
            if value is not None:
                sql += f" AND {column} = ?"
                params.append(value)
        sql += " ORDER BY created_at DESC, id DESC LIMIT ? OFFSET ?"  # newest first: last night's jobs on the first page
        params += [limit, offset]
        return self._all_rows(sql, tuple(params))

    def count_jobs(
        self, tenant_id: str, *, state: str | None = None, block_id: str | None = None, schedule_id: str | None = None
    ) -> int:
        """How many jobs `list_jobs` with these filters lists over all its pages."""
        sql = "SELECT COUNT(*) AS n FROM jobs WHERE tenant_id = ?"
        params: list[Any] = [tenant_id]
        for column, value in (("state", state), ("block_id", block_id), ("schedule_id", schedule_id)):
            if value is not None:
                sql += f" AND {column} = ?"
                params.append(value)
        return self._one(sql, tuple(params))["n"]

    def claim_next_job(self) -> dict[str, Any] | None:
        """Move the next queued job to ``running`` and return it (None if the queue is
        empty, or holds only jobs waiting for their retry time).

        Fair share between tenants: the job comes from the tenant with a job ready that
        has the fewest jobs running, then the one served least recently (its latest
        job's start; never served first), then the one whose oldest ready job is
        oldest; within a tenant, oldest first. One farm's hundred queued jobs delay
        another's by at most one job each.
        """
        now = time.time()
        with self._tx() as con:
            row = con.execute(
                "WITH ready AS (SELECT tenant_id, MIN(created_at) AS oldest FROM jobs "
                "  WHERE state = 'queued' AND (retry_at IS NULL OR retry_at <= :now) GROUP BY tenant_id), "
                "pick AS (SELECT r.tenant_id FROM ready r ORDER BY "
                "  (SELECT COUNT(*) FROM jobs x WHERE x.tenant_id = r.tenant_id AND x.state = 'running'), "
                "  COALESCE((SELECT MAX(x.started_at) FROM jobs x WHERE x.tenant_id = r.tenant_id), 0), "
                "  r.oldest, r.tenant_id LIMIT 1) "
                "SELECT id FROM jobs WHERE tenant_id = (SELECT tenant_id FROM pick) AND state = 'queued' "
                "AND (retry_at IS NULL OR retry_at <= :now) ORDER BY created_at, id LIMIT 1",
                {"now": now},
            ).fetchone()
            if row is None:
                return None
            con.execute(
                "UPDATE jobs SET state = 'running', started_at = ?, attempts = attempts + 1, error = NULL, "
                "retry_at = NULL WHERE id = ?",
                (now, row["id"]),
            )
            job = con.execute("SELECT * FROM jobs WHERE id = ?", (row["id"],)).fetchone()
        return _record(job)

    def set_progress(self, job_id: str, done: int, total: int) -> None:
        with self._tx() as con:
            con.execute(
                "UPDATE jobs SET tiles_done = ?, tiles_total = ? WHERE id = ? AND state = 'running'", (done, total, job_id)
            )

    def finish_job(
        self,
        job_id: str,
        state: str,
        *,
        error: str | None = None,
        outcome: dict | None = None,
        timings: dict | None = None,
    ) -> dict[str, Any]:
        """Move a running job to a final state (``done``, ``failed`` or ``cancelled``)."""
        if state not in FINAL_STATES:
            raise ValueError(f"not a final state: {state}")
        with self._tx() as con:
            sets = "state = ?, error = ?, finished_at = ?"
            params: list[Any] = [state, error, time.time()]
            if outcome is not None:
                sets += ", outcome = ?"
                params.append(json.dumps(outcome))
            if timings is not None:
                sets += ", timings = ?"
                params.append(json.dumps(timings))
            if state == "done":
                sets += ", tiles_done = tiles_total"
            con.execute(f"UPDATE jobs SET {sets} WHERE id = ? AND state = 'running'", (*params, job_id))
        return self.get_job(None, job_id)

    def retry_job(self, job_id: str, *, error: str, retry_at: float) -> dict[str, Any]:
        """Put a running job back in the queue, to be taken again from ``retry_at`` (epoch
        seconds); ``error`` says why its last attempt failed."""
        with self._tx() as con:
            con.execute(
                "UPDATE jobs SET state = 'queued', error = ?, retry_at = ?, tiles_done = 0, tiles_total = 0 "
                "WHERE id = ? AND state = 'running'",
                (error, retry_at, job_id),
            )
        return self.get_job(None, job_id)

    def request_cancel(self, tenant_id: str, job_id: str) -> dict[str, Any]:
        """Cancel a job: a queued one at once, a running one as soon as the runner sees the request."""
        with self._tx() as con:
            row = con.execute("SELECT state FROM jobs WHERE id = ? AND tenant_id = ?", (job_id, tenant_id)).fetchone()
            if row is None:
                raise NotFoundError(f"no job {job_id!r}; list yours with GET /v1/jobs")
            if row["state"] == "queued":
                con.execute(
                    "UPDATE jobs SET state = 'cancelled', cancel_requested = 1, finished_at = ?, error = ? WHERE id = ?",
                    (time.time(), "cancelled before it started", job_id),
                )
            elif row["state"] == "running":
                con.execute("UPDATE jobs SET cancel_requested = 1 WHERE id = ?", (job_id,))
            else:
                raise ConflictError(f"job {job_id} is already {row['state']}; only queued or running jobs can be cancelled")
        return self.get_job(None, job_id)

    def cancel_requested(self, job_id: str) -> bool:
        rec = self._one("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,))
        return bool(rec and rec["cancel_requested"])

    def cancel_interrupted(self) -> list[str]:
        """Cancel the jobs left ``running`` by a dead service that had been asked to stop;
        returns their ids (their work stores are the caller's to delete)."""
        with self._tx() as con:
            ids = [r["id"] for r in con.execute("SELECT id FROM jobs WHERE state = 'running' AND cancel_requested = 1")]
            con.executemany(
                "UPDATE jobs SET state = 'cancelled', finished_at = ?, error = 'cancelled on request' WHERE id = ?",
                [(time.time(), jid) for jid in ids],
            )
        return ids

    def release_job(self, job_id: str) -> None:
        """Put a running job back in the queue as if it had not been claimed (the service
        is stopping): a restart is no attempt of the job's, and must not use up the
        retries meant for a lost cluster."""
        with self._tx() as con:
            con.execute(
                "UPDATE jobs SET state = 'queued', tiles_done = 0, tiles_total = 0, attempts = MAX(attempts - 1, 0) "
                "WHERE id = ? AND state = 'running'",
                (job_id,),
            )

    def requeue_running(self, *, max_crashes: int | None = None) -> int:
        """Put jobs left ``running`` by a dead service back in the queue (those asked to
        stop are cancelled instead, see `cancel_interrupted`).

        The service's death is counted in the job's ``crashes``, not its ``attempts``
        (those are for a lost cluster, `Runner` retries). A job during which the service
        has now died ``max_crashes`` times is failed instead (a poison job: it would take
        the service down at every start, and the rest of the queue with it).

        Called once at start-up, before the runner takes jobs. Returns the number re-queued.
        """
        self.cancel_interrupted()
        with self._tx() as con:
            con.execute(
                "UPDATE jobs SET crashes = crashes + 1, attempts = MAX(attempts - 1, 0), tiles_done = 0, "
                "tiles_total = 0 WHERE state = 'running'"
            )
            poisoned = []
            if max_crashes is not None:
                poisoned = [(r["id"], r["crashes"]) for r in con.execute(
                    "SELECT id, crashes FROM jobs WHERE state = 'running' AND crashes >= ?", (max_crashes,))]
                con.executemany(
                    "UPDATE jobs SET state = 'failed', finished_at = ?, retry_at = NULL, error = 'the service stopped ' "
                    "|| crashes || ' times while running this job; it is not retried (it may be what stops the "
                    "service: see the service log; submit it again to retry)' WHERE id = ?",
                    [(time.time(), jid) for jid, _ in poisoned],
                )
            n = con.execute("UPDATE jobs SET state = 'queued' WHERE state = 'running'").rowcount
        for jid, crashes in poisoned:
            log.warning("job %s failed: the service stopped %d times while running it", jid, crashes)
        return n

    # -- tenant quotas ----------------------------------------------------------------

    def set_quota(self, tenant_id: str, **limits: int | None) -> dict[str, Any]:
        """Set a tenant's ``storage_bytes`` and/or ``queued_jobs`` limit (the keys given;
        None = unlimited); returns `quota`. What the tenant holds already is kept."""
        if not limits.keys() <= {"storage_bytes", "queued_jobs"}:
            raise ValueError(f"not a quota: {sorted(limits.keys() - {'storage_bytes', 'queued_jobs'})}")
        with self._tx() as con:
            con.execute("INSERT OR IGNORE INTO tenant_quotas (tenant_id, updated_at) VALUES (?, ?)", (tenant_id, time.time()))
            for key, value in limits.items():
                con.execute(f"UPDATE tenant_quotas SET {key} = ?, updated_at = ? WHERE tenant_id = ?",
                            (None if value is None else int(value), time.time(), tenant_id))
        return self.quota(tenant_id)

    def quota(self, tenant_id: str) -> dict[str, Any]:
        """A tenant's limits and use: ``{"storage_bytes", "queued_jobs"}`` (limits, None =
        unlimited) and ``{"used_storage_bytes", "used_queued_jobs"}``."""
        con = self._con()
        row = con.execute("SELECT storage_bytes, queued_jobs FROM tenant_quotas WHERE tenant_id = ?", (tenant_id,)).fetchone()
        return {
            "storage_bytes": None if row is None else row["storage_bytes"],
            "queued_jobs": None if row is None else row["queued_jobs"],
            "used_storage_bytes": self._stored_bytes(con, tenant_id),
            "used_queued_jobs": self._queued_jobs(con, tenant_id),
        }

    @staticmethod
    def _stored_bytes(con: sqlite3.Connection, tenant_id: str) -> int:
        return int(con.execute("SELECT COALESCE(SUM(size_bytes), 0) FROM blocks WHERE tenant_id = ?", (tenant_id,)).fetchone()[0])

    @staticmethod
    def _queued_jobs(con: sqlite3.Connection, tenant_id: str) -> int:
        return int(con.execute("SELECT COUNT(*) FROM jobs WHERE tenant_id = ? AND state = 'queued'", (tenant_id,)).fetchone()[0])

    @staticmethod
    def _limit(con: sqlite3.Connection, tenant_id: str, column: str) -> tuple[int | None, str]:
        row = con.execute(
            f"SELECT q.{column} AS lim, t.name FROM tenants t LEFT JOIN tenant_quotas q ON q.tenant_id = t.id WHERE t.id = ?",
            (tenant_id,),
        ).fetchone()
        return (None, "") if row is None else (row["lim"], row["name"])

    def _check_storage(self, con: sqlite3.Connection, tenant_id: str, size_bytes: int) -> None:
        limit, name = self._limit(con, tenant_id, "storage_bytes")
        if limit is not None:
            used = self._stored_bytes(con, tenant_id)
            if used + size_bytes > limit:
                raise StorageQuotaExceeded(tenant=name, limit=limit, used=used, requested=size_bytes)

    def _check_queue(self, con: sqlite3.Connection, tenant_id: str) -> None:
        limit, name = self._limit(con, tenant_id, "queued_jobs")
        if limit is not None:
            used = self._queued_jobs(con, tenant_id)
            if used + 1 > limit:
                raise QueueQuotaExceeded(tenant=name, limit=limit, used=used)

    def check_storage(self, tenant_id: str, size_bytes: int) -> None:
        """StorageQuotaExceeded if a new block of ``size_bytes`` would not fit the
        tenant's storage quota now: asked before a file is copied or landed, so a refused
        one costs nothing (`insert_block` checks again when it records the block)."""
        self._check_storage(self._con(), tenant_id, size_bytes)

    # -- schedules --------------------------------------------------------------------

    def create_schedule(
        self, *, tenant_id: str, inbox: str, cron: str, params: dict, tiling: dict | None, next_run_at: float | None
    ) -> dict[str, Any]:
        sid = new_id()
        with self._tx() as con:
            # one schedule per inbox, checked inside the write transaction: requests at the
            # same moment cannot both pass (BEGIN IMMEDIATE serialises them)
            other = con.execute("SELECT id, tenant_id FROM schedules WHERE inbox = ?", (inbox,)).fetchone()
            if other is not None:
                whose = "this tenant's" if other[1] == tenant_id else "another tenant's"
                raise ParameterError(f"inbox {inbox!r} already has a schedule ({whose}); one schedule per inbox")
            con.execute(
                "INSERT INTO schedules (id, tenant_id, inbox, cron, params, tiling, created_at, next_run_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (sid, tenant_id, inbox, cron, json.dumps(params), json.dumps(tiling) if tiling else None, time.time(), next_run_at),
            )
        return self.get_schedule(None, sid)

    def get_schedule(self, tenant_id: str | None, schedule_id: str) -> dict[str, Any]:
        if tenant_id is None:
            rec = self._one("SELECT * FROM schedules WHERE id = ?", (schedule_id,))
        else:
            rec = self._one("SELECT * FROM schedules WHERE id = ? AND tenant_id = ?", (schedule_id, tenant_id))
        if rec is None:
            raise NotFoundError(f"no schedule {schedule_id!r}; list yours with GET /v1/schedules")
        return rec

    def list_schedules(self, tenant_id: str | None = None) -> list[dict[str, Any]]:
        if tenant_id is None:
            return self._all_rows("SELECT * FROM schedules ORDER BY created_at, id")
        return self._all_rows("SELECT * FROM schedules WHERE tenant_id = ? ORDER BY created_at, id", (tenant_id,))

    def delete_schedule(self, tenant_id: str, schedule_id: str) -> None:
        with self._tx() as con:
            n = con.execute("DELETE FROM schedules WHERE id = ? AND tenant_id = ?", (schedule_id, tenant_id)).rowcount
            if n == 0:
                raise NotFoundError(f"no schedule {schedule_id!r}; list yours with GET /v1/schedules")
            con.execute("DELETE FROM schedule_files WHERE schedule_id = ?", (schedule_id,))

    def set_schedule_times(self, schedule_id: str, *, cron: str, last_run_at: float | None, next_run_at: float | None) -> None:
        """Record a run and the next one, computed from ``cron``: left alone if the
        schedule was paused or given another cron meanwhile (that change set its own)."""
        with self._tx() as con:
            con.execute(
                "UPDATE schedules SET last_run_at = COALESCE(?, last_run_at), next_run_at = ? "
                "WHERE id = ? AND cron = ? AND paused = 0",
                (last_run_at, next_run_at, schedule_id, cron),
            )

    def bring_schedule_forward(self, schedule_id: str, at: float) -> None:
        """Run a schedule at ``at`` if its next run is later (or not set) and it is not paused."""
        with self._tx() as con:
            con.execute(
                "UPDATE schedules SET next_run_at = ? WHERE id = ? AND paused = 0 AND (next_run_at IS NULL OR next_run_at > ?)",
                (at, schedule_id, at),
            )

    def update_schedule(
        self, tenant_id: str | None, schedule_id: str, changes: dict[str, Any] | Callable[[dict[str, Any]], dict[str, Any]]
    ) -> dict[str, Any]:
        """Change a schedule's ``cron``, ``params``, ``tiling``, ``paused`` and
        ``next_run_at`` (the keys given) in one transaction. ``changes`` may be a function
        of the schedule as stored, called inside that transaction, so that what it checks
        (a tiling against the parameters) cannot be changed by another request meanwhile."""
        allowed = {"cron", "params", "tiling", "paused", "next_run_at"}
        where, args = "id = ?", [schedule_id]
        if tenant_id is not None:
            where, args = "id = ? AND tenant_id = ?", [schedule_id, tenant_id]
        with self._tx() as con:
            current = _record(con.execute(f"SELECT * FROM schedules WHERE {where}", args).fetchone())
            if current is None:
                raise NotFoundError(f"no schedule {schedule_id!r}; list yours with GET /v1/schedules")
            if callable(changes):
                changes = changes(current)
            if not changes.keys() <= allowed:
                raise ValueError(f"not a schedule setting: {sorted(changes.keys() - allowed)}")
            values = {k: (json.dumps(v) if k in ("params", "tiling") and v is not None else v) for k, v in changes.items()}
            if "paused" in values:
                values["paused"] = int(bool(values["paused"]))
            if values:
                con.execute(f"UPDATE schedules SET {', '.join(f'{k} = ?' for k in values)} WHERE {where}",
                            [*values.values(), *args])
        return self.get_schedule(tenant_id, schedule_id)

    def known_hash(self, path: str, state: tuple[int, int, int, int]) -> str | None:
        """The sha256 of an inbox file hashed before and unchanged since (``state``: size,
        mtime_ns, ctime_ns, inode), or None: scans re-read every capture left in an inbox
        every night."""
        row = self._one(
            "SELECT sha256 FROM capture_hashes WHERE path = ? AND size = ? AND mtime_ns = ? AND ctime_ns = ? AND inode = ?",
            (path, *state),
        )
        return None if row is None else row["sha256"]

    def remember_hash(self, path: str, state: tuple[int, int, int, int], sha256: str) -> None:
        with self._tx() as con:
            con.execute(
                "INSERT OR REPLACE INTO capture_hashes (path, size, mtime_ns, ctime_ns, inode, sha256) VALUES (?, ?, ?, ?, ?, ?)",
                (path, *state, sha256),
            )

    def schedule_file_seen(self, schedule_id: str, sha256: str) -> bool:
        return self._one(
            "SELECT 1 AS seen FROM schedule_files WHERE schedule_id = ? AND sha256 = ?", (schedule_id, sha256)
        ) is not None

    def record_schedule_file(
        self, *, schedule_id: str, sha256: str, path: str, job_id: str | None, error: str | None
    ) -> bool:
        """Record that a capture was handled; False if it already was (another scan got there first)."""
        with self._tx() as con:
            try:
                con.execute(
                    "INSERT INTO schedule_files (schedule_id, sha256, path, job_id, error, seen_at) VALUES (?, ?, ?, ?, ?, ?)",
                    (schedule_id, sha256, path, job_id, error, time.time()),
                )
            except sqlite3.IntegrityError:
                return False
        return True

    def create_scheduled_job(
        self, *, schedule: dict[str, Any], block_id: str, sha256: str, path: str, capture: str | None = None
    ) -> dict[str, Any] | None:
        """Queue the job of a capture a schedule found and record the capture as handled,
        in one transaction; None (nothing queued) if the capture was handled already,
        e.g. by a scan of the same inbox running at the same moment in another process.
        ``capture`` is the file's name as shown to the farm (the block may be an earlier
        upload of the same bytes under another name)."""
        jid = new_id()
        with self._tx() as con:
            try:
                con.execute(
                    "INSERT INTO schedule_files (schedule_id, sha256, path, job_id, error, seen_at) VALUES (?, ?, ?, ?, ?, ?)",
                    (schedule["id"], sha256, path, jid, None, time.time()),
                )
            except sqlite3.IntegrityError:
                return None
            self._check_queue(con, schedule["tenant_id"])  # rolls the capture's record back too
            con.execute(
                "INSERT INTO jobs (id, tenant_id, block_id, schedule_id, params, tiling, state, created_at, capture) "
                "VALUES (?, ?, ?, ?, ?, ?, 'queued', ?, ?)",
                (jid, schedule["tenant_id"], block_id, schedule["id"], json.dumps(schedule["params"]),
                 json.dumps(schedule["tiling"]) if schedule["tiling"] else None, time.time(), capture),
            )
        return self.get_job(None, jid)

    def capture_scheduled(self, tenant_id: str, sha256: str) -> bool:
        """Whether a schedule of this tenant (any, deleted ones too) already queued a job
        for the capture with this sha256."""
        return self._one(
            "SELECT 1 AS seen FROM jobs j JOIN blocks b ON b.id = j.block_id "
            "WHERE b.tenant_id = ? AND b.sha256 = ? AND j.schedule_id IS NOT NULL LIMIT 1",
            (tenant_id, sha256),
        ) is not None

    def schedule_files(self, schedule_id: str) -> list[dict[str, Any]]:
        return self._all_rows("SELECT * FROM schedule_files WHERE schedule_id = ? ORDER BY seen_at", (schedule_id,))


# -- block files ----------------------------------------------------------------------------


def _sniff_suffix(path: Path) -> str:
    """``.laz`` if the LAS header says the points are compressed, else ``.las``."""
    with open(path, "rb") as fh:
        head = fh.read(105)
    if len(head) > 104 and head[:4] == b"LASF" and head[104] & 0x80:
        return ".laz"
    return ".las"


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def info_record(info: Any) -> dict[str, Any]:
    """A BlockInfo as JSON-able dict (without the server-side path)."""
    rec = dataclasses.asdict(info) if dataclasses.is_dataclass(info) else dict(info)
    rec.pop("path", None)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in rec.items()}


def accept_block(
    store: Store,
    *,
    blocks_dir: Path,
    tenant_id: str,
    tmp_path: Path,
    sha256: str,
    size_bytes: int,
    filename: str | None,
) -> tuple[dict[str, Any], bool]:
    """Validate a fully written temporary file and land it as a block of ``tenant_id``.

    The header is checked with `pipeline.blockinfo.read_info` (InputError if not a usable
    LAS/LAZ file). The file is stored under its checksum, fsynced, renamed into place,
    and only then recorded. The temporary file is always gone afterwards. Returns
    ``(block, created)``; the same file twice gives the same block.
    """
    from pipeline.blockinfo import read_info

    tmp_path = Path(tmp_path)
    try:
        existing = store.block_by_sha(tenant_id, sha256)
        if existing is not None and Path(existing["path"]).exists():
            return existing, False
        if size_bytes == 0:
            raise InputError("the file is empty (0 bytes); upload a LAS or LAZ file")
        store.check_storage(tenant_id, size_bytes)
        suffix = _sniff_suffix(tmp_path)
        typed = tmp_path.with_suffix(suffix)
        os.replace(tmp_path, typed)
        tmp_path = typed
        try:
            info = read_info(str(tmp_path))
        except InputError as exc:
            text = str(exc).replace(tmp_path.name, filename or "the upload")
            raise InputError(text) from None
        blocks_dir.mkdir(parents=True, exist_ok=True)
        final = blocks_dir / f"{sha256}{'.laz' if getattr(info, 'compressed', suffix == '.laz') else '.las'}"
        landed = not final.exists()
        if landed:
            with open(tmp_path, "rb+") as fh:
                os.fchmod(fh.fileno(), FILE_MODE)  # a farm's file: the service user's alone
                os.fsync(fh.fileno())
            os.replace(tmp_path, final)
            _fsync_dir(blocks_dir)
        try:
            return store.insert_block(
                tenant_id=tenant_id,
                sha256=sha256,
                path=str(final),
                filename=filename,
                size_bytes=size_bytes,
                info=info_record(info),
            )
        except StorageQuotaExceeded:  # another upload of the tenant's took the room meanwhile
            if landed and not store.block_file_used(str(final)):
                final.unlink(missing_ok=True)
            raise
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
