"""``/v1/webhooks``: a farm's server called when a job finishes or fails, or a capture is
rejected; each call signed with the webhook's secret, retried with backoff, and kept
with its attempts (``/v1/webhooks/{id}/deliveries``). See `service.webhooks`."""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any, Literal

from fastapi import APIRouter, Query, Response
from pydantic import BaseModel, ConfigDict, Field

from service.api.deps import SettingsDep, StoreDep, TenantDep
from service.api.schemas import JSON_BODY
from service.db.webhooks import EVENTS
from service.webhooks import check_url

router = APIRouter()

Event = Literal["job.done", "job.failed", "capture.rejected"]


class WebhookCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    url: str = Field(max_length=2000, description="http:// or https:// URL the service POSTs each event to")
    secret: str = Field(min_length=16, max_length=200, description="key of the HMAC-SHA256 signature of each call "
                        "(X-Orchard-Signature); kept by the service, never shown again")
    schedule_id: str | None = Field(None, max_length=64, description="only this schedule's events (its jobs and "
                                    "captures); null: every event of the farm")
    events: list[Event] = Field(default_factory=lambda: list(EVENTS), min_length=1,
                                description="the events to be called for (default all)")


class Webhook(BaseModel):
    id: str
    url: str
    schedule_id: str | None
    events: list[str]
    created_at: str
    links: dict[str, str]


class DeliveryTry(BaseModel):
    at: str
    status_code: int | None = Field(description="the receiver's answer; null: no answer (error says why)")
    error: str | None


class Delivery(BaseModel):
    id: str = Field(description="also sent as X-Orchard-Delivery (the same on every attempt)")
    event: str
    state: Literal["pending", "delivered", "failed"] = Field(
        description="pending: being tried (next_attempt_at); delivered: answered 2xx; failed: every attempt failed")
    attempts: int
    status_code: int | None = Field(description="the last attempt's answer")
    error: str | None = Field(description="why the last attempt failed")
    tries: list[DeliveryTry] = Field(description="every attempt, first first")
    created_at: str
    next_attempt_at: str | None
    finished_at: str | None
    body: dict[str, Any] = Field(description="the JSON body sent")


def _iso(ts: float | None) -> str | None:
    return None if ts is None else datetime.fromtimestamp(ts, timezone.utc).isoformat(timespec="seconds")


def _webhook_out(rec: dict) -> Webhook:
    return Webhook(id=rec["id"], url=rec["url"], schedule_id=rec["schedule_id"], events=rec["events"],
                   created_at=_iso(rec["created_at"]),
                   links={"self": f"/v1/webhooks/{rec['id']}", "deliveries": f"/v1/webhooks/{rec['id']}/deliveries"})


def _delivery_out(rec: dict) -> Delivery:
    tries = [DeliveryTry(at=_iso(t["at"]), status_code=t["status_code"], error=t["error"]) for t in rec["tries"]]
    return Delivery(id=rec["id"], event=rec["event"], state=rec["state"], attempts=rec["attempts"],
                    status_code=rec["status_code"], error=rec["error"], tries=tries, created_at=_iso(rec["created_at"]),
                    next_attempt_at=_iso(rec["next_attempt_at"]), finished_at=_iso(rec["finished_at"]), body=rec["body"])


@router.post("/webhooks", response_model=Webhook, status_code=201, tags=["webhooks"],
             summary="Be called when a job finishes or fails, or a capture is rejected", responses=JSON_BODY)
def create_webhook(body: WebhookCreate, response: Response, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    url = check_url(body.url, settings)
    rec = store.webhooks.create(tenant_id=tenant["id"], url=url, secret=body.secret, schedule_id=body.schedule_id,
                               events=list(dict.fromkeys(body.events)))
    response.headers["Location"] = f"/v1/webhooks/{rec['id']}"
    return _webhook_out(rec)


@router.get("/webhooks", response_model=list[Webhook], tags=["webhooks"])
def list_webhooks(tenant: TenantDep, store: StoreDep):
    return [_webhook_out(w) for w in store.webhooks.list(tenant["id"])]


@router.get("/webhooks/{webhook_id}", response_model=Webhook, tags=["webhooks"])
def get_webhook(webhook_id: str, tenant: TenantDep, store: StoreDep):
    return _webhook_out(store.webhooks.get(tenant["id"], webhook_id))


@router.delete("/webhooks/{webhook_id}", status_code=204, tags=["webhooks"], response_class=Response)
def delete_webhook(webhook_id: str, tenant: TenantDep, store: StoreDep):
    store.webhooks.delete(tenant["id"], webhook_id)
    return Response(status_code=204)


@router.get("/webhooks/{webhook_id}/deliveries", response_model=list[Delivery], tags=["webhooks"],
            summary="A webhook's calls, newest first, with every attempt's status code")
def list_deliveries(webhook_id: str, tenant: TenantDep, store: StoreDep,
                    limit: int = Query(100, ge=1, le=1000, description="most deliveries listed")):
    return [_delivery_out(d) for d in store.webhooks.deliveries(tenant["id"], webhook_id, limit=limit)]
