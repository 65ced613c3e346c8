"""What `orchard process` prints: a summary and a line per row, or the tree table."""

from __future__ import annotations

import io

import numpy as np

from service.commands.printout import print_summary, print_trees


def _trees():
    return {
        "tree_id": np.array([1, 2, 3, 4]),
        "row": np.array([1, 1, 2, 3], np.int32),
        "position": np.array([1, 3, 1, 1], np.int32),
        "young": np.array([False, True, False, False]),
        "trunk_x": np.array([0.0, 2.0, 0.0, 9.0]),
        "trunk_y": np.array([0.0, 0.0, 4.0, 9.0]),
        "height_m": np.array([3.0, 1.0, 4.0, 2.0]),
        "crown_diameter_m": np.full(4, 2.0),
        "crown_area_m2": np.full(4, 3.0),
        "trunk_diameter_m": np.array([0.1, np.nan, 0.1, 0.1]),
        "n_points": np.array([10, 20, 30, 40]),
        "wood_fraction": np.full(4, 0.2),
    }


def test_summary_counts_rows_gaps_and_young_and_puts_off_row_trees_last():
    out = io.StringIO()
    # rows 1 and 2 are rows; tree 4 stands off them (a row of its own, numbered after them)
    print_summary(_trees(), {"row": [1, 2], "n_gaps": [1, 0]}, out)
    lines = out.getvalue().splitlines()
    assert lines[0] == "4 trees, 2 rows, 1 empty slots, 1 young, mean height 2.50 m"
    assert [ln.split() for ln in lines[1:]] == [
        ["row", "trees", "empty", "young", "height_m"],
        ["1", "2", "1", "1", "2.00"],
        ["2", "1", "0", "0", "4.00"],
        ["off", "rows", "1", "-", "0", "2.00"],
    ]


def test_summary_without_rows_is_one_line():
    out = io.StringIO()
    trees = {k: v for k, v in _trees().items() if k not in ("row", "position", "young")}
    print_summary(trees, None, out)
    assert out.getvalue() == "4 trees, 0 young, mean height 2.50 m\n"


def test_tree_table_puts_the_address_first_and_says_yes_or_no():
    out = io.StringIO()
    print_trees(_trees(), out)
    lines = [ln.split() for ln in out.getvalue().splitlines()]
    assert lines[0][:4] == ["row", "pos", "tree", "young"]
    assert lines[2][:4] == ["1", "3", "2", "yes"] and lines[2][9] == "nan"
    assert len(lines) == 5
