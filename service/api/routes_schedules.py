"""``/v1/schedules``: watch a capture inbox on a cron schedule; pause, change, scan now."""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter, Request, Response

from service.api.deps import SettingsDep, StoreDep, TenantDep, wake_runner
from service.api.schemas import (
    JSON_BODY,
    Schedule,
    ScheduleCreate,
    ScheduleRun,
    ScheduleUpdate,
    schedule_out,
)
from service.capturefates import capture_fates
from service.jobrequests import request_job, schedule_changes, stored
from service.schedules import check_inbox_use, next_run_time, run_schedule, tenant_inbox_root, validate_cron, validate_inbox

router = APIRouter()


@router.post("/schedules", response_model=Schedule, status_code=201, tags=["schedules"], summary="Register an inbox and a cron schedule",
         responses=JSON_BODY)
def create_schedule(body: ScheduleCreate, request: Request, response: Response, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    cron = validate_cron(body.cron)
    # a tenant's inboxes lie in its own folder: no other farm's captures, no server files
    inbox = validate_inbox(body.inbox, root=tenant_inbox_root(settings, tenant["name"]), root_label="this tenant's inbox folder")
    check_inbox_use(inbox, settings=settings, store=store, tenant_id=tenant["id"])
    job = request_job(body.params, body.tiling and body.tiling.model_dump())  # as a job would: refused now, not every night
    rec = store.schedules.create(
        tenant_id=tenant["id"],
        inbox=str(inbox),
        cron=cron,
        job=stored(job),
        next_run_at=next_run_time(cron, datetime.now().astimezone()).timestamp(),
        orchard_block_id=body.orchard_block_id,
    )
    clock = request.app.state.clock
    if clock is not None:
        clock.wake()
    response.headers["Location"] = f"/v1/schedules/{rec['id']}"
    return schedule_out(rec)


@router.get("/schedules", response_model=list[Schedule], tags=["schedules"])
def list_schedules(tenant: TenantDep, store: StoreDep):
    return [schedule_out(s) for s in store.schedules.list(tenant["id"])]


@router.get("/schedules/{schedule_id}", response_model=Schedule, tags=["schedules"])
def get_schedule(schedule_id: str, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    sched = store.schedules.get(tenant["id"], schedule_id)
    return schedule_out(sched, capture_fates(store, settings, sched))


@router.patch("/schedules/{schedule_id}", response_model=Schedule, tags=["schedules"], summary="Pause, resume or change a schedule",
          responses=JSON_BODY)
def update_schedule(schedule_id: str, body: ScheduleUpdate, request: Request, tenant: TenantDep, store: StoreDep):
    rec = store.schedules.update(tenant["id"], schedule_id, lambda current: schedule_changes(current, body.model_dump(exclude_unset=True)))
    clock = request.app.state.clock
    if clock is not None:
        clock.wake()
    return schedule_out(rec)


@router.delete("/schedules/{schedule_id}", status_code=204, tags=["schedules"], response_class=Response)
def delete_schedule(schedule_id: str, tenant: TenantDep, store: StoreDep):
    store.schedules.delete(tenant["id"], schedule_id)
    return Response(status_code=204)


@router.post("/schedules/{schedule_id}/run", response_model=ScheduleRun, tags=["schedules"], summary="Scan the inbox now")
def run_schedule_now(schedule_id: str, request: Request, tenant: TenantDep, store: StoreDep, settings: SettingsDep):
    sched = store.schedules.get(tenant["id"], schedule_id)
    result = run_schedule(store, settings, sched)
    if result["jobs"]:
        wake_runner(request.app)
    if result["waiting"] and request.app.state.clock is not None:
        request.app.state.clock.wake()  # the schedule now runs once they have settled
    return ScheduleRun(**result)
