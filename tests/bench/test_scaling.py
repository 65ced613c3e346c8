"""The scaling table's block sizes: the 100 M-point block only when asked for."""

from bench.scaling import LARGE, targets


def test_default_sizes_leave_out_the_large_block_and_say_so():
    chosen, notes = targets(None, quick=False, large=False)
    assert chosen == [1_000_000, 10_000_000, 50_000_000]
    assert len(notes) == 1 and "--large" in notes[0]


def test_large_adds_the_100m_block_last():
    chosen, notes = targets(None, quick=False, large=True)
    assert chosen == [1_000_000, 10_000_000, 50_000_000, LARGE] and notes == []
    assert targets([1, 100], quick=False, large=True)[0] == [1_000_000, LARGE]  # not twice


def test_quick_runs_neither_large_block():
    chosen, notes = targets(None, quick=True, large=True)
    assert chosen == [1_000_000, 10_000_000]
    assert any("--quick" in n for n in notes) and any("--large" in n for n in notes)
