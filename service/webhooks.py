"""Webhooks: a farm's server told when a job finishes or fails, or a capture is rejected.

An event is queued in the store as one delivery per webhook that listens to it (the
farm's, and its schedule's), in the thread where it happens (the runner, a scan); the
`WebhookSender` thread POSTs each delivery's JSON body, signed, and retries a failed
attempt (no answer, or an answer other than 2xx) after ``webhook_backoff_s``, doubled
each time, up to ``webhook_attempts`` attempts. Every attempt's status code is kept and
shown by ``GET /v1/webhooks/{id}/deliveries``.

The signature: ``X-Orchard-Signature: sha256=<hex>``, the HMAC-SHA256 with the webhook's
secret of ``<X-Orchard-Timestamp>.<body>`` (the timestamp: POSIX seconds of the
attempt), so a receiver can refuse a body changed on the way and a call replayed later.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

from pipeline.errors import ParameterError
from service.background import Background
from service.db.jobstore import Store
from service.settings import Settings
from service.wording import job_error

log = logging.getLogger("orchard.webhooks")

SIGNATURE_HEADER = "X-Orchard-Signature"
TIMESTAMP_HEADER = "X-Orchard-Timestamp"
EVENT_HEADER = "X-Orchard-Event"
DELIVERY_HEADER = "X-Orchard-Delivery"
_JOB_EVENTS = {"done": "job.done", "failed": "job.failed"}
KEEP_DELIVERIES_S = 30 * 86400  #: how long a delivery that ended stays listed


def sign(secret: str, timestamp: int, body: bytes) -> str:
    """The signature header's value for ``body`` sent at ``timestamp``."""
    mac = hmac.new(secret.encode("utf-8"), f"{timestamp}.".encode("ascii") + body, hashlib.sha256)
    return "sha256=" + mac.hexdigest()


def verify(secret: str, timestamp: str, body: bytes, signature: str, *, now: float | None = None,
           tolerance_s: float = 300.0) -> bool:
    """Whether a call's signature is the webhook's and its timestamp recent: what a
    receiver checks (a reference for the docs and the tests)."""
    try:
        ts = int(timestamp)
    except (TypeError, ValueError):
        return False
    now = time.time() if now is None else now
    return abs(now - ts) <= tolerance_s and hmac.compare_digest(sign(secret, ts, body), signature)


def check_url(url: str, settings: Settings) -> str:
    """The webhook URL if it is an http(s) URL of a host the operator allows
    (``ORCHARD_WEBHOOK_HOSTS``); ParameterError otherwise."""
    url = str(url).strip()
    try:
        parts = urlsplit(url)
        host = parts.hostname
        parts.port  # noqa: B018 - a port out of range raises here
    except ValueError:
        raise ParameterError(f"webhook url {url!r} is not a valid URL") from None
    if parts.scheme not in ("http", "https") or not host:
        raise ParameterError(f"webhook url {url!r} must be an http:// or https:// URL with a host")
    if any(c.isspace() or not c.isprintable() for c in url):
        raise ParameterError("webhook url must not contain spaces or control characters")
    allowed = [h.strip().lower() for h in settings.webhook_hosts.split(",") if h.strip()]
    if "*" not in allowed and host.lower() not in allowed:
        raise ParameterError(
            f"webhook host {host!r} is not one this server calls; its operator allows "
            + (", ".join(repr(h) for h in allowed) if allowed else "none (ORCHARD_WEBHOOK_HOSTS is empty)")
        )
    return url


def backoff_s(attempts: int, settings: Settings) -> float | None:
    """The wait before the next attempt after ``attempts`` failed ones, or None when they
    are used up: ``webhook_backoff_s`` doubled after each failure."""
    if attempts >= settings.webhook_attempts:
        return None
    return settings.webhook_backoff_s * 2 ** (attempts - 1)


def job_event(store: Store, job: dict[str, Any]) -> int:
    """Queue ``job.done`` or ``job.failed`` for a job in that final state (others are no
    event: a cancelled job was cancelled by the farm); returns the deliveries queued."""
    event = _JOB_EVENTS.get(job.get("state"))
    if event is None:
        return 0
    outcome = job.get("outcome") or {}
    body = {"job": {
        "id": job["id"], "state": job["state"], "block_id": job["block_id"], "schedule_id": job.get("schedule_id"),
        "capture": job.get("capture"), "error": job_error(job), "n_trees": outcome.get("n_trees"),
        "partial": outcome.get("partial"), "finished_at": job.get("finished_at"),
        "links": {"self": f"/v1/jobs/{job['id']}", "page": f"/jobs/{job['id']}"},
    }}
    return store.webhooks.queue_event(tenant_id=job["tenant_id"], schedule_id=job.get("schedule_id"), event=event, body=body)


def rejected_event(store: Store, *, tenant_id: str, schedule_id: str, rejected: list[dict[str, str]]) -> int:
    """Queue ``capture.rejected`` for each capture (``{"file", "error"}``) a scan rejected."""
    n = 0
    for r in rejected:
        body = {"schedule_id": schedule_id, "capture": {"file": r["file"], "reason": r["error"]}}
        n += store.webhooks.queue_event(tenant_id=tenant_id, schedule_id=schedule_id, event="capture.rejected", body=body)
    return n


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    # a redirect would send the signed body to a host nobody allowed: its status is the answer
    def redirect_request(self, *args, **kwargs):
        return None


_opener = urllib.request.build_opener(_NoRedirect)


def post(url: str, body: bytes, headers: dict[str, str], timeout_s: float) -> tuple[int | None, str | None]:
    """POST ``body``; (status code, None) when answered, (None, why) when not."""
    req = urllib.request.Request(url, data=body, method="POST", headers={"Content-Type": "application/json", **headers})
    try:
        with _opener.open(req, timeout=timeout_s) as resp:
            resp.read(65536)  # the receiver's words are not kept: only its status
            return resp.status, None
    except urllib.error.HTTPError as exc:
        exc.close()
        return exc.code, None
    except (urllib.error.URLError, OSError, ValueError) as exc:
        reason = getattr(exc, "reason", None) or exc
        return None, f"no answer: {str(reason)[:200]}"


class WebhookSender(Background):
    """Background thread that delivers queued webhook calls, with retries and backoff
    (``wake()``: an event was queued, deliver it now)."""

    def __init__(self, store: Store, settings: Settings, *, poster: Callable = post) -> None:
        super().__init__("orchard-webhooks")
        self.store = store
        self.settings = settings
        self._post = poster

    def deliver_due(self, now: float | None = None) -> int:
        """One attempt at every delivery that is due; returns how many were tried."""
        due = self.store.webhooks.due_deliveries_any_tenant(time.time() if now is None else now)
        for d in due:
            if self._stopping.is_set():
                break
            self.attempt(d)
        return len(due)

    def attempt(self, delivery: dict[str, Any]) -> None:
        body = delivery["body"].encode("utf-8")
        ts = int(time.time())
        headers = {
            SIGNATURE_HEADER: sign(delivery["secret"], ts, body),
            TIMESTAMP_HEADER: str(ts),
            EVENT_HEADER: delivery["event"],
            DELIVERY_HEADER: delivery["id"],
            "User-Agent": "orchard-webhooks",
        }
        status, error = self._post(delivery["url"], body, headers, self.settings.webhook_timeout_s)
        ok = status is not None and 200 <= status < 300
        if not ok and error is None:
            error = f"answered {status}"
        at = time.time()
        wait = None if ok else backoff_s(int(delivery["attempts"]) + 1, self.settings)
        self.store.webhooks.record_attempt(delivery["id"], at=at, status_code=status, error=None if ok else error,
                                           delivered=ok, retry_at=None if wait is None else at + wait)
        if not ok:
            log.info("webhook delivery %s (%s): %s%s", delivery["id"], delivery["event"], error,
                     "; given up" if wait is None else f"; tried again in {wait:.0f} s")

    def run(self) -> None:
        pruned_at = 0.0
        while not self._stopping.is_set():
            try:
                if time.time() - pruned_at > 3600:
                    pruned_at = time.time()
                    self.store.webhooks.prune_deliveries_any_tenant(pruned_at - KEEP_DELIVERIES_S)
                self.deliver_due()
                nxt = self.store.webhooks.next_delivery_at_any_tenant()
            except Exception as exc:  # noqa: BLE001 - keep the sender alive (e.g. store briefly locked)
                log.warning("webhook sender: %s", exc)
                nxt = None
            wait = self.settings.webhook_poll_s if nxt is None else min(max(0.0, nxt - time.time()), self.settings.webhook_poll_s)
            self._wake.wait(wait)
            self._wake.clear()
