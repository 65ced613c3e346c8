"""bench.shoots: the table of trunk tests against shoots touching down."""

import pytest

from bench.shoots import HEADER, VARIANTS, Score, main, table_row


def test_table_row_totals_pooled_f1_and_v_measure_range_by_hand():
    row = table_row(0.05, "x", [Score(8, 2, 2, 0.80), Score(9, 1, 1, 0.84)])
    # 17 found of 20, 3 false: F1 = 34 / (34 + 3 + 3) = 0.85
    assert row == "| 0.05 | x | 2 | 17 of 20 | 3 | 0.85 | 0.820 [0.800, 0.840] |"
    assert row.count("|") == HEADER.splitlines()[0].count("|")


def test_variants_name_real_trunk_parameters():
    from pipeline.params import TrunkParams

    for trunks in VARIANTS.values():
        TrunkParams.model_validate(trunks)  # raises on a misspelt or out-of-range field
    assert TrunkParams.model_validate(VARIANTS["neither test"]).stem_ratio == 0
    assert TrunkParams.model_validate(VARIANTS["stem test (default)"]) == TrunkParams()


@pytest.mark.parametrize("argv", [["--seeds", "0"], ["--noises", "0.5"], ["--noises", "a,b"], ["--noises", ""]])
def test_nonsense_arguments_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert "usage:" in capsys.readouterr().err
