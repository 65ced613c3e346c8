"""FastAPI dependencies of the ``/v1`` routes: the job store, the settings, the tenant.

The app keeps its store and settings on ``app.state`` (`service.app.create_app`); a
route asks for them as `StoreDep`, `SettingsDep` and `TenantDep`.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, FastAPI, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service import sessions
from service.db.jobstore import Store
from service.settings import Settings


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


_bearer = HTTPBearer(auto_error=False, description="a token from `orchard tokens create --tenant NAME`")


def get_tenant(
    request: Request,
    store: Annotated[Store, Depends(get_store)],
    _creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> dict:
    return sessions.request_tenant(request, store)  # a bearer token, or a browser's session cookie


StoreDep = Annotated[Store, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
TenantDep = Annotated[dict, Depends(get_tenant)]


def wake_runner(app: FastAPI) -> None:
    """Tell the app's job runner (if it has one) that a job was queued."""
    runner = getattr(app.state, "runner", None)
    if runner is not None:
        runner.wake()
