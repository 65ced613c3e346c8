"""The orchard in a browser: sign-in, pages for blocks and jobs, offline API docs.

`install(app)` adds the routes (`service.web.routes`) and serves the static files
(the page scripts and the vendored libraries under ``static/vendor``) at ``/static``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the report of `orchard process` uses this package without FastAPI
    from fastapi import FastAPI


def install(app: FastAPI) -> None:
    """Add the browser pages and their static files to the service's app."""
    from fastapi.staticfiles import StaticFiles

    from service.web import render, routes  # here: `service.web.render` serves `orchard process`, which has no FastAPI

    app.include_router(routes.router)
    app.mount(render.STATIC_URL, StaticFiles(directory=render.STATIC_DIR), name="static")
