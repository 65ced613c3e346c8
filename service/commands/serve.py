"""``orchard serve``: the HTTP API with its job runner and schedule clock."""

from __future__ import annotations

import argparse
import contextlib
import logging

NAME = "serve"
HELP = "Run the HTTP service (API under /v1, docs at /docs) with its job runner and overnight schedules."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default=None, help="address to bind (default 127.0.0.1; env ORCHARD_HOST)")
    parser.add_argument("--port", type=int, default=None, help="port to bind (default 8000; env ORCHARD_PORT)")
    parser.add_argument("--data-dir", default=None, help="job store, uploads and results (env ORCHARD_DATA_DIR)")
    parser.add_argument(
        "--scheduler", default=None, metavar="ADDR",
        help="dask scheduler address tcp://HOST:PORT (default: an embedded LocalCluster; env ORCHARD_SCHEDULER)",
    )
    parser.add_argument("--workers", type=int, default=None, help="workers of the embedded LocalCluster (default 2; env ORCHARD_N_WORKERS)")
    parser.add_argument("--max-upload-mb", type=float, default=None, help="largest accepted upload [MB] (env ORCHARD_MAX_UPLOAD_MB)")
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"], help="server log level")


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from service.app import create_app
    from service.settings import build_settings

    settings = build_settings(
        host=args.host,
        port=args.port,
        data_dir=args.data_dir,
        scheduler=args.scheduler,
        n_workers=args.workers,
        max_upload_mb=args.max_upload_mb,
    )
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.log_level != "debug":
        logging.getLogger("distributed").setLevel(logging.WARNING)  # the cluster's own chatter
    app = create_app(settings)

    class Server(uvicorn.Server):
        def handle_exit(self, sig, frame) -> None:  # SIGTERM / Ctrl-C
            begin = getattr(app.state, "begin_shutdown", None)
            if begin is not None:
                begin()
            super().handle_exit(sig, frame)

    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=args.log_level, timeout_graceful_shutdown=10)
    server = Server(config)
    with contextlib.suppress(KeyboardInterrupt):
        server.run()
    if not server.started:  # as uvicorn.run: the app did not start (e.g. its work store is unusable)
        return 3
    return 0
