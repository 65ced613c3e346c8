"""bench.trellis: the table of trellised rows with the post test off and on."""

import math

import pytest

from bench.trellis import HEADER, Score, main, table_row


def test_table_row_totals_pooled_f1_v_measure_range_and_post_share_by_hand():
    row = table_row("s", "t", "on", [Score(8, 2, 2, 0.80, 0.5), Score(9, 1, 1, 0.84, 0.3)])
    # 17 found of 20, 3 false: F1 = 34 / (34 + 3 + 3) = 0.85; trellis points in trees (0.5 + 0.3) / 2
    assert row == "| s | t | on | 2 | 17 of 20 | 3 | 0.85 | 0.820 [0.800, 0.840] | 40 % |"
    assert row.count("|") == HEADER.splitlines()[0].count("|")


def test_a_block_without_a_trellis_has_no_share():
    row = table_row("s", "none", "off", [Score(10, 0, 0, 0.9, math.nan)])
    assert row.endswith("| – |")


@pytest.mark.parametrize("argv", [["--seeds", "0"], ["--radius", "0"], ["--radius", "2"], ["--radius", "x"]])
def test_nonsense_arguments_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert "usage:" in capsys.readouterr().err
