"""bench.overlap: the crown-radius sweep's block scoring and table."""

import pytest

from bench.overlap import HEADER, BlockScore, score_block, table_rows
from pipeline.params import PipelineParams


def test_table_rows_mean_and_range_per_ratio_by_hand():
    blocks = [
        BlockScore(0.5, 0, 0.01, 1.0, 0.97, 0.96),
        BlockScore(0.5, 1, 0.03, 0.9, 0.95, 0.94),
        BlockScore(0.4, 0, 0.0, 1.0, 0.99, 0.99),
    ]
    rows = table_rows("s", blocks)
    assert rows == [
        "| s | 0.40 | 1 | 0.0 % | 1.00 [1.00, 1.00] | 0.990 [0.990, 0.990] | 0.990 [0.990, 0.990] |",
        "| s | 0.50 | 2 | 2.0 % | 0.95 [0.90, 1.00] | 0.960 [0.950, 0.970] | 0.950 [0.940, 0.960] |",
    ]
    assert all(r.count("|") == HEADER.splitlines()[0].count("|") for r in rows)


def test_wider_crowns_reach_further_past_the_midpoint():
    # the same small generated row with narrow and wide crowns: the simulator honours the
    # radius, so more of the wide crowns lies on the neighbour's side
    sim = dict(rows=1, trees_per_row=3, spacing=4.0, density=0.3)
    narrow = score_block(sim, 0.4, 3, PipelineParams())
    wide = score_block(sim, 0.65, 3, PipelineParams())
    assert narrow.beyond_midpoint < 0.01 < wide.beyond_midpoint
    for b in (narrow, wide):
        assert 0.0 <= b.v_measure <= 1.0 and 0.0 <= b.v_measure_closest <= 1.0
        assert b.trunk_f1 == pytest.approx(1.0)
    assert narrow.v_measure > wide.v_measure
