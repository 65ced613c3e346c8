"""The HTML of the browser pages: small shells that the page scripts fill from JSON.

The same job page serves two masters: the service (scripts and styles from
``/static``, data from the JSON API with the session cookie) and ``report.html``
(everything inlined, the data in a ``<script type="application/json">`` element, so the
file opens from disk without a server or a network).

No page carries an inline script of its own (the served pages' Content-Security-Policy
runs none, see `service.headers`): ``<body data-page=...>`` tells the page scripts what
to start, and ``data-job-id`` which job.
"""

from __future__ import annotations

import html
import json
import re
from pathlib import Path

STATIC_DIR = Path(__file__).parent / "web" / "static"  # served by service.web, inlined in a report
STATIC_URL = "/static"
FAVICON = f"{STATIC_URL}/favicon.svg"

_JOB_STYLES = ("vendor/leaflet/leaflet.css", "app.css")
_JOB_SCRIPTS = ("vendor/leaflet/leaflet.js", "orchard.js", "job.js")


def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


def _asset_text(rel: str) -> str:
    text = (STATIC_DIR / rel).read_text(encoding="utf-8")
    # a page opened from disk has no source maps beside it: do not point at one
    return re.sub(r"\n//# sourceMappingURL=\S+\s*$", "\n", text)


def _head(title: str, styles: tuple[str, ...], *, csrf: str | None = None, inline: bool = False) -> str:
    meta = f'<meta name="csrf-token" content="{_e(csrf)}">' if csrf else ""
    if inline:
        css = "".join(f"<style>\n{_asset_text(s)}\n</style>" for s in styles)
        icon = ""  # none: a file opened from disk asks for nothing else
    else:
        css = "".join(f'<link rel="stylesheet" href="{STATIC_URL}/{s}">' for s in styles)
        icon = f'<link rel="icon" href="{FAVICON}" type="image/svg+xml">'
    return (
        '<!doctype html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{_e(title)}</title>{icon}{meta}{css}</head>\n"
    )


def _scripts(scripts: tuple[str, ...], *, inline: bool = False) -> str:
    if inline:
        return "".join(f"<script>\n{_asset_text(s)}\n</script>\n" for s in scripts)
    return "".join(f'<script src="{STATIC_URL}/{s}"></script>\n' for s in scripts)


def _nav(tenant_name: str, csrf: str) -> str:
    return (
        '<header class="top"><a class="brand" href="/blocks">Orchard</a>'
        '<nav><a href="/blocks">Blocks and jobs</a><a href="/docs">API</a></nav>'
        f'<span class="who">{_e(tenant_name)}</span>'
        '<form method="post" action="/signout" class="signout">'
        f'<input type="hidden" name="csrf" value="{_e(csrf)}">'
        '<button type="submit" id="signout">Sign out</button></form></header>\n'
    )


def signin_page(*, error: str | None = None, next_path: str = "/blocks") -> str:
    """The sign-in form: the token goes in the body of a POST, never in a URL."""
    message = f'<p class="error" role="alert">{_e(error)}</p>' if error else ""
    return (
        _head("Sign in — Orchard", ("app.css",))
        + '<body class="signin"><main class="card">'
        "<h1>Orchard</h1><p>Sign in with your farm's token (from <code>orchard tokens create --tenant NAME</code>)."
        " It is kept by this browser as a session for 12 hours, or until you sign out.</p>"
        f"{message}"
        '<form method="post" action="/signin" autocomplete="off">'
        f'<input type="hidden" name="next" value="{_e(next_path)}">'
        '<label for="token">Token</label>'
        '<input type="password" id="token" name="token" required autofocus spellcheck="false" autocomplete="off" placeholder="orch_…">'
        '<button type="submit" id="signin">Sign in</button></form>'
        '<p class="small"><a href="/docs">API documentation</a></p>'
        "</main></body></html>\n"
    )


def blocks_page(*, tenant_name: str, csrf: str) -> str:
    """The tenant's blocks with their jobs (filled and refreshed by ``blocks.js``), and its
    schedules' inboxes with every capture's fate (``inbox.js``)."""
    return (
        _head("Blocks and jobs — Orchard", ("app.css",), csrf=csrf)
        + '<body data-page="blocks">'
        + _nav(tenant_name, csrf)
        + '<main><h1>Blocks and jobs</h1>'
        '<p class="small" id="updated" aria-live="polite">Loading…</p>'
        '<div id="blocks"></div><div id="inboxes"></div></main>\n'
        + _scripts(("orchard.js", "blocks.js", "inbox.js"))
        + "</body></html>\n"
    )


def _job_body(title: str) -> str:
    """The job page's elements, named for ``job.js``."""
    return (
        f'<main class="job"><h1 id="title">{_e(title)}</h1>'
        '<div id="warning" class="warning" hidden></div>'
        '<section id="status" class="status"></section>'
        '<section id="downloads" class="downloads"></section>'
        '<section id="mapsection" hidden>'
        '<div class="mapbar">'
        '<label>Colour by <select id="metric"></select></label>'
        '<form id="searchform" role="search"><input id="search" type="search" '
        'placeholder="tree 12, row 5 tree 3, 5/3 or row 5" aria-label="find a tree, an address or a row">'
        '<button type="submit">Find</button></form>'
        '<span id="searchresult" aria-live="polite"></span></div>'
        '<div class="mapwrap"><div id="map" aria-label="map of the block from above"></div>'
        '<aside id="details"><p class="small">Click a tree for its details.</p></aside></div>'
        '<div id="legend" class="legend"></div>'
        '<section id="changes" hidden></section>'
        '<h2>Block</h2><dl id="blocksummary" class="facts"></dl>'
        '<div id="rowsection" hidden><h2>Rows</h2><div class="scroll"><table id="rowstable" class="data"></table></div></div>'
        '<h2>Trees (<span id="tree-count">0</span>)</h2>'
        '<div class="pager" id="pager"></div>'
        '<div class="scroll"><table id="treestable" class="data"></table></div>'
        "</section></main>\n"
    )


def job_page(*, job_id: str, tenant_name: str, csrf: str) -> str:
    """A job's page in the service: the state while it runs, then the map and the tables."""
    return (
        _head(f"Job {job_id} — Orchard", _JOB_STYLES, csrf=csrf)
        + f'<body data-page="job" data-job-id="{_e(job_id)}">'
        + _nav(tenant_name, csrf)
        + _job_body(f"Job {job_id}")
        + _scripts(_JOB_SCRIPTS)
        + "</body></html>\n"
    )


def report_page(*, title: str, data_json: str, facts: dict[str, str], downloads: dict[str, str],
                warning: str | None = None, fallback: str = "") -> str:
    """``report.html``: the job page with its scripts, styles and data inlined.

    ``data_json`` is `service.reports.mapdata.to_json` of the map data; ``downloads`` maps a
    label to a path relative to the report (the files beside it); ``fallback`` is HTML
    shown when scripts do not run (the static map and table).
    """
    cfg = json.dumps({"title": title, "facts": facts, "downloads": downloads, "warning": warning}).replace("<", "\\u003c")
    return (
        _head(title, _JOB_STYLES, inline=True)
        + '<body data-page="report">'
        + _job_body(title)
        + f'<script type="application/json" id="orchard-data">{data_json}</script>\n'
        + f'<script type="application/json" id="orchard-report">{cfg}</script>\n'
        + f'<noscript>{fallback}</noscript>\n'
        + _scripts(_JOB_SCRIPTS, inline=True)
        + "</body></html>\n"
    )


def message_page(*, title: str, message: str, tenant_name: str | None = None, csrf: str | None = None) -> str:
    """A short page saying what went wrong (a job that is not this farm's: 404)."""
    nav = _nav(tenant_name, csrf) if tenant_name and csrf else ""
    return (
        _head(f"{title} — Orchard", ("app.css",), csrf=csrf)
        + f'<body>{nav}<main class="card"><h1>{_e(title)}</h1><p>{_e(message)}</p>'
        '<p><a href="/blocks">Back to the blocks</a></p></main></body></html>\n'
    )
