"""Made-up node features for pipeline.woodleaf's tests: random features of one tree's size."""

from __future__ import annotations

import numpy as np

from pipeline import woodleaf


def node_features(n: int, width: float, height: float, seed: int = 0) -> np.ndarray:
    """(n, len(FEATURES)) features: a bias column, uniform node features, the tree's width and height."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 1, (n, len(woodleaf.FEATURES)))
    x[:, 0] = 1.0
    x[:, woodleaf.NODE_FEATURES] = width
    x[:, woodleaf.NODE_FEATURES + 1] = height
    return x
