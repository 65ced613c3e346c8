"""Open planting slots and the trees let in on them (pipeline.slots)."""

from __future__ import annotations

import numpy as np

from pipeline.params import PipelineParams
from pipeline.slots import rescue_on_open_slots
from pipeline.trunks import TrunkDetection


def _detection(trunks, cands):
    """Trunks of a row at 1 m with sources one node each, and rejected candidates."""
    k = len(trunks)
    nodes = np.c_[np.r_[trunks, cands[:, :2]], np.full(k + len(cands), 0.05)]
    cand = {
        "x": cands[:, 0], "y": cands[:, 1], "top": cands[:, 2], "support": np.full(len(cands), 80.0),
        "planar": np.zeros(len(cands)), "width": np.full(len(cands), 0.2), "accepted": np.zeros(len(cands), bool),
        "fits": cands[:, 2] >= PipelineParams().trunks.min_tree_height, "foot": np.ones(len(cands)),
    }
    det = TrunkDetection(trunks, np.full(k, 500.0), np.full(k, 0.2), np.arange(k), np.arange(k), cand, 1.0)
    return det, nodes


def test_a_low_tree_on_an_empty_slot_is_a_replant_and_others_are_not():
    row = np.array([[x, 0.0] for x in (0, 1, 2, 4, 5, 6, 7, 9, 10)], dtype=float)  # slots 4 and 9 empty
    cands = np.array([
        [3.05, 0.02, 1.2],   # on the empty slot 4, 1.2 m tall: a replant
        [8.0, 0.0, 0.3],     # on the empty slot 9 but grass-high
        [5.5, 0.0, 1.2],     # between two trees: no slot
        [11.02, 0.0, 1.0],   # the slot beyond the row's east end: a replant
        [3.1, 0.9, 1.3],     # beside the row
    ])
    det, nodes = _detection(row, cands)
    out = rescue_on_open_slots(det, nodes, np.full(len(nodes), 0.05), contact_top=0.1, params=PipelineParams())
    assert out.k == det.k + 2
    np.testing.assert_allclose(out.xy[out.young], [[3.05, 0.02], [11.02, 0.0]])
    assert set(out.source_trunk[out.source_nodes >= det.k].tolist()) == {det.k, det.k + 1}


def test_nothing_is_rescued_with_rows_off_or_too_few_trees():
    row = np.array([[x, 0.0] for x in (0, 1, 2, 4, 5)], dtype=float)
    det, nodes = _detection(row, np.array([[3.0, 0.0, 1.2]]))
    off = PipelineParams(rows={"enabled": False})
    assert rescue_on_open_slots(det, nodes, np.full(len(nodes), 0.05), contact_top=0.1, params=off) is det
    det2, nodes2 = _detection(row[:2], np.array([[3.0, 0.0, 1.2]]))
    assert rescue_on_open_slots(det2, nodes2, np.full(len(nodes2), 0.05), contact_top=0.1, params=PipelineParams()) is det2
