"""The job queue (``jobs``): submitting, fair-share claiming, progress, retries,
cancellation and recovery after the service died."""

from __future__ import annotations

import json
import logging
import time
from typing import Any

from service.db.database import Database, new_id, record
from service.db.errors import ConflictError, NotFoundError
from service.db.tenant_quotas import check_queue_in

log = logging.getLogger("orchard.store")

JOB_STATES = ("queued", "running", "done", "failed", "cancelled")
FINAL_STATES = ("done", "failed", "cancelled")

#: a queued job that must wait: an earlier capture of its orchard block (`service.db.
#: orchard_blocks`) is still queued or running, as a block's captures are processed one
#: at a time in arrival order, each registered to the one before it (``jobs``: the
#: candidate job's table)
CAPTURE_WAITS = (
    "EXISTS (SELECT 1 FROM captures c JOIN captures e ON e.orchard_block_id = c.orchard_block_id AND e.seq < c.seq "
    "JOIN jobs ej ON ej.id = e.job_id WHERE c.job_id = jobs.id AND ej.state IN ('queued', 'running'))"
)


class JobQueue:
    """The ``jobs`` table (a job is queued within its tenant's queue quota)."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def create(
        self, *, tenant_id: str, block_id: str, job: dict, schedule_id: str | None = None
    ) -> dict[str, Any]:
        """Queue a job; ``job`` is its parameters whole (a `pipeline.jobparams.JobParams`
        as JSON), kept as given."""
        jid = new_id()
        with self.db.transaction() as con:
            check_queue_in(con, tenant_id)
            con.execute(
                "INSERT INTO jobs (id, tenant_id, block_id, schedule_id, job, state, created_at) "
                "VALUES (?, ?, ?, ?, ?, 'queued', ?)",
                (jid, tenant_id, block_id, schedule_id, json.dumps(job), time.time()),
            )
        return self.get(tenant_id, jid)

    def get(self, tenant_id: str, job_id: str) -> dict[str, Any]:
        """The tenant's job; NotFoundError if it has none of that id."""
        return _found(self.db.one("SELECT * FROM jobs WHERE id = ? AND tenant_id = ?", (job_id, tenant_id)), job_id)

    def get_any_tenant(self, job_id: str) -> dict[str, Any]:
        """The job of this id whoever's it is: for the runner and the sweep of work
        folders, which hold a job id, not a tenant."""
        return _found(self.db.one("SELECT * FROM jobs WHERE id = ?", (job_id,)), job_id)

    def list(
        self,
        tenant_id: str,
        *,
        state: str | None = None,
        block_id: str | None = None,
        schedule_id: str | None = None,
        limit: int = 100,
        offset: int = 0,
    ) -> list[dict[str, Any]]:
        where, params = _job_filter(tenant_id, state=state, block_id=block_id, schedule_id=schedule_id)
        # newest first: last night's jobs on the first page
        sql = f"SELECT * FROM jobs WHERE {where} ORDER BY created_at DESC, id DESC LIMIT ? OFFSET ?"
        return self.db.rows(sql, (*params, limit, offset))

    def count(
        self, tenant_id: str, *, state: str | None = None, block_id: str | None = None, schedule_id: str | None = None
    ) -> int:
        """How many jobs `list` with these filters lists over all its pages."""
        where, params = _job_filter(tenant_id, state=state, block_id=block_id, schedule_id=schedule_id)
        return self.db.one(f"SELECT COUNT(*) AS n FROM jobs WHERE {where}", params)["n"]

    def claim_next(self) -> dict[str, Any] | None:
        """Move the next queued job to ``running`` and return it (None if the queue is
        empty, or holds only jobs waiting for their retry time).

        Fair share between tenants: the job comes from the tenant with a job ready that
        has the fewest jobs running, then the one served least recently (its latest
        job's start; never served first), then the one whose oldest ready job is
        oldest; within a tenant, oldest first. One farm's hundred queued jobs delay
        another's by at most one job each. A capture of an orchard block waits while an
        earlier capture of that block is queued or running (`CAPTURE_WAITS`).
        """
        now = time.time()
        with self.db.transaction() as con:
            row = con.execute(
                "WITH ready AS (SELECT tenant_id, MIN(created_at) AS oldest FROM jobs "
                f"  WHERE state = 'queued' AND (retry_at IS NULL OR retry_at <= :now) AND NOT {CAPTURE_WAITS} GROUP BY tenant_id), "
                "pick AS (SELECT r.tenant_id FROM ready r ORDER BY "
                "  (SELECT COUNT(*) FROM jobs x WHERE x.tenant_id = r.tenant_id AND x.state = 'running'), "
                "  COALESCE((SELECT MAX(x.started_at) FROM jobs x WHERE x.tenant_id = r.tenant_id), 0), "
                "  r.oldest, r.tenant_id LIMIT 1) "
                "SELECT id FROM jobs WHERE tenant_id = (SELECT tenant_id FROM pick) AND state = 'queued' "
                f"AND (retry_at IS NULL OR retry_at <= :now) AND NOT {CAPTURE_WAITS} ORDER BY created_at, id LIMIT 1",
                {"now": now},
            ).fetchone()
            if row is None:
                return None
            con.execute(
                "UPDATE jobs SET state = 'running', started_at = ?, attempts = attempts + 1, error = NULL, "
                "error_kind = NULL, error_fields = NULL, retry_at = NULL WHERE id = ?",
                (now, row["id"]),
            )
            job = con.execute("SELECT * FROM jobs WHERE id = ?", (row["id"],)).fetchone()
        return record(job)

    def set_progress(self, job_id: str, done: int, total: int) -> None:
        with self.db.transaction() as con:
            con.execute(
                "UPDATE jobs SET tiles_done = ?, tiles_total = ? WHERE id = ? AND state = 'running'", (done, total, job_id)
            )

    def set_note(self, job_id: str, note: str | None) -> None:
        """Say on a running job why it is not moving (its ``error`` while it runs), or
        put back what was there (None clears it)."""
        with self.db.transaction() as con:
            con.execute("UPDATE jobs SET error = ? WHERE id = ? AND state = 'running'", (note, job_id))

    def finish(
        self,
        job_id: str,
        state: str,
        *,
        error: str | None = None,
        error_kind: str | None = None,
        error_fields: dict | None = None,
        outcome: dict | None = None,
        timings: dict | None = None,
    ) -> dict[str, Any]:
        """Move a running job to a final state (``done``, ``failed`` or ``cancelled``).
        Its failure is kept as ``error_kind`` and ``error_fields`` (`service.failures`),
        which each edge words; ``error`` is a text that no failure's kind says."""
        if state not in FINAL_STATES:
            raise ValueError(f"not a final state: {state}")
        with self.db.transaction() as con:
            sets = "state = ?, error = ?, error_kind = ?, error_fields = ?, finished_at = ?"
            params: list[Any] = [state, error, error_kind, _json_or_null(error_fields), time.time()]
            if outcome is not None:
                sets += ", outcome = ?"
                params.append(json.dumps(outcome))
            if timings is not None:
                sets += ", timings = ?"
                params.append(json.dumps(timings))
            if state == "done":
                sets += ", tiles_done = tiles_total"
            con.execute(f"UPDATE jobs SET {sets} WHERE id = ? AND state = 'running'", (*params, job_id))
        return self.get_any_tenant(job_id)

    def retry(
        self, job_id: str, *, retry_at: float, error_kind: str | None = None, error_fields: dict | None = None,
        error: str | None = None,
    ) -> dict[str, Any]:
        """Put a running job back in the queue, to be taken again from ``retry_at`` (epoch
        seconds); ``error_kind`` and ``error_fields`` say why its last attempt failed (as
        in `finish`; ``error``: a text that no kind says)."""
        with self.db.transaction() as con:
            con.execute(
                "UPDATE jobs SET state = 'queued', error = ?, error_kind = ?, error_fields = ?, retry_at = ?, "
                "tiles_done = 0, tiles_total = 0 WHERE id = ? AND state = 'running'",
                (error, error_kind, _json_or_null(error_fields), retry_at, job_id),
            )
        return self.get_any_tenant(job_id)

    def request_cancel(self, tenant_id: str, job_id: str) -> dict[str, Any]:
        """Cancel a job: a queued one at once, a running one as soon as the runner sees the request."""
        with self.db.transaction() as con:
            row = con.execute("SELECT state FROM jobs WHERE id = ? AND tenant_id = ?", (job_id, tenant_id)).fetchone()
            if row is None:
                raise NotFoundError(f"no job {job_id!r}; ", hint="{list.jobs}")
            if row["state"] == "queued":
                con.execute(
                    "UPDATE jobs SET state = 'cancelled', cancel_requested = 1, finished_at = ?, error_kind = 'cancelled', "
                    "error_fields = ? WHERE id = ?",
                    (time.time(), json.dumps({"before_start": True}), job_id),
                )
            elif row["state"] == "running":
                con.execute("UPDATE jobs SET cancel_requested = 1 WHERE id = ?", (job_id,))
            else:
                raise ConflictError(f"job {job_id} is already {row['state']}; only queued or running jobs can be cancelled")
        return self.get(tenant_id, job_id)

    def cancel_requested(self, job_id: str) -> bool:
        rec = self.db.one("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,))
        return bool(rec and rec["cancel_requested"])

    def cancel_interrupted(self) -> list[str]:
        """Cancel the jobs left ``running`` by a dead service that had been asked to stop;
        returns their ids (their work stores are the caller's to delete)."""
        with self.db.transaction() as con:
            ids = [r["id"] for r in con.execute("SELECT id FROM jobs WHERE state = 'running' AND cancel_requested = 1")]
            con.executemany(
                "UPDATE jobs SET state = 'cancelled', finished_at = ?, error_kind = 'cancelled', error_fields = '{}' "
                "WHERE id = ?",
                [(time.time(), jid) for jid in ids],
            )
        return ids

    def release(self, job_id: str) -> None:
        """Put a running job back in the queue as if it had not been claimed (the service
        is stopping): a restart is no attempt of the job's, and must not use up the
        retries meant for a lost cluster."""
        with self.db.transaction() as con:
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
        with self.db.transaction() as con:
            con.execute(
                "UPDATE jobs SET crashes = crashes + 1, attempts = MAX(attempts - 1, 0), tiles_done = 0, "
                "tiles_total = 0 WHERE state = 'running'"
            )
            poisoned = []
            if max_crashes is not None:
                poisoned = [(r["id"], r["crashes"]) for r in con.execute(
                    "SELECT id, crashes FROM jobs WHERE state = 'running' AND crashes >= ?", (max_crashes,))]
                con.executemany(
                    "UPDATE jobs SET state = 'failed', finished_at = ?, retry_at = NULL, error = NULL, "
                    "error_kind = 'crashed', error_fields = json_object('crashes', crashes) WHERE id = ?",
                    [(time.time(), jid) for jid, _ in poisoned],
                )
            n = con.execute("UPDATE jobs SET state = 'queued' WHERE state = 'running'").rowcount
        for jid, crashes in poisoned:
            log.warning("job %s failed: the service stopped %d times while running it", jid, crashes)
        return n


def _json_or_null(value: dict | None) -> str | None:
    return None if value is None else json.dumps(value)
def _found(rec: dict[str, Any] | None, job_id: str) -> dict[str, Any]:
    if rec is None:
        raise NotFoundError(f"no job {job_id!r}; ", hint="{list.jobs}")
    return rec


def _job_filter(tenant_id: str, **equal: str | None) -> tuple[str, tuple[Any, ...]]:
    """The WHERE clause (and its parameters) of a tenant's jobs with the given columns
    equal to the values that are not None, for `JobQueue.list` and `JobQueue.count` alike."""
    where, params = "tenant_id = ?", [tenant_id]
    for column, value in equal.items():
        if value is not None:
            where += f" AND {column} = ?"
            params.append(value)
    return where, tuple(params)
