"""``python -m bench.webpage``: how fast the job page draws, and how much it weighs.

A real `orchard serve` (runner off) on loopback holds a finished job per size with a
synthetic trees table (trees on a grid of rows, 12-vertex crown footprints, row lines
and a few empty slots). Headless Chromium (Debian's, driven by Playwright) signs in and
opens each job page; measured per size (median of ``--repeats`` loads):

- first draw [ms]: from the start of navigation to the first frame with every tree on
  the map (``window.orchardFirstDraw``, set by job.js);
- page weight [kB]: every byte the page loaded (HTML, scripts, styles, JSON), as sent
  (the map's data gzipped, the rest as is);
- zoom and recolour [ms]: one zoom step, and colouring by another metric, each to the
  next frame drawn (what "fluid" means when panning and exploring).

The same data as a self-contained ``report.html`` opened from disk: its size and first draw.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]


def synthetic_map(n: int, *, seed: int = 0) -> tuple[pa.Table, dict]:
    """A trees table of ``n`` trees in rows of 100 (4 m apart, 3 m along the row) and the
    map data the page draws for it (local metres)."""
    rng = np.random.default_rng(seed)
    per_row = min(n, 100)
    k = np.arange(n)
    row, pos = k // per_row + 1, k % per_row + 1
    x = 1000.0 + pos * 3.0 + rng.normal(0, 0.1, n)
    y = 2000.0 + row * 4.0 + rng.normal(0, 0.1, n)
    crown = rng.uniform(1.8, 2.8, n)
    table = pa.table({
        "tree_id": pa.array(k + 1, pa.int64()), "trunk_x": x, "trunk_y": y, "trunk_z": np.zeros(n),
        "height_m": rng.uniform(2.5, 4.5, n), "crown_diameter_m": crown, "crown_area_m2": np.pi * (crown / 2) ** 2,
        "crown_volume_m3": rng.uniform(3, 9, n), "trunk_diameter_m": rng.uniform(0.05, 0.2, n),
        "n_points": pa.array(rng.integers(500, 5000, n), pa.int64()), "wood_fraction": rng.uniform(0.1, 0.3, n),
        "row": pa.array(row, pa.int64()), "position": pa.array(pos, pa.int64()), "young": pa.array(rng.random(n) < 0.05),
    })
    origin = np.floor([x.min(), y.min()])
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    outlines = []
    for i in range(n):
        r = crown[i] / 2 * rng.uniform(0.85, 1.1, 12)
        ring = np.c_[x[i] - origin[0] + r * np.cos(angles), y[i] - origin[1] + r * np.sin(angles)]
        outlines.append(np.round(ring, 2).ravel().tolist())
    cols = {name: table.column(name).to_numpy(zero_copy_only=False) for name in table.column_names}
    from service.reports.mapdata import _clean

    rows = sorted(set(row.tolist()))
    data = {
        "origin": origin.tolist(), "n_trees": n,
        "x": _clean(np.round(x - origin[0], 2)), "y": _clean(np.round(y - origin[1], 2)),
        "columns": {name: _clean(v) for name, v in cols.items()},
        "outlines": outlines,
        "rows": [{"row": r, "line": [3.0 - origin[0] + 1000, 2000 + r * 4.0 - origin[1], 1000 + per_row * 3.0 - origin[0],
                                     2000 + r * 4.0 - origin[1]]} for r in rows],
        "gaps": [{"row": int(row[i]), "position": int(pos[i]) + 1, "x": float(x[i] - origin[0] + 1.5),
                  "y": float(y[i] - origin[1])} for i in range(0, n, 97)],
        "partial": False,
    }
    return table, data


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def prepare(data_dir: Path, sizes: list[int]) -> tuple[str, dict[int, str], dict[int, dict]]:
    """A data folder with one finished job per size; (token, job id per size, map data per size)."""
    import laspy

    from service.auth import create_token
    from service.db.block_files import accept_block
    from service.db.jobstore import Store
    from service.reports.report import atomic_write
    from service.jobfolders import job_dir
    from service.schedules import file_sha256
    from service.settings import Settings
    from service.reports.mapdata import to_json

    settings = Settings(data_dir=data_dir)
    settings.blocks_dir.mkdir(parents=True, exist_ok=True)
    store = Store(settings.store_path)
    try:
        token = create_token(store, "bench")
        tenant = store.accounts.tenant_by_name("bench")
        las_path = data_dir / "upload.las"
        header = laspy.LasHeader(point_format=6, version="1.4")
        las = laspy.LasData(header)
        las.x, las.y, las.z = np.arange(10.0), np.arange(10.0), np.zeros(10)
        las.write(str(las_path))
        block, _ = accept_block(store, blocks_dir=settings.blocks_dir, tenant_id=tenant["id"], tmp_path=las_path,
                                sha256=file_sha256(las_path), size_bytes=las_path.stat().st_size, filename="synthetic.las")
        jobs, datas = {}, {}
        for n in sizes:
            table, data = synthetic_map(n)
            job = store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
            store.jobs.claim_next()
            out = job_dir(settings, job["id"])
            out.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, out / "trees.parquet")
            # (newer than trees.parquet: served as is)
            atomic_write(out / "map.json.gz", gzip.compress(to_json(data).encode(), mtime=0))
            store.jobs.finish(job["id"], "done", outcome={"n_trees": n, "n_points": 0})
            jobs[n], datas[n] = job["id"], data
        return token, jobs, datas
    finally:
        store.close()


def _timings(page) -> dict:
    return page.evaluate(
        """async () => {
            const frame = () => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)));
            const v = window.orchardView, out = {first_draw_ms: window.orchardFirstDraw};
            let t = performance.now(); v.map.setZoom(v.map.getZoom() + 1, {animate: false}); await frame();
            out.zoom_ms = performance.now() - t;
            t = performance.now(); v.metric = 'crown_volume_m3'; v.recolour(); await frame();
            out.recolour_ms = performance.now() - t;
            const nav = performance.getEntriesByType('navigation')[0];
            out.bytes = (nav ? nav.encodedBodySize : 0) +
                performance.getEntriesByType('resource').reduce((s, e) => s + e.encodedBodySize, 0);
            return out;
        }"""
    )


def measure(sizes: list[int], repeats: int, work: Path) -> list[dict]:
    from playwright.sync_api import sync_playwright

    from service.reports.mapdata import to_json
    from service.pages import report_page

    data_dir = work / "data"
    token, jobs, datas = prepare(data_dir, sizes)
    port = _free_port()
    env = {**os.environ, "ORCHARD_RUNNER": "false", "ORCHARD_SCHEDULING": "false"}
    log = open(work / "serve.log", "ab")
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--data-dir", str(data_dir), "--host", "127.0.0.1",
                             "--port", str(port), "--log-level", "warning"], env=env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    results = []
    try:
        import httpx

        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(url + "/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("orchard serve did not come up: see " + str(work / "serve.log"))
            time.sleep(0.2)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            context = browser.new_context(viewport={"width": 1280, "height": 800})
            page = context.new_page()
            page.goto(url + "/signin")
            page.fill("#token", token)
            page.click("#signin")
            page.wait_for_url("**/blocks")
            for n in sizes:
                runs = []
                for _ in range(repeats):
                    page = context.new_page()
                    page.goto(f"{url}/jobs/{jobs[n]}")
                    page.wait_for_selector("body[data-drawn]", timeout=120_000)
                    runs.append(_timings(page))
                    page.close()
                report = work / f"report-{n}.html"
                report.write_text(report_page(title=f"synthetic {n}", data_json=to_json(datas[n]), facts={}, downloads={}),
                                  encoding="utf-8")
                disk = []
                for _ in range(repeats):
                    page = context.new_page()
                    page.goto(report.as_uri())
                    page.wait_for_selector("body[data-drawn]", timeout=120_000)
                    disk.append(page.evaluate("window.orchardFirstDraw"))
                    page.close()
                results.append({
                    "trees": n,
                    "first_draw_ms": statistics.median(r["first_draw_ms"] for r in runs),
                    "zoom_ms": statistics.median(r["zoom_ms"] for r in runs),
                    "recolour_ms": statistics.median(r["recolour_ms"] for r in runs),
                    "page_kB": runs[0]["bytes"] / 1000,
                    "map_json_kB": len(gzip.compress(to_json(datas[n]).encode(), mtime=0)) / 1000,
                    "report_kB": report.stat().st_size / 1000,
                    "report_first_draw_ms": statistics.median(disk),
                })
            browser.close()
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.webpage", description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="500,5000", help="trees per job, comma-separated (default 500,5000)")
    p.add_argument("--repeats", type=int, default=3, help="page loads per size (median reported; default 3)")
    args = p.parse_args(argv)
    if not Path(CHROMIUM).exists():
        print(f"bench.webpage: no browser at {CHROMIUM} (apt-get install -y chromium)", file=sys.stderr)
        return 2
    sizes = [int(s) for s in args.sizes.split(",")]
    with tempfile.TemporaryDirectory(prefix="orchard-webpage-") as tmp:
        results = measure(sizes, args.repeats, Path(tmp))
    print("| trees | first draw [ms] | zoom step [ms] | recolour [ms] | page weight [kB] | of it map.json, gzipped [kB] "
          "| report.html [kB] | report.html first draw [ms] |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in results:
        print(f"| {r['trees']:,} | {r['first_draw_ms']:.0f} | {r['zoom_ms']:.0f} | {r['recolour_ms']:.0f} | {r['page_kB']:.0f} "
              f"| {r['map_json_kB']:.0f} | {r['report_kB']:.0f} | {r['report_first_draw_ms']:.0f} |")
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
