"""``/healthz``: whether the service can take work, for a load balancer or a supervisor."""

from __future__ import annotations

import shutil

from fastapi import APIRouter, Request, Response

from service.api.deps import SettingsDep
from service.api.schemas import Health

API_VERSION = "0.1.0"


router = APIRouter()


@router.get("/healthz", response_model=Health, tags=["service"],
         responses={503: {"model": Health, "description": "not ok: problems says why"}})
def healthz(request: Request, response: Response, settings: SettingsDep) -> Health:
    runner, clock = request.app.state.runner, request.app.state.clock
    problems, free_mb = [], None
    try:
        free_mb = shutil.disk_usage(settings.data_dir).free / 2**20
    except OSError as exc:
        problems.append(f"the data folder cannot be read ({exc.strerror or exc})")
    if free_mb is not None and free_mb < settings.min_free_mb:
        problems.append(f"the data folder's disk has {free_mb:.0f} MB free, below {settings.min_free_mb:g} MB "
                        "(ORCHARD_MIN_FREE_MB): uploads and jobs will fail until space is freed")
    counts = runner.cluster_workers() if runner is not None else None
    if counts is not None and counts[0] == 0:
        want = f" of the {counts[1]} it should have (new ones are starting)" if counts[1] else ""
        problems.append(f"the dask cluster has no workers{want}: jobs wait until some connect")
    if problems:
        response.status_code = 503
    return Health(
        status="not ok" if problems else "ok",
        problems=problems,
        disk_free_mb=None if free_mb is None else round(free_mb, 1),
        version=API_VERSION,
        runner="disabled" if runner is None else ("alive" if runner.is_alive() else "stopped"),
        schedules="disabled" if clock is None else ("alive" if clock.is_alive() else "stopped"),
        cluster="disabled" if runner is None else runner.cluster_state(),
        workers=None if counts is None else counts[0],
        workers_expected=None if counts is None else counts[1],
    )
