"""bench.task_timeline: each worker's idle time per stage and the tiles run again, from a task stream."""

from __future__ import annotations

from bench.task_timeline import report


def test_the_report_counts_idle_time_per_stage_and_tiles_run_again():
    tasks = [  # (start, end, key, worker) [s from the job's start]
        (0.0, 2.0, "split-range-0-/w", "a"), (0.0, 1.0, "split-range-2-/w", "b"),
        (2.5, 4.0, "orchard-ground-0-ab", "a"), (2.5, 3.0, "orchard-ground-1-ab", "b"),
        (3.5, 4.0, "orchard-ground-2-ab", "b"),
        (4.0, 9.0, "orchard-tile-0-cd", "a"), (4.0, 6.0, "orchard-tile-1-cd", "b"),
        (7.0, 8.0, "orchard-tile-2-cd", "b"), (9.5, 10.0, "orchard-tile-1-ef", "a"),
        (10.0, 11.0, "orchard-merge-gh", "a"),
    ]
    text = report({"tasks": tasks, "wall": 11.2, "thread_cpu": {"orchard-tile": (8.0, 1.5)}, "n_tiles": 3,
                   "timings": {"tile": 2.4, "total": 11.2}, "worker_cpu": {"a": 9.0, "b": 4.0}})
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in text.splitlines() if line.startswith("| ") and line.split("|")[1].strip() in
            ("split", "ground", "tiles", "merge")}
    assert rows["split"] == ["0.00", "2.00", "0.00", "1.00"]
    assert rows["ground"] == ["2.50", "4.00", "0.00", "0.50"]
    assert rows["tiles"] == ["4.00", "10.00", "0.50", "3.00"]  # a's wait for the last tile, b's gap and end
    assert "tile tasks 4 (1 run again after the slot trees)" in text
    assert "orchard-tile 8.00 (1.50)" in text and "w0 9.00, w1 4.00" in text
