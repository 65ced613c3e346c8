"""The per-point labels streamed window by window from memory-mapped tile results: the
windows hold the right labels, and the mapped pages read do not stay resident."""

from __future__ import annotations

import re

import numpy as np

from workers.outputs import WINDOW_POINTS, Labels


def _rss_file() -> int:
    """File-backed resident memory of this process [bytes] (Linux)."""
    with open("/proc/self/status") as f:
        return int(re.search(r"RssFile:\s+(\d+) kB", f.read()).group(1)) * 1024


def _mapped_part(folder, n: int, stride: int) -> dict:
    arrays = {
        "index": np.arange(0, n * stride, stride, dtype=np.uint64),
        "tree_id": np.arange(n, dtype=np.int64) % 7,
        "is_ground": np.arange(n) % 3 == 0,
        "is_wood": np.arange(n) % 5 == 0,
        "wood_score": (np.arange(n) % 11).astype(np.float32),
    }
    part = {}
    for name, a in arrays.items():
        np.save(folder / f"{name}.npy", a)
        part[name] = np.load(folder / f"{name}.npy", mmap_mode="r")
    part["map"] = np.array([0, 10, 11, 12, 13, 14, 15])
    return part


def test_windows_hold_the_labels_and_release_the_mapped_pages(tmp_path):
    # 6 M labelled points, every second point of 12 M: 150 MB of mapped results
    n, stride = 6_000_000, 2
    labels = Labels([_mapped_part(tmp_path, n, stride)], n * stride)
    before = _rss_file()
    grown = 0
    for a in range(0, labels.n_points, WINDOW_POINTS):
        b = min(labels.n_points, a + WINDOW_POINTS)
        filled, lab = labels.window(a, b)
        pos = np.arange(a, b)
        assert np.array_equal(filled, pos % stride == 0)
        k = pos[filled] // stride
        assert np.array_equal(lab["tree_id"][filled], np.where(k % 7 == 0, 0, 9 + k % 7))
        assert np.array_equal(lab["is_ground"][filled], k % 3 == 0)
        assert not lab["tree_id"][~filled].any()
        grown = max(grown, _rss_file() - before)
    # one window's pages at a time (about 25 MB), not the 150 MB of the whole results
    assert grown < 60e6, grown / 1e6
