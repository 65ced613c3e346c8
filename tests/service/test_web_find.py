"""The pages' find, zoom and outlines in headless Chromium, and the blocks page's inboxes.

The job page's script is tested through report.html opened from disk (the same script,
no server): a made-up block of 1,049 trees in 25 rows with an empty slot at row 2 tree 3.
"""

from __future__ import annotations

import io
from pathlib import Path

import httpx
import pytest
from service_fixtures import ServerProcess, make_token, write_las
from test_web_browser import CHROMIUM, CHROMIUM_ARGS, Watch, _report_outputs

pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).exists(),
    reason=f"no browser: {CHROMIUM} is missing (Debian: apt-get install -y chromium; .ci/run installs it)",
)

N_ROWS, PER_ROW = 25, 42


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module")
def big_report(tmp_path_factory):
    """report.html of the made-up block, as `service.reports.report.write_report` writes it but
    without its map image and footprints (seconds): the trees are drawn as crown circles."""
    from service.reports import mapdata
    from service import pages

    folder = tmp_path_factory.mktemp("big")
    trees, _ = _report_outputs(folder, n_rows=N_ROWS, per_row=PER_ROW)
    page = pages.report_page(title="Big block", data_json=mapdata.to_json(mapdata.build_map_data(trees)),
                              facts={"Block": "made up"}, downloads={})
    (folder / "report.html").write_text(page, encoding="utf-8")
    return folder / "report.html"


@pytest.fixture()
def report_page(browser, big_report):
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    page = context.new_page()
    watch = Watch(context, page, {"file"})
    page.goto(Path(big_report).as_uri())
    page.wait_for_selector("body[data-drawn]")
    yield page
    watch.clean()
    context.close()


def _find(page, text: str) -> str:
    page.fill("#search", text)
    page.press("#search", "Enter")
    return page.text_content("#searchresult")


def _index(page, row: int, pos: int) -> int:
    return page.evaluate("([r, p]) => window.orchardView.cols.row.findIndex((v, k) => v === r && window.orchardView.cols.position[k] === p)",
                         [row, pos])


def _on_screen(page, x_local: float, y_local: float) -> tuple[float, float, bool]:
    """Where a point (local metres) is in the page, and whether it is inside the map."""
    return tuple(page.evaluate(
        """([x, y]) => { const v = window.orchardView, p = v.map.latLngToContainerPoint([y, x]);
                        const r = document.getElementById('map').getBoundingClientRect();
                        return [r.left + p.x, r.top + p.y, p.x >= 0 && p.y >= 0 && p.x <= r.width && p.y <= r.height]; }""",
        [x_local, y_local]))


def _orange(page, x: float, y: float, half: float) -> int:
    """Pixels of the outline colour in a square of the page around (x, y)."""
    import numpy as np
    from PIL import Image

    png = page.screenshot(clip={"x": x - half, "y": y - half, "width": 2 * half, "height": 2 * half})
    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    return int(((a[..., 0] > 200) & (a[..., 1] > 60) & (a[..., 1] < 130) & (a[..., 2] < 60)).sum())


def _tree(page, i: int) -> tuple[float, float]:
    return tuple(page.evaluate("(i) => [window.orchardView.d.x[i], window.orchardView.d.y[i]]", i))


def test_a_found_tree_is_zoomed_to_and_outlined_alone(report_page):
    page = report_page
    assert page.text_content("#tree-count") == f"{N_ROWS * PER_ROW - 1:,}"
    crown_px = lambda: 2.5 * page.evaluate("window.orchardView.layer.scale()")  # noqa: E731
    assert crown_px() < 20  # the whole block: a tree is a few pixels
    assert "(row 20 tree 30)" in _find(page, "row 20 tree 30")
    i = _index(page, 20, 30)
    assert page.evaluate("window.orchardView.mark") == {"tree": i}
    assert crown_px() >= 60  # clearly visible
    x, y, inside = _on_screen(page, *_tree(page, i))
    assert inside and _orange(page, x, y, 2.5 * crown_px() / 2 + 6) > 50
    # the tree beside the empty slot, then the slot: the tree's outline goes, the slot's ring comes
    _find(page, "2/4")
    j = _index(page, 2, 4)
    tx, ty, _ = _on_screen(page, *_tree(page, j))
    assert _orange(page, tx, ty, crown_px() / 2 + 6) > 50
    assert _find(page, "row 2 tree 3") == "Row 2 tree 3 is an empty slot."
    assert page.evaluate("window.orchardView.mark.tree") is None and page.evaluate("window.orchardView.selected") == -1
    assert page.text_content("#details h3") == "Empty slot (row 2 tree 3)"
    tx, ty, inside_tree = _on_screen(page, *_tree(page, j))
    assert inside_tree and _orange(page, tx, ty, crown_px() / 2 - 3) == 0  # the old outline is gone
    gx, gy, inside_slot = _on_screen(page, *page.evaluate("[window.orchardView.mark.gap.x, window.orchardView.mark.gap.y]"))
    assert inside_slot and _orange(page, gx, gy, crown_px() / 2 + 8) > 30
    assert page.eval_on_selector_all("#treestable tr.selected", "els => els.length") == 0


def test_search_understands_ids_addresses_and_rows(report_page):
    page = report_page
    out = _find(page, "12")
    assert out.startswith("Found tree 12 (row 1 tree 12).") and 'For row 12, type "row 12"' in out
    assert _find(page, "tree 12").startswith("Found tree 12 (row 1 tree 12).")
    for q in ("5/3", "row 5 tree 3", "r5 p3", "5 3", "Row 5, tree 3"):
        assert "(row 5 tree 3)" in _find(page, q), q
    assert _find(page, "row 5") == f"Row 5: {PER_ROW} trees."
    mark = page.evaluate("window.orchardView.mark")
    assert mark["row"] == 5 and len(mark["idx"]) == PER_ROW and "tree" not in mark
    assert page.text_content("#selected-row") == "Row 5"
    ends = [_on_screen(page, *_tree(page, _index(page, 5, p))) for p in (1, PER_ROW)]
    assert all(e[2] for e in ends)  # the whole row in view
    assert _find(page, "row 99") == "No row 99."
    assert _find(page, "row 5 tree 99") == "No such tree."
    assert _find(page, "apple").startswith("Type a tree id")


def test_rows_are_numbered_and_the_table_fits_the_page(report_page):
    page = report_page
    assert page.evaluate("window.orchardView.rowLabels.length") == N_ROWS
    assert page.evaluate("window.orchardView.labelsDrawn") >= N_ROWS // 2
    heads = page.eval_on_selector_all("#treestable th", "els => els.map(e => e.textContent)")
    assert heads[:3] == ["Row", "Position", "Tree"] and "Young" in heads
    width = page.evaluate("() => { const s = document.querySelector('#treestable').parentElement; return [s.scrollWidth, s.clientWidth]; }")
    assert width[0] <= width[1], width
    k = heads.index("Young")
    young = set(page.eval_on_selector_all("#treestable tbody tr", f"els => els.map(e => e.children[{k}].textContent)"))
    assert young == {"yes", "no"}
    _find(page, "1/1")
    assert "yes" in page.text_content("#details")


@pytest.mark.slow
def test_the_blocks_page_lists_rejected_and_ignored_captures(browser, tmp_path):
    srv = ServerProcess(tmp_path / "data", ORCHARD_RUNNER="false", ORCHARD_SCHEDULING="false", ORCHARD_CAPTURE_SETTLE_S="0")
    srv.start()
    try:
        token = make_token(srv.data_dir, "farm-a")
        inbox = srv.data_dir / "inboxes" / "farm-a" / "night"
        inbox.mkdir(parents=True)
        write_las(inbox / "good.laz", 400, seed=1)
        (inbox / "bad.laz").write_text("not points")
        (inbox / "scan.csv").write_text("1 2 3\n")
        with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
            sid = c.post("/v1/schedules", json={"inbox": str(inbox)}).json()["id"]
            assert len(c.post(f"/v1/schedules/{sid}/run").json()["jobs"]) == 1
        context = browser.new_context(viewport={"width": 1200, "height": 800})
        page = context.new_page()
        watch = Watch(context, page, {"127.0.0.1"})
        try:
            page.goto(srv.url + "/signin")
            page.fill("#token", token)
            page.click("#signin")
            page.wait_for_url("**/blocks")
            page.wait_for_selector(f"section[data-schedule='{sid}'] tr[data-capture]")
            fates = dict(page.eval_on_selector_all("#inboxes tr[data-capture]", "els => els.map(e => [e.dataset.capture, e.dataset.fate])"))
            assert fates == {"good.laz": "processed", "bad.laz": "rejected", "scan.csv": "ignored"}
            assert "LASF" in page.text_content("tr[data-capture='bad.laz'] .reason")
            assert ".csv" in page.text_content("tr[data-capture='scan.csv'] .reason")
            page.click("tr[data-capture='good.laz'] a")
            page.wait_for_url("**/jobs/*")
            watch.clean()
        finally:
            context.close()
    finally:
        srv.stop()
