"""The per-point labels streamed window by window from the tiles' stored results: the
windows hold the right labels whatever the parts and bounds, from a local folder or any
other store, and reading them does not grow the process with the block."""

from __future__ import annotations

import re

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from workers.outputs import FENCE, WINDOW_POINTS, Labels
from workers.workstore import WorkStore


def _status(field: str) -> int:
    """A ``/proc/self/status`` figure of this process [bytes] (Linux)."""
    with open("/proc/self/status") as f:
        return int(re.search(field + r":\s+(\d+) kB", f.read()).group(1)) * 1024


def _store_parts(store: WorkStore, owner: np.ndarray, n_parts: int) -> tuple[list[dict], dict]:
    """Parts ``p`` holding the points whose owner is ``p`` (sorted index), stored as a
    tile's results are, with a local → global tree id map; and the expected labels."""
    n = len(owner)
    local = np.arange(n, dtype=np.int64) % 5  # 0: in no tree
    expected = {"tree_id": np.zeros(n, np.int64), "is_ground": np.arange(n) % 3 == 0,
                "is_wood": np.arange(n) % 7 == 0, "wood_score": (np.arange(n) % 11).astype(np.float32)}
    parts = []
    for p in range(n_parts):
        idx = np.flatnonzero(owner == p).astype(np.uint64)
        id_map = np.r_[0, 100 * (p + 1) + np.arange(1, 5)]
        expected["tree_id"][idx.astype(np.int64)] = id_map[local[idx.astype(np.int64)]]
        arrays = {"index": idx, "tree_id": local[idx.astype(np.int64)], "is_ground": expected["is_ground"][idx.astype(np.int64)],
                  "is_wood": expected["is_wood"][idx.astype(np.int64)], "wood_score": expected["wood_score"][idx.astype(np.int64)]}
        part = {}
        for name, a in arrays.items():
            store.put_array(f"results/{p:06d}/{name}.npy", a)
            part[name] = store.open_array(f"results/{p:06d}/{name}.npy")
        part["map"] = id_map
        parts.append(part)
    in_tree = expected["tree_id"] > 0
    expected["is_wood"] &= in_tree
    expected["wood_score"][~in_tree] = 0
    return parts, expected


def _check_windows(labels: Labels, expected: dict, owned: np.ndarray, bounds) -> None:
    for a, b in zip(bounds[:-1], bounds[1:]):
        filled, lab = labels.window(int(a), int(b))
        assert np.array_equal(filled, owned[a:b])
        for k, v in expected.items():
            assert np.array_equal(lab[k][filled], v[a:b][owned[a:b]]), k
        assert not lab["tree_id"][~filled].any()


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 3 * FENCE), st.integers(1, 6), st.integers(0, 2**31 - 1), st.integers(1, 2 * FENCE))
def test_windows_hold_every_part_s_labels(n, n_parts, seed, step):
    # points dealt to parts in runs (as a scanner's path crosses tiles), some to none
    rng = np.random.default_rng(seed)
    owner = np.repeat(rng.integers(-1, n_parts, size=n // 50 + 1), 50)[:n]
    store = WorkStore(f"memory://labels-{seed}-{n}-{n_parts}")
    try:
        parts, expected = _store_parts(store, owner, n_parts)
        bounds = np.unique(np.r_[0, np.arange(0, n, step), rng.integers(0, n, 3), n])
        _check_windows(Labels(parts, n), expected, owner >= 0, bounds)
    finally:
        store.remove("results")


def test_windows_from_a_folder_match_the_labels(tmp_path):
    n = 5 * FENCE + 17
    owner = np.arange(n) % 3 - (np.arange(n) % 13 == 0)  # three interleaved parts, some points in none
    parts, expected = _store_parts(WorkStore(str(tmp_path)), owner, 3)
    _check_windows(Labels(parts, n), expected, owner >= 0, np.r_[0:n:FENCE - 1, n])


def test_reading_the_windows_does_not_grow_with_the_block(tmp_path):
    # 24 tiles' results of 400,000 points each, their points interleaved along the file
    # as a scanner's path makes them: 211 MB of results, 77 MB of them indices. Every
    # window touches every part; the process may hold a window's rows, not the parts.
    n_parts, n = 24, 24 * 400_000
    owner = np.repeat(np.arange(n // 1000) % n_parts, 1000)
    parts, expected = _store_parts(WorkStore(str(tmp_path)), owner, n_parts)
    del expected
    window = 200_000
    labels = Labels(parts, n)
    with open("/proc/self/clear_refs", "w") as f:  # restart the peak (VmHWM) from now
        f.write("5")
    base = _status("VmRSS")
    for a in range(0, n, window):
        filled, _ = labels.window(a, min(n, a + window))
        assert filled.all()
    grown = _status("VmHWM") - base
    # a window's labels and rows: about 10 MB; reading whole parts would hold 77 MB or more
    assert grown < 30e6, grown / 1e6


def test_a_window_is_as_the_writers_ask():
    # the default window the writers use: a block processed whole is one in-memory part
    n = WINDOW_POINTS + 10

    class Result:
        tree_id = np.arange(n) % 4
        is_ground = np.arange(n) % 2 == 0
        is_wood = np.arange(n) % 3 == 0
        wood_score = np.linspace(0, 1, n, dtype=np.float32)

    labels = Labels.single(Result, np.array([0, 7, 8, 9]))
    filled, lab = labels.window(WINDOW_POINTS - 5, n)
    assert filled.all()
    assert np.array_equal(lab["tree_id"], np.array([0, 7, 8, 9])[np.arange(WINDOW_POINTS - 5, n) % 4])
    assert not lab["is_wood"][lab["tree_id"] == 0].any()


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 3 * FENCE), st.integers(0, 2**31 - 1), st.integers(1, 2 * FENCE))
def test_a_whole_block_s_windows_are_the_parts_windows(n, seed, step):
    # a block processed in one piece (Labels.single) takes its windows' rows as they are;
    # reference: the same labels dealt to two parts, read by the general path (copies)
    rng = np.random.default_rng(seed)
    result = type("Result", (), {})()
    result.tree_id = rng.integers(0, 6, n)
    result.is_ground = rng.random(n) < 0.3
    result.is_wood = rng.random(n) < 0.4  # also on points of no tree and of dropped trees
    result.wood_score = rng.choice(np.array([0.0, -0.0, 0.25, 1.0], np.float32), n)
    id_map = np.array([0, 3, 0, 1, 2, 0])  # trees 2 and 5 dropped
    single = Labels.single(result, id_map)
    half = n // 2
    parts = [{"index": np.arange(lo, hi, dtype=np.uint64), "tree_id": result.tree_id[lo:hi], "map": id_map,
              **{f: getattr(result, f)[lo:hi] for f in ("is_ground", "is_wood", "wood_score")}}
             for lo, hi in ((0, half), (half, n))]
    split = Labels([p for p in parts if len(p["index"])], n)
    before = {f: getattr(result, f).copy() for f in ("tree_id", "is_ground", "is_wood", "wood_score")}
    bounds = np.unique(np.r_[0, np.arange(0, n, step), rng.integers(0, n, 3), n])
    for a, b in zip(bounds[:-1], bounds[1:]):
        (f1, got), (f2, want) = single.window(int(a), int(b)), split.window(int(a), int(b))
        assert f1.all() and f2.all()
        for k in want:
            assert got[k].dtype == want[k].dtype and got[k].tobytes() == want[k].tobytes(), k
    for f, v in before.items():  # the result's own arrays are left as they were
        assert getattr(result, f).tobytes() == v.tobytes()
