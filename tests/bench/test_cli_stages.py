"""bench.cli_stages: the categories of a run add up to its whole."""

from __future__ import annotations

import pytest

from bench.cli_stages import CATEGORIES, categories


def test_categories_by_hand():
    s = {"read_points": 1.0, "read_counted": 0.5, "ground_model": 0.5, "classify_ground": 0.25, "voxelize": 0.5, "node_pairs": 0.25,
         "find_posts": 1.0, "segment_nodes": 0.5, "analyse_nodes": 3.5, "block_result": 1.0,
         "node_wood_score": 0.25, "trunk_feet": 0.25, "summarise": 0.5, "merge_and_write": 1.0,
         "write_outputs": 0.75, "write_report": 2.0, "write_trees_csv": 0.25}
    out = categories(s, start_up=1.0, total=12.5, later_imports=0.5)
    assert list(out) == list(CATEGORIES)
    assert out["start-up + imports"] == 1.0 and out["imports after start-up"] == 0.5
    assert out["read"] == 1.5 and out["ground"] == 0.75 and out["trunks and posts"] == 1.0
    assert out["other node work"] == pytest.approx(3.5 - (0.75 + 0.5 + 0.25 + 1.0 + 0.5))
    assert out["label assembly"] == pytest.approx(0.5)
    assert out["merge, trees, rows"] == pytest.approx(0.25)
    assert sum(v for k, v in out.items() if k != "total") == pytest.approx(12.5)
