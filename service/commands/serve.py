"""``orchard serve``: the HTTP API with its job runner and schedule clock."""

from __future__ import annotations

import argparse
import contextlib
import errno
import logging
import os
import resource
import signal
import socket

from pipeline.errors import ParameterError
from service.commands.options import tiling_default
from service.permissions import UMASK

NAME = "serve"
HELP = "Run the HTTP service (API under /v1, docs at /docs) with its job runner and overnight schedules."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default=None, help="address to bind (default 127.0.0.1; env ORCHARD_HOST)")
    parser.add_argument("--port", type=int, default=None, help="port to bind (default 8000; 0: any free port; env ORCHARD_PORT)")
    parser.add_argument("--port-file", default=None, metavar="PATH",
                        help="write the port the server listens on to PATH (one line) once it accepts connections: "
                             "with --port 0, how a supervisor or a test learns it")
    parser.add_argument("--data-dir", default=None, help="job store, uploads and results (env ORCHARD_DATA_DIR)")
    parser.add_argument(
        "--scheduler", default=None, metavar="ADDR",
        help="dask scheduler address tcp://HOST:PORT (default: an embedded LocalCluster; env ORCHARD_SCHEDULER)",
    )
    parser.add_argument("--workers", type=int, default=None, help=f"workers of the embedded LocalCluster (default {tiling_default('workers')}; env ORCHARD_N_WORKERS)")
    parser.add_argument("--dashboard", action="store_true", default=None,
                        help="serve the embedded LocalCluster's dask dashboard (default off; env ORCHARD_DASHBOARD)")
    parser.add_argument("--dask-host", default=None, metavar="HOST",
                        help="address the embedded LocalCluster and its dashboard listen on (default 127.0.0.1; env ORCHARD_DASK_HOST)")
    parser.add_argument("--max-upload-mb", type=float, default=None, help="largest accepted upload [MB] (env ORCHARD_MAX_UPLOAD_MB)")
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"], help="server log level")


def bind(host: str, port: int) -> socket.socket:
    """The listening socket of the server, bound before the app starts, so that an
    address in use is said as such (`ParameterError`: exit 2, as a second runner on a
    data folder) and not as an app that failed to start."""

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # IPPROTO_TCP, not 0: asyncio sets TCP_NODELAY only on sockets that say so, and without
    # it every keep-alive response waited out the client's delayed ACK (about 40 ms)
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn: a restart binds at once
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            why = "the address is already in use (another server, or another orchard serve, listens there)"
        elif exc.errno in (errno.EACCES, errno.EPERM):
            why = "permission denied (ports below 1024 need privileges)"
        else:
            why = exc.strerror or str(exc)
        raise ParameterError(f"cannot listen on {host}:{port}: {why}; choose another with --port "
                             "(or ORCHARD_PORT), or --host") from None
    sock.set_inheritable(True)
    return sock


def write_port_file(path: str, port: int) -> None:
    """``port`` and a newline in ``path``, whole or not at all (a reader polls for the file)."""
    target = os.path.abspath(path)
    tmp = f"{target}.{os.getpid()}.tmp"
    with open(tmp, "w", encoding="ascii") as fh:
        fh.write(f"{port}\n")
    os.replace(tmp, target)


def listen_backlog() -> int:
    """The kernel's limit of a listen queue (``net.core.somaxconn``; ``listen()`` caps at
    it): a burst of connections that overflows the queue drops new ones, ``/healthz``'s
    too, and a dropped connection is tried again only after 1 s."""
    try:
        with open("/proc/sys/net/core/somaxconn", encoding="ascii") as fh:
            return int(fh.read())
    except (OSError, ValueError):
        return 4096


#: file handles kept for the job store, uploads, results and the dask cluster's sockets
FD_RESERVE = 512


def connection_cap(wanted: int) -> int:
    """``wanted`` open connections, or fewer if the process's file-handle limit (raised to
    its hard limit first) would not leave `FD_RESERVE` for the rest: past that limit
    ``accept()`` fails, and asyncio stops accepting anyone for a second each time."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or hard > soft:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard if hard != resource.RLIM_INFINITY else max(soft, 65536), hard))
            soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    return max(1, min(wanted, soft - FD_RESERVE))


def run(args: argparse.Namespace) -> int:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    import uvicorn

    from service.app import create_app, warm_routes
    from service.settings import build_settings

    settings = build_settings(
        host=args.host,
        port=args.port,
        data_dir=args.data_dir,
        scheduler=args.scheduler,
        n_workers=args.workers,
        dashboard=args.dashboard,
        dask_host=args.dask_host,
        max_upload_mb=args.max_upload_mb,
    )
    from service import logs

    logs.configure(args.log_level, log_file=settings.log_file, max_mb=settings.log_max_mb, backups=settings.log_backups)
    if args.log_level != "debug":
        logging.getLogger("distributed").setLevel(logging.WARNING)  # the cluster's own chatter

    os.umask(UMASK)  # what the service and its local workers write is the service user's alone
    if args.port_file and not os.path.isdir(os.path.dirname(os.path.abspath(args.port_file))):
        from pipeline.errors import ParameterError

        raise ParameterError(f"--port-file {args.port_file}: its folder does not exist")
    sock = bind(settings.host, settings.port)
    try:
        app = create_app(settings)
        warm_routes(app)
    except BaseException:
        sock.close()
        raise
    host, port = sock.getsockname()[:2]
    logging.getLogger("orchard.service").info("listening on http://%s:%d", f"[{host}]" if ":" in host else host, port)

    class Server(uvicorn.Server):
        def handle_exit(self, sig, frame) -> None:  # SIGTERM / Ctrl-C
            begin = getattr(app.state, "begin_shutdown", None)
            if begin is not None:
                begin()
            super().handle_exit(sig, frame)

        async def startup(self, sockets=None) -> None:
            await super().startup(sockets)
            if self.started and args.port_file:  # listening now: a reader of the file can connect at once
                write_port_file(args.port_file, port)

    from service.edge import EdgeLimits, EdgeSocket, edge_protocol

    limits = EdgeLimits(
        max_connections=connection_cap(settings.max_connections),
        max_per_client=settings.max_connections_per_client,
        header_timeout_s=settings.header_timeout_s,
        body_timeout_s=settings.body_timeout_s,
    )
    protocol = edge_protocol(limits)
    sock = EdgeSocket.wrap(sock, protocol)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=args.log_level, timeout_graceful_shutdown=10,
                            http=protocol, log_config=None,  # uvicorn's records go through service.logs
                            timeout_keep_alive=5, backlog=listen_backlog())
    server = Server(config)
    # uvicorn hands a SIGTERM on to the previous handler once it has shut down, which ended
    # the process killed by it (status 143): the stop it asked for is done, so `orchard
    # serve` ends with 0. One that comes before uvicorn listens for it stops the server too.
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: setattr(server, "should_exit", True))
    try:
        with contextlib.suppress(KeyboardInterrupt):
            server.run(sockets=[sock])
    finally:
        signal.signal(signal.SIGTERM, previous)
    if not server.started:  # the app did not start (its log says why): a failed run, not "no trees" (3)
        return 1
    return 0
