"""End to end on generated orchards with trunks of 0.4-0.5 m radius and known truth: the
defaults and the options docs/limits.md's "Very thick trunks" names (split from
test_accuracy.py, whose conventions hold: evaluation seeds, thresholds just below the
measured values; a file of its own so that ``-n 2 --dist loadfile`` runs it beside the rest)."""

from __future__ import annotations

import pytest
from test_accuracy import PAPER_SETTING, _score

from pipeline.params import PipelineParams


def test_thick_trunks_are_trees_not_boxes():
    # bark of 0.4 m radius is flat at the features' scale and forms planar patches as
    # large as a vehicle's face; before curved patches were told apart, the box test
    # dropped one of these trees and the surface cut took 58-84 % of the lowest metre of
    # three trunks out of the graph (measured on this block: 7 of 8 trunks, v-measure 0.77)
    s = _score(PAPER_SETTING | {"trunk_radius": 0.4}, 1)
    assert s["trunk_tp"] == 8 and s["trunk_fp"] == 0, s
    assert s["v_measure"] >= 0.93, s


@pytest.mark.parametrize(
    "sim, seed, options, default_fails",
    [
        # 5 cm range noise widens a 0.8 m trunk's cross-section to 1.03 m, past the
        # default 1.0 m limit (measured on this block: 7 of 8 trunks, v-measure 0.906,
        # until a noisy mature block stopped being read as young: 8 of 8 since)
        ({"trunk_radius": 0.4, "noise": 0.05}, 1, {"max_trunk_width": 1.4}, False),
        # contacts on opposite sides of a 1 m trunk lie farther apart than the default
        # 0.8 m cluster radius and drain similar shares (measured on this block: 8 trunks
        # and 4 false ones, v-measure 0.894)
        ({"trunk_radius": 0.5}, 3, {"cluster_radius": 1.2, "max_trunk_width": 1.4}, True),
    ],
)
@pytest.mark.slow
def test_options_for_very_thick_trunks(sim, seed, options, default_fails):
    # the options docs/limits.md's "Very thick trunks" names; the defaults stay (they cost trunks
    # on noisy high-density scans)
    default = _score(PAPER_SETTING | sim, seed)
    assert (default["trunk_tp"] < 8 or default["trunk_fp"] > 0) == default_fails, default
    s = _score(PAPER_SETTING | sim, seed, params=PipelineParams.model_validate({"trunks": options}))
    assert s["trunk_tp"] == 8 and s["trunk_fp"] == 0, s
    assert s["v_measure"] >= 0.94, s
