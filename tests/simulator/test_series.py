"""A series of captures of one generated block."""

import numpy as np

from simulator.planting import make_layout
from simulator.series import capture_series
from simulator.simparams import SimulationParams


def test_a_series_grows_cuts_replants_and_drifts_within_its_ranges():
    base = SimulationParams(rows=3, trees_per_row=10, seed=4)
    caps = capture_series(base, 5, seed=9)
    assert [c.params.scan for c in caps] == [0, 1, 2, 3, 4]
    assert caps[0].params.easting == base.easting and caps[0].cut == ()
    for a, b in zip(caps, caps[1:]):
        shift = np.hypot(b.params.easting - a.params.easting, b.params.northing - a.params.northing)
        assert 0.5 <= shift <= 2.0 and 0.5 <= abs(b.params.rotation - a.params.rotation) <= 2.0
        ratio = np.array(b.params.tree_scale) / np.array(a.params.tree_scale)
        grown = [s for s in range(base.n_trees) if s not in b.replanted]
        assert np.all((ratio[grown] >= 1.05) & (ratio[grown] <= 1.10))
        before, after = make_layout(a.params), make_layout(b.params)
        assert set(np.flatnonzero(before.present & ~after.present)) == set(b.cut)
        assert set(np.flatnonzero(~before.present & after.present)) == set(b.replanted)
        assert after.young[list(b.replanted)].all()
        assert (b.captured_at - a.captured_at).days == 45


def test_the_first_scan_is_the_block_itself():
    base = SimulationParams(seed=4)
    assert capture_series(base, 1, seed=0)[0].params.model_dump(exclude={"tree_scale"}) == base.model_dump(exclude={"tree_scale"})
