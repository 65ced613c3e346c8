"""bench.stems: the plain and the solid stem fit on a generated block, against its trunks."""

from __future__ import annotations

import numpy as np

import bench.stems as stems


def test_the_stem_bench_compares_both_fits_with_the_true_trunks(monkeypatch, capsys):
    monkeypatch.setattr(stems, "SETTINGS", {"three spindles": dict(form="spindle", rows=1, trees_per_row=3, spacing=1.0,
                                                                   row_spacing=3.5, density=1.0)})
    errors = stems.errors(stems.SETTINGS["three spindles"], 0)
    assert set(errors) == {"plain", "solid"} and len(errors["plain"]) == len(errors["solid"]) == 3
    # young stems 3-4 cm thick: the plain fit took one for a 0.5 m circle, and still for a
    # 0.13 m one with the slice cut to the stem's pieces (pipeline.stemslice)
    assert np.nanmax(np.abs(errors["plain"])) > 0.08 and np.all(np.abs(errors["solid"]) < 0.05)
    stems.main(["--seeds", "0", "--settings", "three spindles"])
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| three spindles")]
    assert [r.split(" | ")[3] for r in rows] == ["plain", "solid"] and all(r.split(" | ")[2] == "3" for r in rows)
