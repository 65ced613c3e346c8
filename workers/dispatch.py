"""The dispatch loop: run a task on every tile, on dask or in this process.

:func:`dispatch` submits one task per tile (a dask task when a client is given, else a
call in this process), feeds what happens to a :class:`workers.tilestate.TileState` and
acts on its decisions: keep a result, run a tile again, go on without it, or stop. The
job's tile stages use it: :func:`block_ground_stats`, :func:`process_tiles` and
:func:`settle_slot_trees`.
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Sized

import numpy as np

from pipeline.errors import OrchardError
from pipeline.ground import ground_stats, stats_stride
from workers.jobspec import ClusterLost, JobCancelled, JobSpec, TileFailed
from workers.slottrees import SLOT_KEY, block_slot_trees, tiles_to_run_again
from workers.tasks import ground_sample, process_tile, result_key
from workers.tilestate import Decision, TileState
from workers.workstore import JOB_KEY, WorkStore

#: Seconds without any dask worker before a job gives up instead of waiting forever.
NO_WORKER_TIMEOUT = 120.0


def check_cancel(cancel: threading.Event | None) -> None:
    if cancel is not None and cancel.is_set():
        raise JobCancelled("job cancelled")


def describe(tile: dict) -> str:
    x0, y0, x1, y1 = tile["core"]
    return f"tile {tile['id']} (core x {x0:.2f}..{x1:.2f}, y {y0:.2f}..{y1:.2f}, {tile['n_buffered']} points)"


def error_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:300]}"


def dispatch(
    task: Callable,
    tiles: list[dict],
    state: TileState,
    *,
    store: WorkStore,
    client,
    cancel: threading.Event | None,
    key: str,
    args: Callable[[int], tuple],
    stop: Callable[[dict, str], Exception],
    accept: Callable[[dict, object], object] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> TileState:
    """Run ``task(store.url, tile id, *args(tile id))`` for the tiles of ``state``.

    Parameters
    ----------
    task : callable
        A task body of :mod:`workers.tasks`.
    tiles : list of dict
        The tiles of ``state`` (index entries: ``id``, ``core``, ``n_buffered``).
    state : TileState
        Decides retries, what a failure means, and holds the results.
    store : WorkStore
    client : distributed.Client or None
        None: run the tiles one by one in this process (retried here); else one dask
        task per tile (retried by dask), the canary first.
    cancel : threading.Event, optional
        Set it to stop (raises JobCancelled).
    key : str
        Prefix of the dask task keys.
    args : callable
        The task's arguments after the tile id, per tile id.
    stop : callable
        The exception to raise when ``state`` stops the job on a tile: given the tile
        and its last error line.
    accept : callable, optional
        Checks a tile's result and returns the result to keep (it may raise an
        OrchardError, which stops the job as every OrchardError of a task does).
    progress : callable (tiles settled, tiles total), optional

    Returns
    -------
    TileState
        ``state``, every tile settled.
    """
    by_id = {t["id"]: t for t in tiles}
    accept = accept or (lambda tile, result: result)
    if progress:
        progress(0, state.total)

    def act(tid: int, decision: Decision) -> None:
        if decision is Decision.STOP:
            raise stop(by_id[tid], state.errors[tid])
        if progress and decision in (Decision.KEEP, Decision.GIVE_UP):
            progress(state.settled, state.total)

    try:
        if client is None:
            _run_here(task, by_id, state, store=store, cancel=cancel, args=args, accept=accept, act=act)
        else:
            _run_on_cluster(task, by_id, state, store=store, client=client, cancel=cancel, key=key, args=args,
                            accept=accept, act=act)
        return state
    except JobCancelled:
        state.cancel()
        raise


def _run_here(task, by_id: dict[int, dict], state: TileState, *, store: WorkStore, cancel, args, accept, act) -> None:
    """`dispatch` without a cluster: the tiles one by one in this process, retried here."""
    while (tid := state.next_tile()) is not None:
        check_cancel(cancel)
        try:
            result = accept(by_id[tid], task(store.url, tid, *args(tid)))
        except OrchardError:
            raise
        except Exception as exc:  # noqa: BLE001 - recorded per tile, as on dask
            act(tid, state.tile_failed(tid, error_line(exc)))
        else:
            act(tid, state.tile_succeeded(tid, result))


def _run_on_cluster(task, by_id: dict[int, dict], state: TileState, *, store: WorkStore, client, cancel, key: str,
                    args, accept, act) -> None:
    """`dispatch` on a cluster: one dask task per tile (retried by dask), taken as they finish.

    No more tiles are submitted than the cluster has threads, the next one as one
    finishes, in :func:`run_order`: all at once, dask would queue some behind a long tile
    on one worker, and another worker that ran out of tiles would wait for dask's work
    stealing to take one over (0.26–1.72 s in the service bench's block, docs/performance.md)."""
    token = uuid.uuid4().hex[:8]
    todo = deque(run_order(state, by_id))
    futures = {}

    def submit(running: int) -> None:
        for _ in range(min(len(todo), cluster_threads(client) - running)):
            tid = todo.popleft()
            fut = client.submit(task, store.url, tid, *args(tid), key=f"{key}-{tid}-{token}",
                                retries=state.retries, pure=False, priority=state.priority(tid))
            futures[fut] = tid

    submit(0)
    with contextlib.closing(_completed(client, futures, cancel, store, todo)) as done:
        for n_done, (tid, fut) in enumerate(done, start=1):
            submit(len(futures) - n_done)
            if fut.status == "finished":
                act(tid, state.tile_succeeded(tid, accept(by_id[tid], fut.result())))
                continue
            exc = fut.exception()
            if isinstance(exc, OrchardError):
                raise exc
            act(tid, state.tile_failed(tid, error_line(exc), attempts=state.retries + 1))


def run_order(state: TileState, by_id: dict[int, dict]) -> list[int]:
    """The order tiles are handed to a cluster: the canary first, then the largest
    (most buffered points) first, so that no long tile starts last."""
    return sorted(state.tiles, key=lambda t: (-state.priority(t), -int(by_id[t].get("n_buffered", 0)), t))


def cluster_threads(client) -> int:
    """The threads of the cluster's workers now (at least 1: a cluster without workers
    gets one tile, and :func:`_completed` waits for workers to come)."""
    return max(1, sum(client.nthreads().values()))


def block_ground_stats(store: WorkStore, tiles: list[dict], spec: JobSpec, client, cancel, n_points: int) -> list[float]:
    """The block's ground (shift, noise) from :func:`workers.tasks.ground_sample` of
    every tile; any tile that keeps failing stops the job (TileFailed)."""
    stride = stats_stride(n_points)
    params_json = spec.params.model_dump_json()
    state = TileState([t["id"] for t in tiles], partial=False)

    def stop(tile: dict, error: str) -> TileFailed:
        return TileFailed(
            f"{describe(tile)} failed after {state.retries + 1} attempts to model its ground: {error}", tile["id"]
        )

    dispatch(ground_sample, tiles, state, store=store, client=client, cancel=cancel, key="orchard-ground",
             args=lambda tid: (params_json, stride), stop=stop)
    parts = state.ordered_results()
    return list(ground_stats(np.concatenate(parts) if parts else np.zeros(0)))


def process_tiles(store: WorkStore, tiles: list[dict], spec: JobSpec, client, progress, cancel) -> tuple[list[dict], dict[int, str]]:
    """Process ``tiles`` with :func:`workers.tasks.process_tile` under the failure
    policy of :class:`workers.tilestate.TileState`.

    Returns
    -------
    (summaries in tile-id order, given-up tile → its last error line)

    Raises
    ------
    TileFailed (the canary kept failing), JobCancelled, ClusterLost, OrchardError
    """
    params_json = spec.params.model_dump_json()
    inject = set(spec.inject_failure)
    state = TileState([t["id"] for t in tiles])

    def stop(tile: dict, error: str) -> TileFailed:
        return TileFailed(
            f"{describe(tile)} failed after {state.retries + 1} attempts: {error}",
            tile["id"],
            hint=f"; its data is kept in {store.url} (run the job's tiles again with {{job.work_dir}} {store.url} "
            "{job.resume})",
        )

    dispatch(process_tile, tiles, state, store=store, client=client, cancel=cancel, key="orchard-tile",
             args=lambda tid: (params_json, tid in inject), stop=stop,
             accept=lambda tile, summary: kept(summary, store, tile), progress=progress)
    return state.ordered_results(), state.failed


def settle_slot_trees(store: WorkStore, record: dict, index: dict, summaries: list[dict], spec: JobSpec, client,
                      progress, cancel) -> tuple[list[dict], dict[int, str]]:
    """Decide the block's trees on open slots (replants and full-grown trees) from the
    tiles' summaries (:mod:`workers.slottrees`), keep them in the job record, and run
    again the tiles that let in others.

    Returns
    -------
    (every summary, the changed tiles' new ones in place; given-up tile → its last error line)
    """
    trees = block_slot_trees(summaries, spec.params)
    record[SLOT_KEY] = trees.tolist()
    store.put_json(JOB_KEY, record)
    again = tiles_to_run_again([t for t in index["tiles"] if t["n_core"] > 0], summaries, trees, index["origin"])
    if not again:
        return summaries, {}
    total = len(summaries)
    # progress goes on from where the first run ended (each tile run again counts once more)
    step = (lambda done, n: progress(total - n + done, total)) if progress else None
    for t in again:  # a tile given up now has no result, not the one made without the trees
        store.remove(result_key(t["id"]))
    new, failed = process_tiles(store, again, spec, client, step, cancel)
    by_id = {s["tile_id"]: s for s in summaries} | {s["tile_id"]: s for s in new}
    return [by_id[k] for k in sorted(by_id) if k not in failed], failed


def kept(summary: dict, store: WorkStore, tile: dict) -> dict:
    """A tile's summary, unless its task found no job in the work store: the job's store
    was deleted under it (cancelled), or, if this process still sees the job there, the
    worker that ran the tile does not see the same store."""
    if summary.get("abandoned"):
        if store.exists(JOB_KEY):
            raise TileFailed(
                f"{describe(tile)}: the dask worker that ran it does not see the job's work store {store.url}",
                tile["id"],
                hint="; every worker must reach the work store at the same address ({job.work_dir} or "
                "ORCHARD_WORK_DIR on a folder all of them share, or an fsspec URL)",
            )
        raise JobCancelled("job cancelled: its work store was deleted")
    return summary


def run_task(client, fn: Callable, *args, key: str, store: WorkStore | None = None, **kwargs):
    """``fn(*args, **kwargs)`` as one dask task on a worker of ``client`` (its key
    ``<key>-<token>``), awaited as a job's tasks are (:func:`gather`, without a cancel:
    a step that publishes outputs runs to its end); what it raises is raised here."""
    future = client.submit(fn, *args, key=f"{key}-{uuid.uuid4().hex[:8]}", pure=False, **kwargs)
    return gather(client, [future], None, store)[0]


def gather(client, futures: list, cancel, store: WorkStore | None,
           progress: Callable[[int, int], None] | None = None) -> list:
    """The results of dask ``futures`` as they finish (in that order), stopping like
    :func:`_completed` on a cancel or a cluster left without workers (``store``: the job's
    work store, None before it has one); ``progress(done, total)`` as each finishes."""
    results = []
    if progress:
        progress(0, len(futures))
    with contextlib.closing(_completed(client, dict.fromkeys(futures), cancel, store)) as done:
        for _, fut in done:
            results.append(fut.result())
            if progress:
                progress(len(results), len(futures))
    return results


def _completed(client, futures: dict, cancel, store: WorkStore | None, queued: Sized = ()):
    """Yield ``(futures[f], f)`` for each dask future ``f`` as it finishes, and then for
    the futures the caller added to ``futures`` meanwhile (``queued``: what it has still
    to add, for the count of what is left).

    Raises JobCancelled when ``cancel`` is set, and ClusterLost after NO_WORKER_TIMEOUT
    seconds without any worker; the futures still pending when it stops (or is closed)
    are cancelled.
    """
    from distributed import wait

    pending = set(futures)
    known = len(futures)

    def added() -> list:  # the futures the caller added since (the last ones of the dict)
        nonlocal known
        new, known = list(itertools.islice(reversed(futures), len(futures) - known)), len(futures)
        return new

    last_worker_seen = time.monotonic()
    last_check = 0.0
    try:
        while pending:
            check_cancel(cancel)
            try:
                res = wait(pending, timeout=0.5, return_when="FIRST_COMPLETED")
            except TimeoutError:
                now = time.monotonic()
                if now - last_check > 5.0:
                    last_check = now
                    if client.scheduler_info().get("workers"):
                        last_worker_seen = now
                    elif now - last_worker_seen > NO_WORKER_TIMEOUT:
                        # before the job has a work store there is nothing to resume from
                        raise ClusterLost(
                            f"no dask worker for {NO_WORKER_TIMEOUT:.0f} s (they died or left; their logs say why) "
                            f"with {len(pending) + len(queued)} {'tasks' if store is None else 'tiles'} to go",
                            hint="; start workers and submit the job again" if store is None
                            else f"; start workers and resume with {{job.work_dir}} {store.url} {{job.resume}}",
                        ) from None
                continue
            for fut in res.done:
                pending.discard(fut)
                yield futures[fut], fut
                pending.update(added())
    finally:
        pending.update(added())
        if pending:
            client.cancel(list(pending))
