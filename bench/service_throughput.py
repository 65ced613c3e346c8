"""``python -m bench.service_throughput``: one job through ``orchard serve``, where orchards
are processed.

    python -m bench.service_throughput [--points-m 100] [--topologies embedded,external] [--copc PDAL_PYTHON]

A vase block at mobile density (:mod:`bench.density`'s scanner: 500,000 points a tree)
grown to about ``--points-m`` million points is uploaded to a fresh ``orchard serve``
with 2 workers and processed with the service's defaults (tiles chosen by the memory
budget). Two topologies, one after the other:

- ``embedded``: ``orchard serve`` with its embedded cluster (2 worker processes, mutual
  TLS with certificates made at its start);
- ``external``: ``dask scheduler`` and two ``dask worker`` processes started apart,
  speaking TLS with a CA and a certificate made here (dask's configuration in the
  environment, as docs/cluster.md tells an operator), and ``orchard serve --scheduler
  tls://...``.

Measured per topology, in one run: the job's wall time from its start to its last
output (the job store's ``started_at`` to ``finished_at``), the CPU seconds every process
of the topology spent from before the upload to the report written (``report.html``,
drawn after the job is recorded done) (psutil, sampled every 0.2 s: the service, the
scheduler, each worker), their peak resident memory (sampled), and the figures per
point, per hectare (planted area) and per tree. Beside them, ``laspy.read`` of the same
file in a fresh process on every core (:func:`bench.density.read_whole`): the job's
share of the decode rate is ``decode time / job wall time``.

``--copc PYTHON``: a Python with PDAL's bindings (``writers.copc``) converts the block to
COPC first and the job takes the ``.copc.laz`` (its tiles read their own octree nodes).
Prints Markdown.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import psutil

from bench.blocks import make_block
from bench.density import FORMS, SEED, Scanner, grown, mobile_density, planted_area, read_whole
from simulator.simparams import SimulationParams

#: seconds to wait for a role of a topology to come up
START_TIMEOUT = 120.0


def vase_block(work: Path, points_m: float):
    """The vase block at mobile density grown to about ``points_m`` million points, and its
    planted area [m²]."""
    scanner = Scanner()
    vase = next(iter(FORMS.values()))
    per_tree = scanner.points_per_tree(vase["spacing"], vase["row_spacing"])
    sim = grown(vase, max(1, round(points_m * 1e6 / per_tree)))
    params = SimulationParams(seed=SEED, density=mobile_density(vase, scanner), **sim)
    return make_block(work, f"service-vase-{points_m:g}M", params), planted_area(sim)


_COPC = """
import json, sys, pdal
pdal.Pipeline(json.dumps({"pipeline": [{"type": "readers.las", "filename": sys.argv[1]},
    {"type": "writers.copc", "filename": sys.argv[2], "forward": "all"}]})).execute()
"""


def to_copc(las: str, pdal_python: str) -> str:
    """The block as COPC beside it (made once), by PDAL's ``writers.copc``."""
    out = las[: -len(".laz")] + ".copc.laz"
    if not Path(out).exists():
        subprocess.run([pdal_python, "-c", _COPC, las, out + ".part"], check=True, timeout=7200)
        os.replace(out + ".part", out)
    return out


class Sampler:
    """Peak RSS and the last CPU times of every process of the given roots' trees, every
    ``interval`` s; the CPU a process spent is its last times minus its first."""

    def __init__(self, roots: dict[str, int], interval: float = 0.2):
        self.roots, self.interval = roots, interval
        self.peak: dict[int, int] = {}
        self.start_rss: dict[int, int] = {}
        self.peak_at: dict[int, float] = {}
        self.first: dict[int, float] = {}
        self.last: dict[int, float] = {}
        self.role: dict[int, str] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _procs(self):
        for role, pid in self.roots.items():
            try:
                root = psutil.Process(pid)
                yield from ((role if p.pid == pid else f"{role} child", p) for p in [root, *root.children(recursive=True)])
            except psutil.Error:
                continue

    def sample(self) -> None:
        for role, p in self._procs():
            try:
                with p.oneshot():
                    rss, t = p.memory_info().rss, p.cpu_times()
            except psutil.Error:
                continue
            cpu = t.user + t.system
            self.role.setdefault(p.pid, role)
            if rss > self.peak.get(p.pid, 0):
                self.peak[p.pid], self.peak_at[p.pid] = rss, time.time()
            self.start_rss.setdefault(p.pid, rss)
            self.first.setdefault(p.pid, cpu)
            self.last[p.pid] = cpu

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self.sample()

    def __enter__(self) -> "Sampler":
        self.sample()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.sample()

    def rows(self) -> list[tuple[str, int, float, int, float]]:
        """(role, peak RSS [bytes], CPU seconds, RSS when first seen [bytes], time of the
        peak [s since the epoch]) of every process seen, by role; a short-lived helper
        process (resource tracker) included."""
        out = [(self.role[p], self.peak[p], self.last[p] - self.first[p], self.start_rss[p], self.peak_at[p])
               for p in self.peak]
        return sorted(out, key=lambda r: (r[0], -r[1]))


def _start(cmd: list[str], log: Path, env: dict) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=open(log, "ab"), stderr=subprocess.STDOUT, env=env, start_new_session=True)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:  # the service first, then the workers, then the scheduler
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(10)


def _wait_for(log: Path, pattern: str, proc: subprocess.Popen) -> re.Match:
    deadline = time.monotonic() + START_TIMEOUT
    while time.monotonic() < deadline:
        m = re.search(pattern, log.read_text(errors="replace")) if log.exists() else None
        if m:
            return m
        if proc.poll() is not None:
            raise RuntimeError(f"{proc.args[:4]} exited {proc.returncode}:\n{log.read_text(errors='replace')[-3000:]}")
        time.sleep(0.2)
    raise RuntimeError(f"{proc.args[:4]} did not come up:\n{log.read_text(errors='replace')[-3000:]}")


def make_tls(folder: Path) -> dict[str, str]:
    """A CA and one certificate for every role (PEM files in ``folder``), and dask's
    configuration naming them, as docs/cluster.md's external-cluster TLS."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = dt.datetime.now(dt.timezone.utc)
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "orchard-bench")])
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - dt.timedelta(hours=1))
            .not_valid_after(now + dt.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName([x509.DNSName("localhost")]), critical=False)
            .sign(key, hashes.SHA256()))
    pem, pkey = folder / "node.pem", folder / "node-key.pem"
    pem.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    pkey.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    env = {"DASK_DISTRIBUTED__COMM__REQUIRE_ENCRYPTION": "True", "DASK_DISTRIBUTED__COMM__TLS__CA_FILE": str(pem)}
    for role in ("SCHEDULER", "WORKER", "CLIENT"):
        env[f"DASK_DISTRIBUTED__COMM__TLS__{role}__CERT"] = str(pem)
        env[f"DASK_DISTRIBUTED__COMM__TLS__{role}__KEY"] = str(pkey)
    return env


def start_topology(kind: str, folder: Path) -> tuple[str, dict[str, int], list[subprocess.Popen]]:
    """Start ``embedded`` or ``external``: the service's URL, the pids to sample by role,
    and the processes to stop (in that order)."""
    data = folder / "data"
    data.mkdir(parents=True)
    env = dict(os.environ, ORCHARD_SCHEDULING="false", ORCHARD_RUNNER_POLL_S="0.2", ORCHARD_N_WORKERS="2")
    procs, roots = [], {}
    serve = [sys.executable, "-m", "service.cli", "serve", "--data-dir", str(data), "--host", "127.0.0.1",
             "--port", "0", "--log-level", "info"]
    if kind == "external":
        env.update(make_tls(folder))
        env.pop("MALLOC_TRIM_THRESHOLD_", None)
        env.pop("MALLOC_MMAP_THRESHOLD_", None)
        # the embedded cluster's allocator settings (workers.cluster.WORKER_MALLOC_ENV), as docker/local-topology.sh
        env["DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON"] = json.dumps(
            {"MALLOC_MMAP_THRESHOLD_": "16777216", "MALLOC_TRIM_THRESHOLD_": "33554432", "OMP_NUM_THREADS": 1,
             "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1})
        sched = _start([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
                        "--protocol", "tls", "--no-dashboard"], folder / "scheduler.log", env)
        address = _wait_for(folder / "scheduler.log", r"Scheduler at:\s+(tls://\S+)", sched).group(1)
        roots["scheduler"] = sched.pid
        workers = []
        for i in range(2):
            w = _start([sys.executable, "-m", "dask", "worker", address, "--host", "127.0.0.1", "--nworkers", "1",
                        "--nthreads", "1", "--memory-limit", "2GiB", "--no-dashboard", "--name", f"bench-worker-{i}",
                        "--preload", "workers.preload",  # as docs/cluster.md tells an operator
                        "--local-directory", str(folder / f"worker-{i}")], folder / f"worker-{i}.log", env)
            roots[f"worker {i}"] = w.pid
            workers.append(w)
        for i, w in enumerate(workers):
            _wait_for(folder / f"worker-{i}.log", r"Registered to", w)
        serve += ["--scheduler", address]
        procs = [None, *reversed(workers), sched]
    srv = _start(serve, folder / "serve.log", env)
    procs[0:1] = [srv]
    roots = {"service": srv.pid, **roots}
    port = int(_wait_for(folder / "serve.log", r"listening on http://127\.0\.0\.1:(\d+)", srv).group(1))
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + START_TIMEOUT
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + "/healthz", timeout=2).json().get("cluster") == "connected":
                break
        except (httpx.HTTPError, ValueError):
            pass
        time.sleep(0.5)
    return url, roots, procs


def run_job(url: str, data: Path, las: str, timeout: float) -> tuple[dict, float]:
    """Upload ``las``, run one job with the defaults, wait for it and its report: (the job,
    with ``report_after_s``: the report seen that long after the job's end; upload seconds)."""
    token = subprocess.run([sys.executable, "-m", "service.cli", "tokens", "--data-dir", str(data), "create",
                            "--tenant", "bench"], capture_output=True, text=True, check=True).stdout.strip()
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=3600) as c:
        t = time.perf_counter()
        with open(las, "rb") as fh:
            r = c.post("/v1/blocks", files={"file": (Path(las).name, fh)})
        r.raise_for_status()
        upload = time.perf_counter() - t
        job = c.post("/v1/jobs", json={"block_id": r.json()["id"]})
        job.raise_for_status()
        jid = job.json()["id"]
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            cur = c.get(f"/v1/jobs/{jid}").json()
            if cur["state"] in ("failed", "cancelled"):
                return cur, upload
            # the report and its map are drawn after the job is recorded done: part of what is measured
            if cur["state"] == "done" and (data / "jobs" / jid / "report.html").exists():
                cur["report_after_s"] = time.time() - _epoch(cur["finished_at"])
                return cur, upload
            time.sleep(0.5)
    raise RuntimeError(f"job {jid} not done after {timeout:.0f} s")


def _epoch(iso: str) -> float:
    return dt.datetime.fromisoformat(iso.replace("Z", "+00:00")).timestamp()


def _seconds(a: str, b: str) -> float:
    return _epoch(b) - _epoch(a)


def measure(kind: str, las: str, folder: Path, timeout: float) -> dict:
    url, roots, procs = start_topology(kind, folder)
    try:
        with Sampler(roots) as sampler:
            job, upload = run_job(url, folder / "data", las, timeout)
    finally:
        _stop(procs)
    if job["state"] != "done":
        raise RuntimeError(f"the job ended {job['state']}: {job.get('error')}")
    return {"kind": kind, "job": job, "upload_s": upload, "wall_s": _seconds(job["started_at"], job["finished_at"]),
            "processes": sampler.rows()}


def report(r: dict, n_points: int, area_m2: float, decode_s: float) -> str:
    job, wall = r["job"], r["wall_s"]
    cpu = sum(p[2] for p in r["processes"])  # upload included: the service's share of it is small
    n_trees, ha = int(job["n_trees"]), area_m2 / 1e4
    lines = [f"### {r['kind']}: {n_points:,} points, {n_trees} trees, {ha:.2f} ha planted, "
             f"{job.get('tiles_total')} tiles", "",
             "| job wall [s] | share of laspy.read's rate | CPU [s] | CPU µs / point | s / ha | s / tree | upload [s] |",
             "|---:|---:|---:|---:|---:|---:|---:|",
             f"| {wall:.1f} | {100 * decode_s / wall:.1f} % | {cpu:.1f} | {1e6 * cpu / n_points:.2f} | {wall / ha:.1f} "
             f"| {wall / max(n_trees, 1):.2f} | {r['upload_s']:.1f} |", "",
             "| process | RSS before the upload [MiB] | peak RSS [MiB] | peak at [s of the job] | CPU [s] |",
             "|---|---:|---:|---:|---:|"]
    start = _epoch(job["started_at"])
    lines += [f"| {role} | {first / 2**20:,.0f} | {rss / 2**20:,.0f} | {at - start:.0f} | {c:.1f} |"
              for role, rss, c, first, at in r["processes"] if rss > 20 * 2**20]
    if job.get("report_after_s") is not None:
        lines += ["", f"report.html seen {job['report_after_s']:.1f} s after the job's end (sampled to then)"]
    if job.get("timings"):
        lines += ["", "job phases [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in job["timings"].items()
                                                     if isinstance(v, (int, float)))]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.service_throughput", description=__doc__.splitlines()[0])
    p.add_argument("--points-m", type=float, default=100.0, help="block size, millions of points (default 100)")
    p.add_argument("--topologies", default="embedded,external", help="embedded, external or both (default both)")
    p.add_argument("--copc", metavar="PYTHON", help="convert the block to COPC with this Python's PDAL and process that")
    p.add_argument("--timeout", type=float, default=7200.0, help="longest wait for a job [s] (default 7200)")
    p.add_argument("--work-dir", type=Path, default=Path(os.environ.get("ORCHARD_BENCH_WORK", "/tmp/orchard-bench")),
                   help="folder for the blocks (default /tmp/orchard-bench)")
    args = p.parse_args(argv)
    kinds = [k.strip() for k in args.topologies.split(",") if k.strip()]
    if args.points_m <= 0 or not kinds or set(kinds) - {"embedded", "external"}:
        p.error("--points-m must be positive; --topologies: embedded, external or both")
    block, area = vase_block(args.work_dir, args.points_m)
    las = to_copc(block.las, args.copc) if args.copc else block.las
    print(f"block {Path(las).name}: {block.n_points:,} points, {block.n_trees} trees, {area / 1e4:.2f} ha",
          file=sys.stderr, flush=True)
    decode_s, decode_rss = read_whole(las)
    print(f"`laspy.read` of the file (fresh process, every core): {decode_s:.2f} s, "
          f"{block.n_points / decode_s / 1e6:.2f} M points/s, peak RSS {decode_rss / 2**20:,.0f} MiB; "
          f"load average at start {os.getloadavg()[0]:.1f}\n", flush=True)
    for kind in kinds:
        with tempfile.TemporaryDirectory(prefix=f"orchard-throughput-{kind}-") as tmp:
            r = measure(kind, las, Path(tmp), args.timeout)
        print(report(r, block.n_points, area, decode_s) + f"\n\nload average after: {os.getloadavg()[0]:.1f}\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
