"""Independent pieces of work side by side on the cores this process may use.

Some steps loop over items whose work releases the GIL (qhull's hull of each crown): with
a free core they run two at a time at no cost in results, which stay in the items' order.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the system has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def map_in_threads(fn: Callable[[T], R], items: Iterable[T], *, threads: int | None = None) -> list[R]:
    """``[fn(x) for x in items]``, on up to ``threads`` threads (default
    :func:`usable_cores`), in order. At most ``threads`` items are in flight, so an item
    made by a generator is held only while it is worked on. The first exception raised
    by ``fn`` is raised here."""
    threads = usable_cores() if threads is None else int(threads)
    if threads <= 1:
        return [fn(x) for x in items]
    out: list[R] = []
    pending: deque = deque()
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="pipeline") as pool:
        for x in items:
            pending.append(pool.submit(fn, x))
            if len(pending) >= threads:
                out.append(pending.popleft().result())
        while pending:
            out.append(pending.popleft().result())
    return out
