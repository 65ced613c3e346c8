"""The pages of a capture of an orchard block in a real browser (Debian's Chromium through
Playwright): report.html opened from disk and the job page of a real `orchard serve`
colour the trees by growth, list the removed, new and replanted trees and the rows that
lag, and show a tree's history when it is clicked; without the capture columns (a job of
its own) they show what they showed before.

The outputs are made by hand with the contract's columns (`seasons_fixtures`): capture 2
of a block whose row 1 grew 0.30 m and row 2 0.05 m.
"""

from __future__ import annotations

import io
from pathlib import Path

import httpx
import numpy as np
import pytest
from seasons_fixtures import DATES, write_capture_outputs
from service_fixtures import ServerProcess, make_token, write_las
from test_web_browser import CHROMIUM, Watch, browser  # noqa: F401 - the module's browser fixture

from service.db.jobstore import Store
from service.reports.report import write_report
from service.seasons import capture_record

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"no browser: {CHROMIUM} is missing")]


def _report(folder: Path, which: str, *, with_history: bool = True) -> Path:
    write_capture_outputs(folder, which, with_history=with_history)
    import pyarrow.parquet as pq

    trees = pq.read_table(str(folder / "trees.parquet")).to_pydict()
    # points around each trunk, as the job's sample of the block would be (local frame)
    rng = np.random.default_rng(0)
    origin = np.array([np.floor(min(trees["trunk_x"])), np.floor(min(trees["trunk_y"])), 0.0])
    xy = np.concatenate([np.c_[x - origin[0] + rng.uniform(-0.9, 0.9, 40), y - origin[1] + rng.uniform(-0.9, 0.9, 40)]
                         for x, y in zip(trees["trunk_x"], trees["trunk_y"])])
    ids = np.repeat(trees["tree_id"], 40)
    from pipeline.mapsample import REPORT_POINTS

    return write_report(block_path=str(folder / "none.laz"), trees_parquet=folder / "trees.parquet",
                        points_parquet=folder / "points.parquet", out_dir=folder, title=f"Capture {which}",
                        sample={"xy": xy, "tree_id": ids, "origin": origin, "max_points": REPORT_POINTS})


def _pixel(page, i: int, dx: float = 0.55) -> tuple[int, int, int]:
    """The colour the page shows ``dx`` metres east of tree ``i``'s trunk (inside its crown)."""
    x, y = page.evaluate(
        """([i, dx]) => { const v = window.orchardView;
                    const p = v.map.latLngToContainerPoint([v.d.y[i], v.d.x[i] + dx]); const r = document.getElementById('map').getBoundingClientRect();
                    return [r.left + p.x, r.top + p.y]; }""", [i, dx])
    from PIL import Image

    img = Image.open(io.BytesIO(page.screenshot())).convert("RGB")
    return img.getpixel((round(x), round(y)))


def _expected(page, i: int) -> tuple[int, int, int]:
    """Tree ``i``'s bin colour drawn at 80 % over the map's background (#f4f1e8)."""
    rgb = page.evaluate("(i) => { const v = window.orchardView; return v.binColour[v.bin[i]]; }", i)
    if rgb.startswith("#"):
        c = [int(rgb[k:k + 2], 16) for k in (1, 3, 5)]
    else:
        c = [int(v) for v in rgb[rgb.index("(") + 1:-1].split(",")]
    return tuple(round(0.8 * a + 0.2 * b) for a, b in zip(c, (0xF4, 0xF1, 0xE8)))


def _index_of_key(page, key: int) -> int:
    return page.evaluate("(k) => window.orchardView.cols.tree_key.indexOf(k)", key)


def _click_tree(page, i: int) -> None:
    x, y = page.evaluate(
        """(i) => { const v = window.orchardView;
                    const p = v.map.latLngToContainerPoint([v.d.y[i], v.d.x[i]]); const r = document.getElementById('map').getBoundingClientRect();
                    return [r.left + p.x, r.top + p.y]; }""", i)
    page.mouse.click(x, y)


def _check_capture_page(page) -> None:
    """What a page of capture 2 must show (report and job page alike)."""
    page.wait_for_selector("body[data-drawn]", timeout=60_000)
    assert page.evaluate("document.getElementById('metric').value") == "height_change_m"
    # growth colours: row 1 (+0.30 m, the most) dark green, row 2 (+0.05 m) pale, a new tree grey
    grew, lagged, new = (_index_of_key(page, k) for k in (1, 5, 8))
    for i in (grew, lagged, new):
        got, want = _pixel(page, i), _expected(page, i)
        assert max(abs(a - b) for a, b in zip(got, want)) <= 12, (i, got, want)
    g, l_, n = (_pixel(page, i) for i in (grew, lagged, new))
    assert g[1] > g[0] + 60 and l_[0] > g[0] + 80  # green against a paler yellow-green
    assert abs(n[0] - n[1]) < 12 and abs(n[1] - n[2]) < 20  # no previous measure: grey
    assert "grew" in page.text_content("#legend")
    # the lists
    removed = page.text_content("#removedtrees")
    assert "row 1 tree 3 (key 3)" in removed and f"last seen {DATES['c1']}" in removed
    assert page.locator("#newtrees li").count() == 1 and "row 2 tree 5" in page.text_content("#newtrees")
    assert page.locator("#replantedtrees li").count() == 1 and "row 2 tree 3" in page.text_content("#replantedtrees")
    lag = page.text_content("#laggingrows")
    assert "Row 2" in lag and "Row 1" not in lag
    assert "residual 2.1 cm" in page.text_content("#registration")
    # a tree's history on a click on the map
    _click_tree(page, grew)
    page.wait_for_selector("#tree-history")
    cells = page.eval_on_selector_all("#tree-history tbody tr", "rows => rows.map(r => [...r.children].map(c => c.textContent))")
    assert [c[0] for c in cells] == [DATES["c1"], DATES["c2"]] and [c[1] for c in cells] == ["new", "same"]
    assert float(cells[1][2]) - float(cells[0][2]) == pytest.approx(0.30, abs=0.011)
    assert page.locator("#details svg.sparkline circle").count() == 2
    # and of a removed tree, from its list
    page.click("#removedtrees a")
    assert page.text_content("#selected-tree") == "Removed tree (key 3)"
    assert [r[1] for r in page.eval_on_selector_all("#tree-history tbody tr",
                                                    "rows => rows.map(r => [...r.children].map(c => c.textContent))")] == ["new", "removed"]


def test_report_of_a_capture_shows_growth_changes_and_history(browser, tmp_path):  # noqa: F811
    report = _report(tmp_path, "c2")
    context = browser.new_context(viewport={"width": 1100, "height": 800})
    page = context.new_page()
    watch = Watch(context, page, {"file"})
    try:
        page.goto(report.as_uri())
        _check_capture_page(page)
        assert "Block history" in page.text_content("#downloads")  # history.parquet beside it
        watch.clean()
    finally:
        context.close()
    # no inline script added: at most leaflet, orchard.js, job.js and the bootstrap (the data is JSON)
    assert report.read_text().count("<script>") <= 4


@pytest.mark.parametrize("which, history", [("c1", False), ("c1", True)])
def test_pages_without_changes_show_what_they_showed_before(browser, tmp_path, which, history):  # noqa: F811
    report = _report(tmp_path, which, with_history=history)
    context = browser.new_context(viewport={"width": 1000, "height": 700})
    page = context.new_page()
    watch = Watch(context, page, {"file"})
    try:
        page.goto(report.as_uri())
        page.wait_for_selector("body[data-drawn]")
        assert page.evaluate("document.getElementById('metric').value") == "height_m"
        if history:  # the block's first capture: keys, but nothing to compare with yet
            assert "first capture" in page.text_content("#firstcapture")
        else:
            assert page.is_hidden("#changes")
        _click_tree(page, 0)
        assert page.text_content("#selected-tree").startswith("Tree 1")
        assert page.locator("#tree-history").count() == (1 if history else 0)
        watch.clean()
    finally:
        context.close()


@pytest.fixture(scope="module")
def served_capture(tmp_path_factory):
    """A real server (runner off) with farm a's orchard block whose second capture's job
    is done with capture 2's outputs."""
    root = tmp_path_factory.mktemp("seasons-web")
    srv = ServerProcess(root / "data", ORCHARD_RUNNER="false", ORCHARD_SCHEDULING="false")
    srv.start()
    try:
        token = make_token(srv.data_dir, "farm-a")
        las = write_las(root / "scan.laz", 500, seed=4)
        with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
            ob = c.post("/v1/orchard-blocks", json={"name": "North"}).json()
            cap = c.post(f"/v1/orchard-blocks/{ob['id']}/captures", files={"file": ("july.laz", las.read_bytes())}).json()
        out = srv.data_dir / "jobs" / cap["job_id"]  # the server's job folder (service.jobfolders.job_dir)
        write_capture_outputs(out, "c2")
        store = Store(srv.data_dir / "orchard.sqlite")
        try:  # done, as the runner would record it
            with store.db.transaction() as con:
                con.execute("UPDATE jobs SET state = 'running' WHERE id = ?", (cap["job_id"],))
            store.orchard_blocks.set_capture_record(cap["job_id"], capture_record(out))
            store.jobs.finish(cap["job_id"], "done", outcome={"n_trees": 8, "outputs": {"history": str(out / "history.parquet")}})
        finally:
            store.close()
        yield srv, token, ob, cap
    finally:
        srv.stop()


def test_job_page_of_a_capture_shows_growth_changes_and_history(browser, served_capture):  # noqa: F811
    srv, token, ob, cap = served_capture
    context = browser.new_context(viewport={"width": 1100, "height": 800})
    page = context.new_page()
    watch = Watch(context, page, {"127.0.0.1"})
    try:
        page.goto(srv.url + "/signin")
        page.fill("#token", token)
        page.click("#signin")
        page.wait_for_url("**/blocks")
        # the blocks page lists the orchard block with its capture, which leads to the job page
        row = page.wait_for_selector(f"[data-orchard-block='{ob['id']}'] tr[data-capture='{cap['id']}']")
        assert "2026-07-01 (from the file)" in row.inner_text() and "6 same, 1 new, 1 replanted, 1 removed" in row.inner_text()
        assert "1 capture(s), 1 processed, latest 2026-07-01" in page.text_content(f"[data-orchard-block='{ob['id']}']")
        page.click(f"tr[data-capture='{cap['id']}'] a")
        page.wait_for_url(f"**/jobs/{cap['job_id']}")
        _check_capture_page(page)
        assert page.text_content("#orchardblock").startswith("capture 1 of orchard block North, 2026-07-01")
        href = page.get_attribute("#downloads a:has-text('Block history')", "href")
        assert page.request.get(srv.url + href).status == 200
        watch.clean()
    finally:
        context.close()
