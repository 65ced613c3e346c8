"""`create_app(settings)` served by uvicorn on a loopback port in a thread of the test
process: the app's own start (lifespan) runs, and faults can be injected into it."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

from service_fixtures import free_port

from service.app import create_app
from service.settings import Settings


@contextlib.contextmanager
def app_in_thread(settings: Settings) -> Iterator[str]:
    """Serve the app of ``settings``; yields its base URL, stops it afterwards."""
    import uvicorn

    app = create_app(settings)
    port = free_port()
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not srv.started and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert srv.started, "the app did not start"
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        srv.should_exit = True
        thread.join(30)
