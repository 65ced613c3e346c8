"""A farm's webhooks (``webhooks``) and their calls (``webhook_deliveries``): each event
a webhook listens to is queued as a delivery, tried by `service.webhooks.WebhookSender`
until it is answered with a 2xx or its attempts are used up, and kept with every
attempt's status code."""

from __future__ import annotations

import json
import time
from typing import Any

from pipeline.errors import ParameterError
from service.db.database import Database, new_id
from service.db.errors import NotFoundError

#: what a webhook can be called for
EVENTS = ("job.done", "job.failed", "capture.rejected")
#: most webhooks of one tenant: each event is a call to every one of them
MAX_WEBHOOKS = 20


def _decoded(rec: dict[str, Any] | None, *keys: str) -> dict[str, Any] | None:
    if rec is not None:
        for k in keys:
            if k in rec and isinstance(rec[k], str):
                rec[k] = json.loads(rec[k])
    return rec


class Webhooks:
    """The ``webhooks`` and ``webhook_deliveries`` tables."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def create(self, *, tenant_id: str, url: str, secret: str, schedule_id: str | None,
                       events: list[str]) -> dict[str, Any]:
        wid = new_id()
        with self.db.transaction() as con:
            n = con.execute("SELECT COUNT(*) FROM webhooks WHERE tenant_id = ?", (tenant_id,)).fetchone()[0]
            if n >= MAX_WEBHOOKS:
                raise ParameterError(f"this farm has {n} webhooks, the most it may have; delete one first (DELETE /v1/webhooks/ID)")
            if schedule_id is not None and con.execute(
                "SELECT 1 FROM schedules WHERE id = ? AND tenant_id = ?", (schedule_id, tenant_id)
            ).fetchone() is None:
                raise NotFoundError(f"no schedule {schedule_id!r}; ", hint="{list.schedules}")
            con.execute(
                "INSERT INTO webhooks (id, tenant_id, schedule_id, url, secret, events, created_at) VALUES (?, ?, ?, ?, ?, ?, ?)",
                (wid, tenant_id, schedule_id, url, secret, json.dumps(list(events)), time.time()),
            )
        return self.get(tenant_id, wid)

    def get(self, tenant_id: str, webhook_id: str) -> dict[str, Any]:
        rec = self.db.one("SELECT * FROM webhooks WHERE id = ? AND tenant_id = ?", (webhook_id, tenant_id))
        if rec is None:
            raise NotFoundError(f"no webhook {webhook_id!r}; ", hint="{list.webhooks}")
        return _decoded(rec, "events")

    def list(self, tenant_id: str) -> list[dict[str, Any]]:
        rows = self.db.rows("SELECT * FROM webhooks WHERE tenant_id = ? ORDER BY created_at, id", (tenant_id,))
        return [_decoded(r, "events") for r in rows]

    def delete(self, tenant_id: str, webhook_id: str) -> None:
        with self.db.transaction() as con:
            if con.execute("DELETE FROM webhooks WHERE id = ? AND tenant_id = ?", (webhook_id, tenant_id)).rowcount == 0:
                raise NotFoundError(f"no webhook {webhook_id!r}; ", hint="{list.webhooks}")
            con.execute("DELETE FROM webhook_deliveries WHERE webhook_id = ?", (webhook_id,))

    def queue_event(self, *, tenant_id: str, schedule_id: str | None, event: str,
                            body: dict[str, Any]) -> int:
        """Queue a delivery of ``event`` to each webhook of the tenant that listens to it
        (the tenant's own, and the schedule's); returns how many. ``body`` gets the
        delivery's ``id`` and ``event``."""
        now = time.time()
        with self.db.transaction() as con:
            hooks = con.execute(
                "SELECT id, events FROM webhooks WHERE tenant_id = ? AND (schedule_id IS NULL OR schedule_id = ?)",
                (tenant_id, schedule_id),
            ).fetchall()
            n = 0
            for hook in hooks:
                if event not in json.loads(hook["events"]):
                    continue
                did = new_id()
                text = json.dumps({"id": did, "event": event, "created_at": now, **body}, separators=(",", ":"))
                con.execute(
                    "INSERT INTO webhook_deliveries (id, webhook_id, tenant_id, event, body, state, created_at, next_attempt_at) "
                    "VALUES (?, ?, ?, ?, ?, 'pending', ?, ?)",
                    (did, hook["id"], tenant_id, event, text, now, now),
                )
                n += 1
        return n

    def due_deliveries_any_tenant(self, now: float, *, limit: int = 50) -> list[dict[str, Any]]:
        """Pending deliveries whose next attempt is due, of every tenant, each with its
        webhook's ``url`` and ``secret`` (the sender's, not a tenant's, lookup)."""
        rows = self.db.rows(
            "SELECT d.*, w.url, w.secret FROM webhook_deliveries d JOIN webhooks w ON w.id = d.webhook_id "
            "WHERE d.state = 'pending' AND d.next_attempt_at <= ? ORDER BY d.next_attempt_at LIMIT ?",
            (now, int(limit)),
        )
        return [_decoded(r, "tries") for r in rows]

    def next_delivery_at_any_tenant(self) -> float | None:
        row = self.db.one("SELECT MIN(next_attempt_at) AS at FROM webhook_deliveries WHERE state = 'pending'")
        return None if row is None else row["at"]

    def record_attempt(self, delivery_id: str, *, at: float, status_code: int | None, error: str | None,
                                delivered: bool, retry_at: float | None) -> None:
        """One attempt's answer; the delivery is ``delivered``, pending again until
        ``retry_at``, or ``failed`` for good (``retry_at`` None)."""
        with self.db.transaction() as con:
            row = con.execute("SELECT tries FROM webhook_deliveries WHERE id = ?", (delivery_id,)).fetchone()
            if row is None:  # its webhook was deleted meanwhile
                return
            tries = json.loads(row["tries"]) + [{"at": at, "status_code": status_code, "error": error}]
            state = "delivered" if delivered else ("pending" if retry_at is not None else "failed")
            con.execute(
                "UPDATE webhook_deliveries SET state = ?, attempts = attempts + 1, status_code = ?, error = ?, tries = ?, "
                "next_attempt_at = ?, finished_at = ? WHERE id = ?",
                (state, status_code, error, json.dumps(tries), None if state != "pending" else retry_at,
                 None if state == "pending" else at, delivery_id),
            )

    def prune_deliveries_any_tenant(self, before: float) -> int:
        """Forget the deliveries of every tenant that ended (delivered or failed) before
        ``before``; returns how many (the table would grow with every job otherwise)."""
        with self.db.transaction() as con:
            return con.execute("DELETE FROM webhook_deliveries WHERE state != 'pending' AND finished_at < ?", (before,)).rowcount

    def deliveries(self, tenant_id: str, webhook_id: str, *, limit: int = 100) -> list[dict[str, Any]]:
        """A webhook's deliveries, newest first."""
        self.get(tenant_id, webhook_id)
        rows = self.db.rows(
            "SELECT * FROM webhook_deliveries WHERE webhook_id = ? AND tenant_id = ? ORDER BY created_at DESC, id LIMIT ?",
            (webhook_id, tenant_id, int(limit)),
        )
        return [_decoded(r, "tries", "body") for r in rows]
