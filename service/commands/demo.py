"""``orchard demo``: the whole product in one command, on a generated orchard block.

Starts the service on loopback (uvicorn in a background thread, an embedded dask
LocalCluster behind its job runner), creates a tenant token, generates a small orchard
with the simulator, uploads it over HTTP, submits a tiled job, shows its progress,
downloads the per-tree table and the report, prints the table and where the report
page is, then shuts everything down.
"""

from __future__ import annotations

import argparse
import csv
import io
import re
import sys
import tempfile
import threading
import time
from pathlib import Path

from pipeline.errors import OrchardError
from service.commands.options import tiling_default
from service.commands.serve import bind

NAME = "demo"
HELP = "Run the service locally on a generated orchard block and print the per-tree table."

_TABLE = [
    ("tree_id", "tree", "{:>4}"),
    ("row", "row", "{:>3}"),
    ("position", "pos", "{:>3}"),
    ("trunk_x", "trunk x", "{:>12.2f}"),
    ("trunk_y", "trunk y", "{:>12.2f}"),
    ("height_m", "height m", "{:>8.2f}"),
    ("crown_diameter_m", "crown ⌀ m", "{:>9.2f}"),
    ("crown_area_m2", "crown m²", "{:>8.1f}"),
    ("crown_volume_m3", "crown m³", "{:>8.1f}"),
    ("trunk_diameter_m", "trunk ⌀ m", "{:>9.3f}"),
    ("n_points", "points", "{:>8}"),
    ("wood_fraction", "wood", "{:>5.2f}"),
]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data-dir", default=None, help="service data folder (default: a new temporary folder, kept afterwards)")
    parser.add_argument("--rows", type=int, default=2, help="tree rows of the generated orchard (default 2)")
    parser.add_argument("--trees-per-row", type=int, default=5, help="trees in each row (default 5)")
    parser.add_argument("--density", type=float, default=0.5, help="point density scale of the simulator (default 0.5)")
    parser.add_argument("--seed", type=int, default=1, help="random seed of the generated orchard (default 1)")
    parser.add_argument("--tile-size", type=float, default=20.0, help="tile size [m] for the dask workers (default 20; 0 = one tile)")
    workers = tiling_default("workers")
    parser.add_argument("--workers", type=int, default=workers, help=f"dask workers of the embedded LocalCluster (default {workers})")


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _format_value(fmt: str, raw: str) -> str:
    try:
        value = float(raw)
        if "f" not in fmt:
            value = int(value)
        return fmt.format(value)
    except (TypeError, ValueError):
        width = int(re.match(r"\{:>(\d+)", fmt).group(1))  # "{:>12.2f}" -> 12
        return (raw or "–").rjust(width)


def format_table(csv_text: str) -> str:
    """The per-tree table of ``trees.csv`` as aligned text."""
    rows = list(csv.DictReader(io.StringIO(csv_text)))
    widths = [len(_format_value(fmt, "0")) for _, _, fmt in _TABLE]
    lines = ["  ".join(label.rjust(max(w, len(label))) for (_, label, _), w in zip(_TABLE, widths))]
    for r in rows:
        lines.append(
            "  ".join(_format_value(fmt, r.get(key, "")).rjust(max(w, len(label))) for (key, label, fmt), w in zip(_TABLE, widths))
        )
    return "\n".join(lines)


class _Progress:
    def __init__(self) -> None:
        self.tty = sys.stderr.isatty()
        self.last = None

    def show(self, job: dict) -> None:
        done, total, state = job["tiles_done"], job["tiles_total"], job["state"]
        key = (state, done, total)
        if key == self.last:
            return
        self.last = key
        width = 30
        filled = int(width * done / total) if total else 0
        bar = "#" * filled + "-" * (width - filled)
        line = f"  job {state:<9} tiles {done}/{total or '?'} [{bar}]"
        if self.tty:
            print("\r" + line, end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr, flush=True)

    def end(self) -> None:
        if self.tty:
            print(file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Generate a block, serve it, process it over HTTP and print its trees; 0 when done."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.app import create_app
    from service.auth import create_token
    from service.settings import build_settings
    from workers.cluster import interrupts_deferred

    t_start = time.perf_counter()
    data_dir = Path(args.data_dir) if args.data_dir else Path(tempfile.mkdtemp(prefix="orchard-demo-"))
    out_dir = data_dir / "demo"
    out_dir.mkdir(parents=True, exist_ok=True)
    settings = build_settings(
        data_dir=data_dir, host="127.0.0.1", port=0, n_workers=args.workers, scheduling=False, dashboard=False
    )
    sim, block_path = _generate_block(args, out_dir)
    app = create_app(settings)
    token = create_token(app.state.store, "demo-farm")
    server, thread, base = _start_server(app, settings.host, data_dir)
    try:
        _wait_started(server, thread)
        job, csv_text, report_path = _run_job(base, token, args, block_path, out_dir)
    finally:
        _say("shutting the service and its dask workers down ...")
        server.should_exit = True
        with interrupts_deferred():  # a Ctrl-C now waits until the cluster is closed
            thread.join(60)

    timings = ", ".join(f"{k} {v:.1f} s" for k, v in (job.get("timings") or {}).items() if isinstance(v, (int, float)))
    print(f"\n{job['n_trees']} trees found in {job['n_points']:,} points ({sim.rows * sim.trees_per_row} simulated); {timings}\n")
    print(format_table(csv_text))
    print(f"\nper-tree table: {out_dir / 'trees.csv'}")
    print(f"report page:    {report_path}")
    _say(f"demo finished in {time.perf_counter() - t_start:.0f} s")
    return 0


def _generate_block(args: argparse.Namespace, out_dir: Path):
    """The simulator's parameters and the LAZ block it generated in ``out_dir`` (its truth beside it)."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from simulator.simparams import SimulationParams
    from simulator.simulate import simulate_orchard
    from simulator.truth import write_simulation

    sim = SimulationParams(rows=args.rows, trees_per_row=args.trees_per_row, density=args.density, seed=args.seed)
    _say(f"orchard demo: generating a {sim.rows} x {sim.trees_per_row} tree orchard block (simulator, seed {sim.seed}) ...")
    orchard = simulate_orchard(sim)
    block_path = out_dir / "orchard-block.laz"
    write_simulation(orchard, str(block_path), str(out_dir / "truth.parquet"))
    _say(f"  {len(orchard.xyz):,} points -> {block_path}")
    return sim, block_path


def _start_server(app, host: str, data_dir: Path):
    """The uvicorn server of ``app`` started in a background thread on a free port of
    ``host``, the thread, and the server's base URL.

    The socket is bound here, before the server starts, and handed to it: a port picked
    free first and bound later races with every other process on the machine.
    """
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    import uvicorn

    sock = bind(host, 0)
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host=host, port=port, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, name="orchard-demo-server", daemon=True)
    _say(f"starting the service on http://{host}:{port} (docs at /docs), data in {data_dir}")
    thread.start()
    return server, thread, f"http://{host}:{port}"


def _wait_started(server, thread: threading.Thread, seconds: float = 60) -> None:
    """RuntimeError unless the server accepts connections within ``seconds``."""
    deadline = time.monotonic() + seconds
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the service did not start")
        time.sleep(0.05)


def _run_job(base: str, token: str, args: argparse.Namespace, block_path: Path, out_dir: Path):
    """Upload the block, run a job on it and download its results into ``out_dir``, over
    HTTP as a client would: the finished job, its per-tree CSV text and the report's path.

    Raises
    ------
    OrchardError
        The job did not finish.
    """
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    import httpx

    with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=120) as http:
        _say("uploading the block over HTTP (POST /v1/blocks) ...")
        with open(block_path, "rb") as fh:
            r = http.post("/v1/blocks", files={"file": (block_path.name, fh, "application/octet-stream")})
        r.raise_for_status()
        block = r.json()
        _say(f"  block {block['id']}: {block['n_points']:,} points, sha256 {block['sha256'][:12]}...")
        body: dict = {"block_id": block["id"]}
        if args.tile_size and args.tile_size > 0:
            body["tiling"] = {"tile_size": args.tile_size}
        r = http.post("/v1/jobs", json=body)
        r.raise_for_status()
        job = r.json()
        tiling = f"{args.tile_size:g} m tiles" if "tiling" in body else "one tile"
        _say(f"submitted job {job['id']} ({tiling}) on {args.workers} dask worker(s); waiting ...")
        job = _follow(http, job["id"])
        if job["state"] != "done":
            raise OrchardError(f"the job {job['state']}: {job['error']}")
        csv_text = http.get(f"/v1/jobs/{job['id']}/trees.csv").text
        (out_dir / "trees.csv").write_text(csv_text, encoding="utf-8")
        report = http.get(f"/v1/jobs/{job['id']}/report")
        report.raise_for_status()
        report_path = out_dir / "report.html"
        report_path.write_text(report.text, encoding="utf-8")
    return job, csv_text, report_path


def _follow(http, job_id: str) -> dict:
    """The job once it is done, failed or cancelled, its progress shown meanwhile."""
    progress = _Progress()
    while True:
        job = http.get(f"/v1/jobs/{job_id}").json()
        progress.show(job)
        if job["state"] in ("done", "failed", "cancelled"):
            break
        time.sleep(0.3)
    progress.end()
    return job
