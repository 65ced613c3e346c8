"""The benchmark report renders the tile-size comparison from a run's raw data."""

from bench.report import render

MACHINE = {"date": "2026-01-01 00:00 UTC", "cpu": "test CPU", "logical_cores": 2, "usable_cores": 2, "ram_gib": 1.0,
           "os": "Linux", "python": "CPython 3.11", "versions": {"numpy": "2"}}


def test_tile_size_table_by_hand():
    row = {"tile_size": 20.0, "buffer_factor": ((20 + 2 * 6.15) / 20) ** 2, "n_tiles": 10, "n_found": 51, "wall_s": 24.8,
           "cpu_s": 45.9, "points_per_s": 10_158_991 / 24.8, "worker_maxrss": [0.9 * 2**30, 0.91 * 2**30],
           "timings": {"tile": 5.6, "process": 18.5, "merge_write": 0.7}}
    data = {"machine": MACHINE, "command": "python -m bench", "elapsed_s": 60.0,
            "tiles": {"rows": [row], "workers": 2, "buffer": 6.15,
                      "block": {"n_points": 10_158_991, "n_trees": 51}}}
    text = render(data)
    assert "## Tile size" in text and "a 6.15 m buffer on every side" in text
    assert "| 20 m | 2.61 | 10 | 51 | 24.8 s | 45.9 s | 0.41 M/s | 5.6 s / 18.5 s / 0.7 s | 0.91 GiB |" in text
    assert "## Tile size" not in render({k: v for k, v in data.items() if k != "tiles"})
