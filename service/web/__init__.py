"""The orchard in a browser: sign-in, pages for blocks and jobs, offline API docs.

`install(app)` adds the routes (`service.web.routes`) and serves the static files
(the page scripts and the vendored libraries under ``static/vendor``) at ``/static``.
The pages' HTML is `service.pages`, which the report of ``orchard process`` uses too,
without FastAPI.
"""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from service import pages
from service.web import routes


def install(app: FastAPI) -> None:
    """Add the browser pages and their static files to the service's app."""
    app.include_router(routes.router)
    app.mount(pages.STATIC_URL, StaticFiles(directory=pages.STATIC_DIR), name="static")
