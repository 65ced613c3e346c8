"""The dispatch loop on a cluster: tiles handed out as threads free up, the canary
first, then the largest; the failure policy holds with tiles still to hand out."""

from __future__ import annotations

import pytest

from workers.dispatch import dispatch, run_order
from workers.jobspec import TileFailed
from workers.tilestate import TileState
from workers.workstore import WorkStore


def _task(url: str, tile_id: int, fail: tuple) -> int:
    if tile_id in fail:
        raise RuntimeError(f"tile {tile_id} fails (testing)")
    return 10 * tile_id


class _Recording:
    """A client that records each tile submitted and how many of the tiles submitted
    before it were still running then."""

    def __init__(self, client):
        self.client, self.submitted = client, []

    def submit(self, fn, *args, **kwargs):
        running = sum(not f.done() for _, f in self.submitted)
        fut = self.client.submit(fn, *args, **kwargs)
        self.submitted.append(((args[1], running), fut))
        return fut

    def __getattr__(self, name):
        return getattr(self.client, name)


def _tiles(sizes: dict[int, int]) -> list[dict]:
    return [{"id": t, "core": (0.0, 0.0, 1.0, 1.0), "n_buffered": n} for t, n in sizes.items()]


def _dispatch(client, tmp_path, tiles, fail=(), partial=True):
    state = TileState([t["id"] for t in tiles], partial=partial)
    dispatch(_task, tiles, state, store=WorkStore(str(tmp_path)), client=client, cancel=None, key="test-tile",
             args=lambda tid: (tuple(fail),), stop=lambda tile, error: TileFailed(error, tile["id"]))
    return state


def test_tiles_are_handed_out_as_threads_free_up_the_canary_then_the_largest_first(dask_client, tmp_path):
    sizes = {0: 5, 1: 90, 2: 40, 3: 70, 4: 10, 5: 60, 6: 30}
    client = _Recording(dask_client)
    threads = sum(dask_client.nthreads().values())
    state = _dispatch(client, tmp_path, _tiles(sizes))
    order = [tid for (tid, _), _ in client.submitted]
    assert order == [0, 1, 3, 5, 2, 6, 4] == run_order(state, {t["id"]: t for t in _tiles(sizes)})
    assert threads == 2 and max(running for (_, running), _ in client.submitted) < threads
    assert state.finished and state.ordered_results() == [10 * t for t in sorted(sizes)]
    # a stage without a canary: the largest first
    assert run_order(TileState(sizes, partial=False), {t["id"]: t for t in _tiles(sizes)}) == [1, 3, 5, 2, 6, 4, 0]


def test_a_later_tile_that_fails_is_given_up_and_the_tiles_after_it_still_run(dask_client, tmp_path):
    sizes = {0: 5, 1: 90, 2: 40, 3: 70, 4: 10}
    state = _dispatch(_Recording(dask_client), tmp_path, _tiles(sizes), fail=(1,))
    assert state.failed.keys() == {1} and "tile 1 fails" in state.failed[1]
    assert sorted(state.results) == [0, 2, 3, 4]


def test_a_failing_canary_stops_the_job_and_no_tile_is_left_running(dask_client, tmp_path):
    client = _Recording(dask_client)
    with pytest.raises(TileFailed, match="tile 0 fails"):
        _dispatch(client, tmp_path, _tiles({0: 5, 1: 90, 2: 40, 3: 70, 4: 10, 5: 20}), fail=(0,))
    for _, fut in client.submitted:  # finished, or cancelled when the job stopped
        assert fut.status in ("finished", "error", "cancelled")
