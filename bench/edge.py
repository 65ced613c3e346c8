"""``python -m bench.edge``: the HTTP edge under abuse, on loopback.

``idle``: clients hold as many idle connections as they can (each sends half a request
line and headers, then nothing; a connection the server closes is opened again at
once) for ``--hold`` seconds, from their own loopback addresses (127.0.0.2, .3, ...),
while this process asks ``/healthz`` every quarter second on fresh connections from
127.0.0.1. Reports the slowest ``/healthz`` answer, how many failed, the connections
the clients opened, and how much the server's log grew.

``bodies``: ``--clients`` client processes each send 1 MB JSON bodies of many keys to
``POST /v1/jobs`` (half with a token, half without) for ``--hold`` seconds while this
process times ``/healthz``. ``quiet``: ``/healthz`` alone, the machine's baseline.

Everything is bounded: the clients stop by themselves after ``--hold`` seconds, the
server is stopped at the end, and nothing leaves loopback.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import selectors
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

PARTIAL = b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "


def raise_nofile(wanted: int) -> int:
    """Raise this process's file-handle limit towards ``wanted`` (at most its hard limit)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = min(wanted, hard) if hard != resource.RLIM_INFINITY else wanted
    if target > soft:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


def hold_idle(port: int, n: int, source: str, hold_s: float, out, reopen: bool = False, rate: float = 0.0) -> None:
    """Open ``n`` idle connections to 127.0.0.1:``port`` from ``source`` and hold them for
    ``hold_s`` s; with ``reopen``, each one the server closes is opened again at once (a
    flood of new connections, as fast as this process can make them). ``rate`` > 0 opens
    at most that many a second (0: as fast as it can)."""
    limit = raise_nofile(n + 64)
    n = min(n, limit - 64)
    sel = selectors.DefaultSelector()
    opened = refused = 0
    start = time.monotonic()
    end = start + hold_s
    live: set[socket.socket] = set()
    while time.monotonic() < end:
        while len(live) < n and (reopen or opened < n) and time.monotonic() < end \
                and (not rate or opened < rate * (time.monotonic() - start) + 1):
            s = socket.socket()
            s.setblocking(False)
            try:
                s.bind((source, 0))
                s.connect_ex(("127.0.0.1", port))
            except OSError:
                s.close()
                refused += 1
                break
            live.add(s)
            sel.register(s, selectors.EVENT_WRITE)
            opened += 1
        for key, events in sel.select(timeout=0.05):
            s = key.fileobj
            if events & selectors.EVENT_WRITE:
                try:
                    s.send(PARTIAL)
                    sel.modify(s, selectors.EVENT_READ)
                    continue
                except OSError:
                    pass
            # readable (the server answered or closed) or failed: open another in its place
            sel.unregister(s)
            s.close()
            live.discard(s)
            refused += 1
    for s in live:
        s.close()
    out.put({"source": source, "opened": opened, "closed_by_server_or_failed": refused})


def _flood_bodies(url: str, token: str | None, body: bytes, end: float, statuses: list) -> None:
    headers = {"Content-Type": "application/json", **({"Authorization": f"Bearer {token}"} if token else {})}
    with httpx.Client(base_url=url, timeout=60) as c:
        while time.monotonic() < end:
            try:
                statuses.append(c.post("/v1/jobs", content=body, headers=headers).status_code)
            except httpx.HTTPError as exc:
                statuses.append(type(exc).__name__)


class Server:
    """`orchard serve` on port 0 of 127.0.0.1 (its port read from ``--port-file``), runner off."""

    def __init__(self, root: Path, **env: str) -> None:
        self.data_dir = root / "data"
        self.log_file = root / "serve.log"
        self.port_file = root / "serve.port"
        self.env = {**os.environ, "ORCHARD_RUNNER": "false", "ORCHARD_SCHEDULING": "false",
                    "ORCHARD_LOG_FILE": str(self.log_file), **env}
        self.proc = None
        self.url = ""

    def __enter__(self) -> "Server":
        self.port_file.unlink(missing_ok=True)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--data-dir", str(self.data_dir), "--host", "127.0.0.1",
             "--port", "0", "--port-file", str(self.port_file), "--log-level", "info"],
            env=self.env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"orchard serve exited: {self.log_text()[-2000:]}")
            if self.port_file.exists():  # written once it listens
                self.url = f"http://127.0.0.1:{int(self.port_file.read_text())}"
                try:
                    if httpx.get(self.url + "/healthz", timeout=5).status_code == 200:
                        return self
                except httpx.HTTPError:
                    pass
            time.sleep(0.1)
        self.__exit__()
        raise RuntimeError(f"orchard serve did not answer /healthz: {self.log_text()[-2000:]}")

    @property
    def port(self) -> int:
        return int(self.url.rsplit(":", 1)[1])

    def log_text(self) -> str:
        return self.log_file.read_text(errors="replace") if self.log_file.exists() else ""

    def log_bytes(self) -> int:
        return sum(p.stat().st_size for p in self.log_file.parent.glob(self.log_file.name + "*"))

    def __exit__(self, *exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)


def _probe(url: str, stop: threading.Event, every_s: float = 0.25) -> list:
    """``/healthz`` latencies [s] (or the error's name) on a fresh connection each time, until ``stop``."""
    seen = []
    # one client (making one per request costs tens of ms of its own), no kept-alive
    # connection: each request connects afresh, through the same accept queue as everyone
    probe = httpx.Client(timeout=10, limits=httpx.Limits(max_keepalive_connections=0))
    while not stop.is_set():
        t0 = time.perf_counter()
        try:
            status = probe.get(url + "/healthz").status_code
            seen.append(time.perf_counter() - t0 if status == 200 else f"HTTP {status}")
        except httpx.HTTPError as exc:
            seen.append(type(exc).__name__)
        stop.wait(every_s)
    probe.close()
    return seen


def _summary(seen: list) -> dict:
    times = [s for s in seen if isinstance(s, float)]
    return {"healthz_asked": len(seen), "healthz_failed": len(seen) - len(times),
            "healthz_failures": sorted({s for s in seen if not isinstance(s, float)}),
            "healthz_median_ms": round(1000 * statistics.median(times), 1) if times else None,
            "healthz_p95_ms": round(1000 * sorted(times)[int(0.95 * (len(times) - 1))], 1) if times else None,
            "healthz_max_ms": round(1000 * max(times), 1) if times else None,
            "healthz_over_1s": sum(t > 1.0 for t in times)}


def idle(server: Server, *, connections: int, clients: int, hold_s: float, reopen: bool = False, rate: float = 0.0) -> dict:
    """Hold ``connections`` idle connections from ``clients`` loopback addresses while probing ``/healthz``."""
    log0 = server.log_bytes()
    out = mp.get_context("spawn").Queue()
    procs = [mp.get_context("spawn").Process(target=hold_idle, args=(server.port, connections // clients, f"127.0.0.{2 + i}", hold_s, out, reopen, rate))
             for i in range(clients)]
    for p in procs:
        p.start()
    stop = threading.Event()
    seen: list = []
    probe = threading.Thread(target=lambda: seen.extend(_probe(server.url, stop)))
    time.sleep(1.0)  # the clients' connections pile up first
    probe.start()
    reports = [out.get(timeout=hold_s + 120) for _ in procs]
    stop.set()
    probe.join()
    for p in procs:
        p.join(30)
    return {"connections": connections, "clients": clients, "hold_s": hold_s, "reopen": reopen,
            "rate_per_client": rate or "unlimited", **_summary(seen),
            "opened": sum(r["opened"] for r in reports),
            "closed_by_server": sum(r["closed_by_server_or_failed"] for r in reports),
            "log_growth_bytes": server.log_bytes() - log0}


def _body_client(url: str, token: str | None, hold_s: float, out) -> None:
    """One flooding client (a process of its own: its work must not slow the probe's)."""
    params = {f"k{i:06d}": 1 for i in range(60_000)}
    body = json.dumps({"block_id": "x", "params": params}).encode()
    body += b" " * max(0, 1000 * 1024 - len(body))
    statuses: list = []
    _flood_bodies(url, token, body, time.monotonic() + hold_s, statuses)
    out.put((len(body), statuses))


def bodies(server: Server, *, clients: int, hold_s: float, token: str | None) -> dict:
    """``clients`` client processes send 1 MB bodies of many keys for ``hold_s`` s
    (every other one with a token) while this process probes ``/healthz``."""
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    procs = [ctx.Process(target=_body_client, args=(server.url, token if i % 2 else None, hold_s, out))
             for i in range(clients)]
    for p in procs:
        p.start()
    stop = threading.Event()
    seen: list = []
    probe = threading.Thread(target=lambda: seen.extend(_probe(server.url, stop, every_s=0.1)))
    time.sleep(1.5)  # (the clients start)
    probe.start()
    reports = [out.get(timeout=hold_s + 120) for _ in procs]
    stop.set()
    probe.join()
    for p in procs:
        p.join(30)
    counts: dict = {}
    for _, statuses in reports:
        for s in statuses:
            counts[str(s)] = counts.get(str(s), 0) + 1
    return {"clients": clients, "body_bytes": reports[0][0], "hold_s": hold_s, **_summary(seen), "answers": counts}


def quiet(server: Server, *, hold_s: float) -> dict:
    """``/healthz`` with nothing else going on: the machine's own baseline."""
    stop = threading.Event()
    seen: list = []
    probe = threading.Thread(target=lambda: seen.extend(_probe(server.url, stop, every_s=0.1)))
    probe.start()
    time.sleep(hold_s)
    stop.set()
    probe.join()
    return {"hold_s": hold_s, **_summary(seen)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.edge", description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["idle", "bodies", "quiet"])
    p.add_argument("--connections", type=int, default=20_000, help="idle connections in all (default 20000)")
    p.add_argument("--clients", type=int, default=None, help="client processes (idle: default 2) or threads (bodies: 16)")
    p.add_argument("--reopen", action="store_true", help="idle: open a connection again as soon as the server closes it")
    p.add_argument("--rate", type=float, default=0.0, help="idle: connections a second per client (default 0: as fast as it can)")
    p.add_argument("--hold", type=float, default=45.0, help="seconds the clients keep at it (default 45)")
    args = p.parse_args(argv)
    raise_nofile(4096)
    with tempfile.TemporaryDirectory(prefix="orchard-edge-") as tmp:
        with Server(Path(tmp)) as server:
            if args.what == "quiet":
                result = quiet(server, hold_s=args.hold)
            elif args.what == "idle":
                result = idle(server, connections=args.connections, clients=args.clients or 2, hold_s=args.hold,
                              reopen=args.reopen, rate=args.rate)
            else:
                from service.auth import create_token
                from service.db.jobstore import Store

                store = Store(server.data_dir / "orchard.sqlite")
                token = create_token(store, "bench-edge")
                store.close()
                result = bodies(server, clients=args.clients or 16, hold_s=args.hold, token=token)
            print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
