"""pipeline.woodleaf: the narrow trees' model and the blend by the tree's width and height."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline import woodleaf
from woodleaf_inputs import node_features as _features


def _wide(x):
    return 1 / (1 + np.exp(-(x @ woodleaf.COMBINED_WEIGHTS)))


def test_wide_trees_keep_the_wide_model():
    x = _features(200, width=0.6, height=4.0)  # a vase tree
    np.testing.assert_allclose(woodleaf.combined_score(x), _wide(x), atol=1e-3)


def test_tall_trees_keep_the_wide_model_however_narrow():
    x = _features(200, width=0.15, height=20.0)  # a narrow forest tree, outside the narrow model's range
    np.testing.assert_allclose(woodleaf.combined_score(x), _wide(x), atol=1e-3)


def _model(x, weights):
    return 1 / (1 + np.exp(-(woodleaf.narrow_features(x) @ weights)))


def test_narrow_orchard_trees_take_the_narrow_model():
    x = _features(200, width=0.24, height=3.0)  # a hedge: the spindles' model plays no part
    narrow = _model(x, woodleaf.NARROW_WEIGHTS)
    g = woodleaf.narrowness(np.array(0.24), np.array(3.0))  # 0.88
    np.testing.assert_allclose(woodleaf.combined_score(x), g * narrow + (1 - g) * _wide(x), atol=1e-3)
    assert not np.allclose(narrow, _wide(x), atol=0.05)


def test_the_narrowest_trees_take_the_spindles_model():
    x = _features(200, width=0.15, height=3.0)  # a tall spindle
    spindle = _model(x, woodleaf.SPINDLE_WEIGHTS)
    np.testing.assert_allclose(woodleaf.combined_score(x), spindle, atol=0.01)
    assert not np.allclose(spindle, _model(x, woodleaf.NARROW_WEIGHTS), atol=0.05)
    # all-zero spindle weights: the narrow model for every narrow tree
    got = woodleaf.combined_score(x, spindle_weights=np.zeros_like(woodleaf.SPINDLE_WEIGHTS))
    np.testing.assert_allclose(got, _model(x, woodleaf.NARROW_WEIGHTS), atol=0.01)


def test_the_blend_is_continuous_in_width():
    widths = np.linspace(0.1, 0.5, 81)
    s = np.array([woodleaf.combined_score(_features(1, w, 3.0, seed=1))[0] for w in widths])
    assert np.abs(np.diff(s)).max() < 0.1


def test_all_zero_narrow_weights_mean_the_wide_model():
    x = _features(50, width=0.15, height=3.0)
    got = woodleaf.combined_score(x, narrow_weights=np.zeros_like(woodleaf.NARROW_WEIGHTS))
    np.testing.assert_allclose(got, _wide(x))


@pytest.mark.slow
def test_the_spindles_model_finds_a_generated_spindle_rows_wood_better():
    # an evaluation seed (the models were fitted on seeds 1000+); measured 0.671 -> 0.691
    from pipeline.params import PipelineParams
    from pipeline.process import analyse_nodes
    from simulator.simparams import SimulationParams
    from simulator.simulate import simulate_orchard

    o = simulate_orchard(SimulationParams(form="spindle", rows=1, trees_per_row=10, spacing=1.0, row_spacing=3.5, seed=3))
    a = analyse_nodes(o.xyz - np.floor(o.xyz.min(axis=0)), params=PipelineParams())
    nt = a.segmentation.node_tree
    x = woodleaf.wood_features(woodleaf.path_counts(a.segmentation.paths.pred), nt, a.trunks.xy, a.vox.centroids,
                               a.node_height, a.vox.counts, a.features, a.adjacency)
    pv, tree = a.vox.point_voxel, o.tree_id[a.veg_idx] > 0
    wood = o.is_wood[a.veg_idx][tree]
    thr = PipelineParams().matter.effective_threshold()

    def f1(score):
        pred = ((score >= thr) & (nt > 0))[pv][tree]
        return 2 * (pred & wood).sum() / (pred.sum() + wood.sum())

    own = f1(woodleaf.combined_score(x))
    shared = f1(woodleaf.combined_score(x, spindle_weights=np.zeros_like(woodleaf.SPINDLE_WEIGHTS)))
    assert own > shared + 0.01, (own, shared)
