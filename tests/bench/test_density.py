"""bench.density's arithmetic: the assumed scanner's points per m² and per tree, the
simulator density that reaches them, block growth, and the table's per-hectare,
per-tree and per-point figures."""

import pytest

from bench.blocks import count_points
from bench.density import (
    FORMS,
    HEADER,
    CliFailed,
    Scanner,
    block_row,
    density_table,
    grown,
    main,
    mobile_density,
    planted_area,
    read_whole,
    run_cli,
)
from simulator.simparams import SimulationParams


def test_points_per_m2_and_per_tree_by_hand():
    s = Scanner(pulse_rate=300_000, speed=1.5, return_fraction=0.5)
    # 150,000 useful points a second over 1.5 m of a 4 m alley each second
    assert s.points_per_m2(4.0) == pytest.approx(25_000)
    assert s.points_per_tree(1.35, 4.0) == pytest.approx(135_000)
    assert s.points_per_tree(5.0, 6.0) == pytest.approx(500_000)
    # twice as fast, half the points
    assert Scanner(300_000, 3.0, 0.5).points_per_m2(4.0) == pytest.approx(12_500)


def test_planted_area_counts_every_slot():
    assert planted_area(dict(rows=2, trees_per_row=3, spacing=5.0, row_spacing=6.0)) == 180.0


def test_mobile_density_reaches_the_points_per_m2():
    sim = dict(form="spindle", rows=1, trees_per_row=3, spacing=1.0, row_spacing=3.5)
    scanner = Scanner(pulse_rate=20_000, speed=1.5, return_fraction=0.5)  # small: a fast test
    density = mobile_density(sim, scanner)
    n = count_points(SimulationParams(seed=0, density=density, **sim))
    assert n / planted_area(sim) == pytest.approx(scanner.points_per_m2(3.5), rel=0.05)


@pytest.mark.parametrize("n_trees", [1, 2, 8, 40, 200])
def test_grown_blocks_have_about_the_trees_asked(n_trees):
    sim = grown(FORMS["vase 5 m × 6 m"], n_trees)
    got = sim["rows"] * sim["trees_per_row"]
    assert sim["trees_per_row"] >= 3 and got >= n_trees * 0.7
    assert got <= max(3, n_trees * 1.4)
    assert {k: v for k, v in sim.items() if k not in ("rows", "trees_per_row")} == {
        k: v for k, v in FORMS["vase 5 m × 6 m"].items() if k not in ("rows", "trees_per_row")}


def test_block_row_per_hectare_tree_and_point():
    row = {"name": "b", "n_points": 2_000_000, "n_trees": 10, "area_m2": 500.0, "wall_s": 20.0, "decode_s": 2.0,
           "decode_1core_s": 4.0, "decode_rss": 300 * 2**20, "main_maxrss": 1000 * 2**20, "children_rss": [500 * 2**20], "tiled": True}
    cells = [c.strip() for c in block_row(row).strip("|").split("|")]
    assert len(cells) == HEADER.splitlines()[0].count("|") - 1
    assert cells[:10] == ["b", "2,000,000", "10", "0.050", "4,000", "200,000", "20.0", "100", "6.7", "2.00"]
    # the decoder does 1 M points/s (0.5 on one core); end to end is a tenth of it
    assert cells[10:14] == ["1.00", "0.50", "10.0 %", "yes"]
    assert cells[14] == "1,000 + 500"
    assert float(cells[15].replace(",", "")) == pytest.approx(1000 * 2**20 / 2e6, abs=1)
    assert cells[16] == "300"


@pytest.mark.slow  # a fresh interpreter importing laspy, and a simulated block
def test_whole_file_read_reports_time_and_memory(tmp_path):
    from simulator.truth import write_simulation

    las = tmp_path / "b.laz"
    write_simulation(SimulationParams(rows=1, trees_per_row=1, density=0.05, seed=1), str(las), str(tmp_path / "t.parquet"))
    seconds, rss = read_whole(str(las))
    assert 0 < seconds < 60 and 10 * 2**20 < rss < 2**31


def test_density_table_lists_every_form():
    text = density_table(Scanner(), FORMS)
    assert text.count("\n") == 1 + len(FORMS)
    assert "| tall spindle 1.0 m × 3.5 m | 1 × 3.5 | 28,571 | 100,000 |" in text


def test_bad_assumptions_are_refused(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--return-fraction", "1.5"])
    assert e.value.code == 2
    assert "--return-fraction" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["--sizes", "1,x"])
    assert e.value.code == 2


def test_a_refused_block_is_a_row_with_the_reason(tmp_path):
    las = tmp_path / "not-a-block.laz"
    las.write_bytes(b"not a LAS file")
    with pytest.raises(CliFailed) as e:
        run_cli(str(las), tmp_path / "out")
    assert e.value.code != 0 and e.value.message
    assert block_row("| b | refused |") == "| b | refused |"
