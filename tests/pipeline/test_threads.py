"""Work side by side on threads: the same results, in order, with bounded items in flight."""

import threading

import numpy as np
import pytest

import pipeline.threads
from pipeline.threads import map_in_threads, usable_cores


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_results_come_in_the_items_order(threads):
    items = list(range(50))
    # later items finish first: the order must come from the items, not from completion
    out = map_in_threads(lambda x: (threading.Event().wait(0.001 * (50 - x) / 50), x * x)[1], items, threads=threads)
    assert out == [x * x for x in items]


def test_no_more_items_than_threads_are_in_flight():
    made, done, worst = [0], [0], [0]
    lock = threading.Lock()

    def items():
        for x in range(40):
            with lock:
                made[0] += 1
                worst[0] = max(worst[0], made[0] - done[0])
            yield x

    def work(x):
        threading.Event().wait(0.002)
        with lock:
            done[0] += 1
        return x

    assert map_in_threads(work, items(), threads=3) == list(range(40))
    # an item is made before it is submitted; the one just made waits for the oldest
    assert worst[0] <= 3 + 1


def test_an_error_in_the_work_is_raised():
    def work(x):
        if x == 7:
            raise ValueError("item 7")
        return x

    with pytest.raises(ValueError, match="item 7"):
        map_in_threads(work, range(20), threads=2)


def test_one_core_runs_in_the_calling_thread(monkeypatch):
    monkeypatch.setattr(pipeline.threads.os, "sched_getaffinity", lambda pid: {3}, raising=False)
    assert usable_cores() == 1
    main = threading.get_ident()
    assert map_in_threads(lambda x: threading.get_ident(), range(5)) == [main] * 5
    monkeypatch.setattr(pipeline.threads.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    assert usable_cores() == 4


def test_crown_hulls_are_the_same_on_one_core_and_on_several(monkeypatch):
    from pipeline.metrics import combine_partials, tree_partials
    from pipeline.params import MetricsParams

    rng = np.random.default_rng(5)
    n = 30_000
    xyz = rng.normal(size=(n, 3)) * [1.0, 1.0, 0.8] + [0, 0, 2.0]
    tree_id = rng.integers(0, 9, n)
    xyz[:, 0] += tree_id * 3.0
    args = (xyz, tree_id, rng.random(n) < 0.2, np.zeros(8))
    results = {}
    for cores in (1, 2):
        monkeypatch.setattr(pipeline.threads, "usable_cores", lambda cores=cores: cores)
        part = tree_partials(*args, params=MetricsParams())
        merged = combine_partials([part, part], [np.arange(9), np.r_[0, np.arange(8, 0, -1)]])
        results[cores] = (part, merged)
    for a, b in zip(results[1], results[2]):
        assert np.array_equal(a.tree_id, b.tree_id) and len(a.crown_xyz) == len(b.crown_xyz) == 8
        for x, y in zip(a.crown_xy + a.crown_xyz, b.crown_xy + b.crown_xyz):
            assert np.array_equal(x, y)
