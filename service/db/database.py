"""The job store's SQLite database: schema, migrations, connections and transactions.

One connection per thread, every state change in one ``BEGIN IMMEDIATE`` transaction,
so the HTTP threads, the job runner and the schedule clock (and a second process such
as ``orchard tokens create``) can share the file (WAL mode). Records are returned as
plain dicts with JSON columns decoded.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import threading
import uuid
from pathlib import Path
from typing import Any, Iterator

from service.permissions import private_dir, private_file

#: every table as the current version creates it; a store written by an earlier version
#: gets the columns it lacks from `Database._migrate`
SCHEMA = """
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
    job TEXT NOT NULL,
    state TEXT NOT NULL,
    tiles_done INTEGER NOT NULL DEFAULT 0,
    tiles_total INTEGER NOT NULL DEFAULT 0,
    timings TEXT NOT NULL DEFAULT '{}',
    outcome TEXT,
    error TEXT,
    error_kind TEXT,
    error_fields TEXT,
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
    job TEXT NOT NULL,
    created_at REAL NOT NULL,
    last_run_at REAL,
    next_run_at REAL,
    paused INTEGER NOT NULL DEFAULT 0,
    orchard_block_id TEXT
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
CREATE TABLE IF NOT EXISTS orchard_blocks (
    id TEXT PRIMARY KEY,
    tenant_id TEXT NOT NULL REFERENCES tenants(id),
    name TEXT NOT NULL,
    created_at REAL NOT NULL,
    UNIQUE (tenant_id, name)
);
CREATE TABLE IF NOT EXISTS captures (
    id TEXT PRIMARY KEY,
    tenant_id TEXT NOT NULL REFERENCES tenants(id),
    orchard_block_id TEXT NOT NULL REFERENCES orchard_blocks(id),
    seq INTEGER NOT NULL,
    block_id TEXT NOT NULL REFERENCES blocks(id),
    job_id TEXT NOT NULL UNIQUE REFERENCES jobs(id),
    captured_at TEXT,
    captured_at_source TEXT,
    given_captured_at TEXT,
    arrived_at REAL NOT NULL,
    record TEXT,
    UNIQUE (orchard_block_id, seq)
);
CREATE INDEX IF NOT EXISTS captures_by_tenant ON captures(tenant_id, orchard_block_id, seq);
CREATE TABLE IF NOT EXISTS capture_hashes (
    path TEXT PRIMARY KEY,
    size INTEGER NOT NULL,
    mtime_ns INTEGER NOT NULL,
    ctime_ns INTEGER NOT NULL,
    inode INTEGER NOT NULL,
    sha256 TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS webhooks (
    id TEXT PRIMARY KEY,
    tenant_id TEXT NOT NULL REFERENCES tenants(id),
    schedule_id TEXT,
    url TEXT NOT NULL,
    secret TEXT NOT NULL,
    events TEXT NOT NULL,
    created_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS webhook_deliveries (
    id TEXT PRIMARY KEY,
    webhook_id TEXT NOT NULL,
    tenant_id TEXT NOT NULL,
    event TEXT NOT NULL,
    body TEXT NOT NULL,
    state TEXT NOT NULL,
    attempts INTEGER NOT NULL DEFAULT 0,
    status_code INTEGER,
    error TEXT,
    tries TEXT NOT NULL DEFAULT '[]',
    created_at REAL NOT NULL,
    next_attempt_at REAL,
    finished_at REAL
);
CREATE INDEX IF NOT EXISTS webhook_deliveries_due ON webhook_deliveries(state, next_attempt_at);
"""

#: columns stored as JSON text, decoded by `record`
JSON_COLUMNS = ("info", "job", "timings", "outcome", "record", "error_fields", "job_error_fields")

#: the fields of a job's tiling that the ``tiling`` column of a store written before
#: jobs were stored whole could hold (`Database._merge_job_columns`)
_OLD_TILING = ("tile_size", "buffer", "grid_origin")


def new_id() -> str:
    """A random, unguessable resource id (32 hex digits)."""
    return uuid.uuid4().hex


def new_token_id() -> str:
    """A token's id: 12 hex digits, shown in listings and used to revoke it (not a secret)."""
    return uuid.uuid4().hex[:12]


def record(row: sqlite3.Row | None) -> dict[str, Any] | None:
    """A row as a plain dict with its JSON columns decoded (None stays None)."""
    if row is None:
        return None
    rec = dict(row)
    for key in JSON_COLUMNS:
        if key in rec and rec[key] is not None:
            rec[key] = json.loads(rec[key])
    return rec


class Database:
    """The SQLite file under ``path`` (created if missing, brought up to the schema),
    with one connection per thread."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        private_dir(self.path.parent)
        private_file(self.path)  # before SQLite opens it: its -wal and -shm files take this file's mode
        self._local = threading.local()
        self._all: list[sqlite3.Connection] = []
        self._all_lock = threading.Lock()
        self.connection().executescript(SCHEMA)
        self._migrate()

    def _migrate(self) -> None:
        """Bring a store written by an earlier version up to the schema (added columns; a
        table it lacks was made by `SCHEMA`)."""
        self._add_column("jobs", "retry_at", "REAL")
        self._add_column("jobs", "capture", "TEXT")
        self._add_column("jobs", "crashes", "INTEGER NOT NULL DEFAULT 0")
        self._add_column("schedules", "paused", "INTEGER NOT NULL DEFAULT 0")
        self._add_column("schedules", "orchard_block_id", "TEXT")  # (orchard_blocks and captures: new tables)
        self._add_column("jobs", "error_kind", "TEXT")
        self._add_column("jobs", "error_fields", "TEXT")
        self._merge_job_columns()
        self._migrate_tokens()

    def _merge_job_columns(self) -> None:
        """A store written before a job's parameters were stored whole kept them in two
        columns of ``jobs`` and ``schedules``, ``params`` (the pipeline's) and ``tiling``
        (the request's tile size and buffer; NULL: one tile): they become the one ``job``
        column (a `pipeline.jobparams.JobParams`' fields), in place, in one transaction."""
        def merged(con) -> list[str]:
            return [t for t in ("jobs", "schedules")
                    if "params" in {r["name"] for r in con.execute(f"PRAGMA table_info({t})")}]

        if not merged(self.connection()):
            return
        with self.transaction() as con:
            for table in merged(con):  # (another process may have merged them meanwhile)
                con.execute(f"ALTER TABLE {table} ADD COLUMN job TEXT NOT NULL DEFAULT '{{}}'")
                for row in con.execute(f"SELECT rowid, params, tiling FROM {table}").fetchall():
                    tiling = json.loads(row["tiling"]) if row["tiling"] else {}
                    job = {"pipeline": json.loads(row["params"]), "tiling": {k: tiling[k] for k in _OLD_TILING if k in tiling}}
                    con.execute(f"UPDATE {table} SET job = ? WHERE rowid = ?", (json.dumps(job), row["rowid"]))
                con.execute(f"ALTER TABLE {table} DROP COLUMN params")
                con.execute(f"ALTER TABLE {table} DROP COLUMN tiling")

    def _migrate_tokens(self) -> None:
        """Tokens stored before they had ids get one; their visible prefix stays unknown
        (only their hash was kept), and they never expire."""
        for column, decl in (("id", "TEXT"), ("prefix", "TEXT"), ("last_used_at", "REAL"), ("expires_at", "REAL")):
            self._add_column("tokens", column, decl)
        if self.one("SELECT 1 AS x FROM tokens WHERE id IS NULL LIMIT 1") is not None:
            with self.transaction() as con:
                for row in con.execute("SELECT hash FROM tokens WHERE id IS NULL").fetchall():
                    con.execute("UPDATE tokens SET id = ? WHERE hash = ?", (new_token_id(), row["hash"]))
        self.connection().execute("CREATE UNIQUE INDEX IF NOT EXISTS tokens_by_id ON tokens(id)")

    def _add_column(self, table: str, column: str, decl: str) -> None:
        def present() -> bool:
            return any(r["name"] == column for r in self.connection().execute(f"PRAGMA table_info({table})"))

        if not present():
            try:
                self.connection().execute(f"ALTER TABLE {table} ADD COLUMN {column} {decl}")
            except sqlite3.OperationalError:  # another process added it meanwhile
                if not present():
                    raise

    # -- connections and transactions ------------------------------------------------

    def connection(self) -> sqlite3.Connection:
        """This thread's connection, opened on first use."""
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
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (``BEGIN IMMEDIATE`` … ``COMMIT``, rolled back on error)."""
        con = self.connection()
        con.execute("BEGIN IMMEDIATE")
        try:
            yield con
        except BaseException:
            con.execute("ROLLBACK")
            raise
        con.execute("COMMIT")

    def one(self, sql: str, params: tuple = ()) -> dict[str, Any] | None:
        """The first row of a query as a record (None if it has none)."""
        return record(self.connection().execute(sql, params).fetchone())

    def rows(self, sql: str, params: tuple = ()) -> list[dict[str, Any]]:
        """Every row of a query as records."""
        return [record(r) for r in self.connection().execute(sql, params).fetchall()]

    def close(self) -> None:
        """Close every thread's connection; a later call opens new ones."""
        with self._all_lock:
            for con in self._all:
                with contextlib.suppress(sqlite3.Error):
                    con.close()
            self._all.clear()
        self._local = threading.local()

