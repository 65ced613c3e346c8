"""Wood/leaf classification from shortest-path counts.

The paper's score is S = log(p) / log(p_max), p the number of shortest paths through a
node (from the trunk to every node) and p_max its maximum over the graph, thresholded
at a fixed value. Path counts are subtree sizes of the segmentation's shortest-path
forest, so they cost one linear sweep instead of one search per target.

Our method ("combined") adds what the measurements on generated orchards showed to
help: the score is normalised per tree rather than over the whole block, averaged
over a neighbourhood (a trunk wider than a voxel carries its paths down a narrow
"highway" and the smoothing spreads it over the whole stem), and combined with local
shape (branches are linear, foliage is scattered) in a fixed logistic model.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from pipeline.enrichment import ShapeFeatures
from pipeline.graph import subtree_sizes
from pipeline.params import MatterParams

PAPER_THRESHOLD = 0.216  # the threshold the paper selected on its real data

# Logistic model of the "combined" score: weights for
# [1, S_tree_smoothed, linearity, scattering, log1p(points per voxel), height_fraction].
# Fitted by `python -m bench.fit_matter` on generated orchards (seeds 1000-1005), never on
# the blocks used for evaluation.
COMBINED_WEIGHTS = np.array([-4.0, 6.0, 2.0, -2.0, 0.5, -1.0])


def path_counts(pred: np.ndarray) -> np.ndarray:
    """Number of shortest paths through each node, (m,) float64 (>= 1)."""
    return subtree_sizes(pred)


def log_score(counts: np.ndarray, group: np.ndarray | None = None) -> np.ndarray:
    """S = log(p) / log(p_max), with p_max over the whole array or per ``group``.

    Parameters
    ----------
    counts : (m,) float64, >= 1
    group : (m,) int64, optional — normalise within each group id (e.g. tree)

    Returns
    -------
    (m,) float64 in [0, 1]
    """
    lp = np.log(np.maximum(counts, 1.0))
    if group is None:
        top = lp.max() if lp.size else 1.0
        return lp / top if top > 0 else np.zeros_like(lp)
    top = np.zeros(int(group.max()) + 1 if group.size else 1)
    np.maximum.at(top, group, lp)
    denom = top[group]
    return np.where(denom > 0, lp / np.where(denom > 0, denom, 1.0), 0.0)


def smooth(values: np.ndarray, adjacency: sparse.csr_matrix) -> np.ndarray:
    """Mean of ``values`` over each node's neighbourhood (adjacency with diagonal)."""
    deg = np.asarray(adjacency.sum(axis=1)).ravel()
    return (adjacency @ values) / np.maximum(deg, 1.0)


def combined_score(
    s_tree: np.ndarray,
    features: ShapeFeatures,
    counts_per_voxel: np.ndarray,
    height_fraction: np.ndarray,
    adjacency: sparse.csr_matrix,
    *,
    weights: np.ndarray = COMBINED_WEIGHTS,
) -> np.ndarray:
    """Wood probability per node from path counts and shape.

    Parameters
    ----------
    s_tree : (m,) float64 — per-tree log path-count score
    features : ShapeFeatures
    counts_per_voxel : (m,) int64
    height_fraction : (m,) float64 — node height / height of its tree, in [0, 1]
    adjacency : (m, m) neighbourhood matrix used for smoothing

    Returns
    -------
    (m,) float64 in [0, 1]
    """
    x = np.column_stack(
        [
            np.ones_like(s_tree),
            smooth(s_tree, adjacency),
            smooth(features.linearity, adjacency),
            smooth(features.scattering, adjacency),
            np.log1p(counts_per_voxel),
            height_fraction,
        ]
    )
    return 1.0 / (1.0 + np.exp(-(x @ weights)))


def classify(
    score: np.ndarray,
    node_tree: np.ndarray,
    *,
    params: MatterParams,
) -> np.ndarray:
    """Wood mask per node: score at or above the threshold, and in a tree."""
    return (score >= params.threshold) & (node_tree > 0)
