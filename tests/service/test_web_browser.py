"""The pages in a real browser: headless Chromium (Debian's) driven by Playwright through
a real `orchard serve` on loopback, and report.html opened from disk.

Every test asserts that no request leaves the server (or the file) and that the page
logs no console error. With ORCHARD_WEB_SCREENSHOTS=<folder> the walk-through saves a
screenshot of each page there (docs/screenshots/ holds those of the docs).
"""

from __future__ import annotations

import io
import os
import shutil
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from service_fixtures import ServerProcess, make_token, simulated_block, wait_for_job, write_las

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]

pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).exists(),
    reason=f"no browser: {CHROMIUM} is missing (Debian: apt-get install -y chromium; .ci/run installs it)",
)


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


class Watch:
    """What a page asked for outside ``allowed`` hosts (blocked, and recorded) and the
    errors it logged."""

    def __init__(self, context, page, allowed: set[str]) -> None:
        self.outside: list[str] = []
        self.errors: list[str] = []
        self.allowed = allowed
        context.route("**/*", self._route)
        # a Content-Security-Policy violation becomes a console error (Chromium logs most
        # of them itself; this catches the report-only kinds too)
        context.add_init_script("document.addEventListener('securitypolicyviolation', e => "
                                "console.error('CSP violation: ' + e.violatedDirective + ' ' + e.blockedURI))")
        page.on("request", lambda r: None if self._local(r.url) else self.outside.append(r.url))
        page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: self.errors.append(str(e)))

    def _local(self, url: str) -> bool:
        parts = urlsplit(url)
        if parts.scheme in ("data", "blob"):  # made by the page itself (ReDoc's worker)
            return True
        return parts.scheme == "file" if "file" in self.allowed else parts.hostname in self.allowed

    def _route(self, route) -> None:
        if self._local(route.request.url):
            route.continue_()
        else:
            route.abort()

    def clean(self) -> None:
        assert self.outside == [], f"requests left the server: {self.outside}"
        assert self.errors == [], f"console errors: {self.errors}"


def _shot(page, name: str) -> None:
    """A small PNG of the page (256 colours) into $ORCHARD_WEB_SCREENSHOTS, if set."""
    folder = os.environ.get("ORCHARD_WEB_SCREENSHOTS")
    if not folder:
        return
    from PIL import Image

    png = page.screenshot(full_page=False)
    img = Image.open(io.BytesIO(png)).convert("RGB").quantize(colors=256)
    Path(folder).mkdir(parents=True, exist_ok=True)
    img.save(Path(folder) / f"{name}.png", optimize=True)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A server with its runner on, farm A's finished job and farm B's job."""
    root = tmp_path_factory.mktemp("web")
    srv = ServerProcess(root / "data", ORCHARD_SCHEDULING="false")
    srv.start()
    try:
        tokens = {"a": make_token(srv.data_dir, "farm-a"), "b": make_token(srv.data_dir, "farm-b")}
        block = simulated_block(root / "orchard.laz", rows=2, trees_per_row=3, density=0.4, seed=3)
        other = write_las(root / "other.laz", 2000, seed=5)
        jobs = {}
        for farm, path in (("a", block), ("b", other)):
            with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {tokens[farm]}"}, timeout=60) as c:
                b = c.post("/v1/blocks", files={"file": (path.name, path.read_bytes())}).json()
                jobs[farm] = c.post("/v1/jobs", json={"block_id": b["id"]}).json()
        with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {tokens['a']}"}, timeout=60) as c:
            jobs["a"] = wait_for_job(c, jobs["a"]["id"], timeout=240)
            assert jobs["a"]["state"] == "done", jobs["a"]
            trees = c.get(f"/v1/jobs/{jobs['a']['id']}/trees", params={"limit": 1000}).json()["items"]
        yield srv, tokens, jobs, trees
    finally:
        srv.stop()


def _click_tree(page, i: int) -> None:
    """Click tree ``i``'s trunk on the map's canvas, where the browser draws it."""
    x, y = page.evaluate(
        """(i) => { const v = window.orchardView;
                    const p = v.map.latLngToContainerPoint([v.d.y[i], v.d.x[i]]); const r = document.getElementById('map').getBoundingClientRect();
                    return [r.left + p.x, r.top + p.y]; }""",
        i,
    )
    page.mouse.click(x, y)


@pytest.mark.slow
def test_walk_through_sign_in_blocks_job_sign_out_and_docs(browser, served):
    srv, tokens, jobs, trees = served
    job = jobs["a"]
    context = browser.new_context(viewport={"width": 1100, "height": 760})
    page = context.new_page()
    watch = Watch(context, page, {"127.0.0.1"})
    try:
        # sign in: the server sends a browser without a session to the form
        page.goto(srv.url + "/")
        assert urlsplit(page.url).path == "/signin"
        _shot(page, "signin")
        page.fill("#token", tokens["a"])
        page.click("#signin")
        page.wait_for_url("**/blocks")
        assert tokens["a"] not in page.url

        # the blocks list, with the finished job
        row = page.wait_for_selector(f"tr[data-job='{job['id']}']")
        assert "done" in row.inner_text()
        _shot(page, "blocks")

        # the job page: the map draws every tree
        page.click(f"a[href='/jobs/{job['id']}']")
        page.wait_for_selector("body[data-drawn]", timeout=60_000)
        assert page.text_content("#tree-count") == str(job["n_trees"]) == str(len(trees))
        assert page.evaluate("window.orchardView.drawn") == job["n_trees"]  # every tree on the canvas

        # a click on a crown shows that tree
        _click_tree(page, 1)
        assert page.text_content("#selected-tree").startswith(f"Tree {trees[1]['tree_id']}")

        # search: by address where the trees have one, else by id
        target = trees[-1]
        if target.get("row") is not None and target.get("position") is not None:
            query, expected = f"row {target['row']} tree {target['position']}", f"(row {target['row']} tree {target['position']})"
        else:
            query, expected = str(target["tree_id"]), f"Found tree {target['tree_id']}"
        page.fill("#search", query)
        page.press("#search", "Enter")
        assert expected in page.text_content("#searchresult")
        assert page.text_content("#selected-tree").startswith(f"Tree {target['tree_id']}")
        _shot(page, "job")
        page.fill("#search", "99999")
        page.press("#search", "Enter")
        assert page.text_content("#searchresult") == "No such tree."

        # the table sorts by a column
        page.click("#treestable th[data-key='height_m']")
        heights = [float(c) for c in page.evaluate(
            """() => { const k = [...document.querySelectorAll('#treestable th')].findIndex(th => th.dataset.key === 'height_m');
                       return [...document.querySelectorAll('#treestable tbody tr')].map(tr => tr.children[k].textContent); }""")]
        assert heights == sorted(heights) and len(heights) == len(trees)

        # a download with the session cookie
        href = page.get_attribute("#downloads a:has-text('Trees (CSV)')", "href")
        csv = page.request.get(srv.url + href)
        assert csv.status == 200 and csv.text().count("\n") == len(trees) + 1

        # another farm's job: 404
        resp = page.goto(f"{srv.url}/jobs/{jobs['b']['id']}")
        assert resp.status == 404 and "No such job" in page.text_content("h1")
        watch.errors = [e for e in watch.errors if "404" not in e]  # the browser logs the 404 it was shown

        # sign out: the pages and the API want a session again
        page.goto(srv.url + "/blocks")
        before = len(watch.errors)
        page.click("#signout")
        # the sign-out's own redirect, or a refresh of the page (blocks, inboxes) that met
        # the ended session first and came with ?next=/blocks: either is the sign-in page
        page.wait_for_url(lambda url: urlsplit(url).path == "/signin")
        # a refresh already in flight when the form was sent is answered 401, which the
        # browser logs (the page sends no new one once signing out: orchard.js, O.leaving)
        watch.errors[before:] = [e for e in watch.errors[before:] if "status of 401" not in e]
        page.goto(srv.url + "/blocks")
        assert urlsplit(page.url).path == "/signin"
        assert page.request.get(srv.url + "/v1/jobs").status == 401

        # the API docs, offline
        page.goto(srv.url + "/docs")
        page.wait_for_selector(".swagger-ui .opblock", timeout=30_000)
        _shot(page, "docs")
        page.goto(srv.url + "/redoc")
        page.wait_for_selector("[role=search], .menu-content", timeout=30_000)
        page.wait_for_timeout(500)
        _shot(page, "redoc")
        watch.clean()
    finally:
        context.close()


@pytest.mark.slow
def test_served_pages_run_under_the_security_headers(browser, served):
    srv, tokens, jobs, trees = served
    job = jobs["a"]
    context = browser.new_context(viewport={"width": 1000, "height": 700})
    page = context.new_page()
    watch = Watch(context, page, {"127.0.0.1"})
    try:
        page.goto(srv.url + "/signin")
        page.fill("#token", tokens["a"])
        page.click("#signin")
        page.wait_for_url("**/blocks")
        page.wait_for_selector(f"tr[data-job='{job['id']}']")  # blocks.js started without an inline script
        resp = page.goto(f"{srv.url}/jobs/{job['id']}")
        assert "script-src 'self';" in resp.headers["content-security-policy"]
        page.wait_for_selector("body[data-drawn]", timeout=60_000)  # so did job.js
        # the served report: its inlined scripts run, named by hash, and nothing else inline
        resp = page.goto(f"{srv.url}/v1/jobs/{job['id']}/report")
        assert "'sha256-" in resp.headers["content-security-policy"] and resp.headers["x-frame-options"] == "DENY"
        page.wait_for_selector("body[data-drawn]", timeout=60_000)
        assert page.text_content("#tree-count") == str(len(trees))
        watch.clean()
        for path in ("/docs", "/redoc"):
            resp = page.goto(srv.url + path)
            assert "frame-ancestors 'none'" in resp.headers["content-security-policy"], path
        page.goto(srv.url + "/docs")
        page.wait_for_selector(".swagger-ui .opblock", timeout=30_000)
        page.goto(srv.url + "/redoc")
        page.wait_for_selector("[role=search], .menu-content", timeout=30_000)
        page.wait_for_timeout(500)
        watch.clean()
        # on the report, an inline script that was not in the file (as an injected one would be) does not run
        page.goto(f"{srv.url}/v1/jobs/{job['id']}/report")
        page.wait_for_selector("body[data-drawn]", timeout=60_000)
        ran = page.evaluate("""() => { const s = document.createElement('script'); s.textContent = 'window.injected = 1';
                                       document.body.appendChild(s); return window.injected === 1; }""")
        assert ran is False
        assert any("Content Security Policy" in e for e in watch.errors), watch.errors  # and the browser said so
        page.goto(srv.url + "/signin")  # (leaves the report: its violation reports are in)
        watch.errors = []
        # another page (here: one made by the test) cannot frame the report
        page.set_content(f'<iframe id="f" src="{srv.url}/v1/jobs/{job["id"]}/report"></iframe>')
        page.wait_for_timeout(1500)
        framed = page.frame_locator("#f").locator("body[data-page]")
        assert framed.count() == 0
        assert any("frame" in e.lower() for e in watch.errors), watch.errors  # Chromium says why it refused
    finally:
        context.close()


def _report_outputs(folder: Path, n_rows: int = 3, per_row: int = 4) -> tuple[Path, Path]:
    """trees/points/rows/gaps Parquet files of a made-up block: trees on a grid, row 2's
    slot 3 empty; points: a square of points around each trunk."""
    rng = np.random.default_rng(1)
    rows, pos = np.meshgrid(np.arange(1, n_rows + 1), np.arange(1, per_row + 1), indexing="ij")
    keep = ~((rows == 2) & (pos == 3))
    rows, pos = rows[keep], pos[keep]
    n = len(rows)
    x, y = 500000.0 + pos * 4.0, 6000000.0 + rows * 5.0
    trees = pa.table({
        "tree_id": pa.array(np.arange(1, n + 1), pa.int64()), "trunk_x": x, "trunk_y": y, "trunk_z": np.zeros(n),
        "height_m": rng.uniform(2, 4, n), "crown_diameter_m": np.full(n, 2.5), "crown_area_m2": np.full(n, 4.9),
        "crown_volume_m3": np.full(n, 6.0), "trunk_diameter_m": np.full(n, 0.1), "n_points": pa.array(np.full(n, 50), pa.int64()),
        "wood_fraction": np.full(n, 0.2), "row": pa.array(rows, pa.int64()), "position": pa.array(pos, pa.int64()),
        "young": pa.array(pos == 1), "geometry": pa.array([b"\x01"] * n),
    })
    pq.write_table(trees, folder / "trees.parquet")
    pq.write_table(pa.table({"row": [2], "position": [3], "x": [500012.0], "y": [6000010.0]}), folder / "gaps.parquet")
    import laspy

    offsets = rng.uniform(-1, 1, (50, 2))
    pts = np.concatenate([np.c_[x[i] + offsets[:, 0], y[i] + offsets[:, 1]] for i in range(n)])
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.array([0.001] * 3), np.array([500000.0, 6000000.0, 0.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], np.ones(len(pts))
    las.write(str(folder / "block.las"))
    pq.write_table(pa.table({"point_index": pa.array(np.arange(len(pts)), pa.uint64()),
                             "tree_id": pa.array(np.repeat(np.arange(1, n + 1), 50), pa.int64())}), folder / "points.parquet")
    return folder / "trees.parquet", folder / "points.parquet"


@pytest.mark.slow
def test_report_html_opens_from_disk_offline(browser, tmp_path):
    from service.reports.report import write_report, write_trees_csv

    trees, points = _report_outputs(tmp_path)
    write_trees_csv(trees, tmp_path / "trees.csv")
    report = write_report(block_path=str(tmp_path / "block.las"), trees_parquet=trees, points_parquet=points,
                          out_dir=tmp_path, title="Orchard report — made up", summary={"Block": "made up"})
    moved = tmp_path / "elsewhere"  # a copy on its own still works: nothing is fetched
    moved.mkdir()
    shutil.copy(report, moved / "report.html")
    context = browser.new_context(viewport={"width": 1000, "height": 700})
    page = context.new_page()
    watch = Watch(context, page, {"file"})
    try:
        page.goto((moved / "report.html").as_uri())
        page.wait_for_selector("body[data-drawn]")
        assert page.text_content("#tree-count") == "11"
        assert page.evaluate("window.orchardView.d.outlines.filter(Boolean).length") == 11  # footprints from the points
        page.fill("#search", "3/4")
        page.press("#search", "Enter")
        assert "(row 3 tree 4)" in page.text_content("#searchresult")
        page.fill("#search", "row 2 tree 3")
        page.press("#search", "Enter")
        assert page.text_content("#searchresult") == "Row 2 tree 3 is an empty slot."
        rows = page.eval_on_selector_all("#rowstable tbody tr", "els => els.map(e => e.children[1].textContent)")
        assert rows == ["4", "3", "4"]
        page.select_option("#metric", "young")
        assert "yes" in page.text_content("#legend")
        _shot(page, "report")
        watch.clean()
    finally:
        context.close()


@pytest.mark.slow
def test_the_job_links_its_page_and_every_download(served):
    srv, tokens, jobs, trees = served
    job = jobs["a"]
    assert job["links"]["page"] == f"/jobs/{job['id']}"
    with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {tokens['a']}"}, timeout=60) as c:
        for name, link in job["links"].items():
            if name not in ("self", "page"):
                assert c.get(link).status_code == 200, name
        plain = c.get(f"/web/jobs/{job['id']}/map.json", headers={"Accept-Encoding": "identity"})
        assert "content-encoding" not in plain.headers and plain.json()["n_trees"] == len(trees)
        packed = c.get(f"/web/jobs/{job['id']}/map.json", headers={"Accept-Encoding": "gzip"})
        assert packed.headers["content-encoding"] == "gzip" and packed.json() == plain.json()
