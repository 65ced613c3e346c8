"""pipeline.graph.NodePairs.within: the pairs at most a radius long, without a copy when all are."""

from __future__ import annotations

import numpy as np

from pipeline.graph import node_pairs


def test_within_a_radius_covering_every_pair_is_the_same_pairs():
    nodes = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.3, 0, 0], [0.3, 0.05, 0]])
    pairs = node_pairs(nodes, 0.25)
    assert pairs.within(0.25) is pairs
    shorter = pairs.within(0.12)
    assert sorted(map(tuple, shorter.pairs.tolist())) == [(0, 1), (2, 3)]
    assert len(shorter) == 2 and (shorter.length <= 0.12).all()
