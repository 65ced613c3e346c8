"""Tree forms: vase, tall spindle and hedgerow trees, and replants of each form."""

from __future__ import annotations

import numpy as np
import pytest

from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

SPINDLE = SimulationParams(form="spindle", rows=2, trees_per_row=5, spacing=1.0, row_spacing=3.5, density=0.25, seed=3)
HEDGE = SimulationParams(form="hedge", rows=2, trees_per_row=5, spacing=1.3, row_spacing=4.0, density=0.25, seed=3)


@pytest.fixture(scope="module")
def spindle():
    return simulate_orchard(SPINDLE)


@pytest.fixture(scope="module")
def hedge():
    return simulate_orchard(HEDGE)


def _tree_points(o, k):
    m = o.tree_id == k
    return o.xyz[m] - o.trunks[k - 1], m


def test_spindle_leaders_are_thin_and_tall(spindle):
    assert len(spindle.trunks) == SPINDLE.n_trees
    # 3-5 cm at the ground, a little thinner 0.3 m up (where the truth radius is taken)
    assert np.all((2 * spindle.trunk_radius > 0.026) & (2 * spindle.trunk_radius < 0.05))
    for k in range(1, len(spindle.trunks) + 1):
        d, _ = _tree_points(spindle, k)
        assert 2.7 < d[:, 2].max() < 3.65, k
        # the stem near the ground is one thin pole: its points hug the trunk axis
        low = (d[:, 2] > 0.1) & (d[:, 2] < 0.4)
        r = np.hypot(d[low, 0], d[low, 1])
        assert np.count_nonzero(r < 0.1) > 5, k
        assert np.mean(r < 0.07) > 0.8, k  # radius 1.5-2.5 cm, noise and ghosting around it


def test_spindle_laterals_are_short_and_trained_along_the_row(spindle):
    counts = []
    for k in range(1, len(spindle.trunks) + 1):
        d, _ = _tree_points(spindle, k)
        crown = d[d[:, 2] > 0.7]
        ax, ay = np.abs(crown[:, 0]), np.abs(crown[:, 1])
        assert 0.3 < np.percentile(ax, 98) < 0.95, k  # laterals 0.3-0.7 m (+ spurs and leaves)
        assert np.percentile(ax, 90) > 1.3 * np.percentile(ay, 90), k  # along the row more than across
        counts.append(len(d))
    # a small tree: ~10-30 k points at density 1
    assert 8_000 < np.median(counts) / SPINDLE.density < 35_000


def test_spindle_crowns_touch_along_the_row(spindle):
    p = SPINDLE
    for r in range(p.rows):
        for c in range(p.trees_per_row - 1):
            a, b = r * p.trees_per_row + c + 1, r * p.trees_per_row + c + 2
            da, _ = _tree_points(spindle, a)
            db, _ = _tree_points(spindle, b)
            gap = spindle.trunks[b - 1, 0] - spindle.trunks[a - 1, 0]
            # tree a reaches at least to the midpoint, and so does b from the other side
            assert da[:, 0].max() > 0.45 * gap and db[:, 0].min() < -0.45 * gap, (a, b)


def test_hedge_trunk_branches_low_into_a_wall(hedge):
    from simulator.forms import grow_tree

    class Flat:
        def z(self, x, y):
            return np.zeros(np.shape(x))

    for i in range(8):
        tree = grow_tree(np.random.default_rng([9, i]), HEDGE, np.zeros(2), Flat())
        # the first cylinder is the trunk: from below the ground to the branching point
        assert 0.5 <= tree.cyl_b[0, 2] <= 0.8
        assert 0.04 <= tree.cyl_ra[0] / 1.08 <= 0.06  # 8-12 cm diameter
    assert np.all((2 * hedge.trunk_radius > 0.07) & (2 * hedge.trunk_radius < 0.13))
    for k in range(1, len(hedge.trunks) + 1):
        d, m = _tree_points(hedge, k)
        assert 2.4 < d[:, 2].max() < 3.15, k
        # below the branching point only the trunk; the crown is 1-1.5 m wide across the row
        low = d[:, 2] < 0.45
        assert np.percentile(np.hypot(d[low, 0], d[low, 1]), 95) < 0.12, k
        crown = d[:, 2] > 0.9
        width = np.percentile(d[crown, 1], 98) - np.percentile(d[crown, 1], 2)
        assert 0.8 < width < 1.7, (k, width)


def test_hedge_crowns_form_a_continuous_wall(hedge):
    p = HEDGE
    tree = hedge.tree_id > 0
    for r in range(p.rows):
        row = hedge.trunks[r * p.trees_per_row : (r + 1) * p.trees_per_row]
        for a, b in zip(row[:-1], row[1:]):
            mid = 0.5 * (a + b)
            h = hedge.xyz[:, 2] - mid[2]
            at = tree & (np.abs(hedge.xyz[:, 0] - mid[0]) < 0.1) & (np.abs(hedge.xyz[:, 1] - mid[1]) < 0.6)
            for lo in (1.0, 1.5, 2.0):  # no hole between neighbours up the wall
                assert np.count_nonzero(at & (h > lo) & (h < lo + 0.5)) > 10, (r, lo)


@pytest.mark.parametrize("form, spacing", [("vase", 2.5), ("hedge", 1.3)])
def test_replants_of_every_form_are_30_to_50_percent_of_a_tree(form, spacing):
    p = SimulationParams(form=form, rows=1, trees_per_row=6, spacing=spacing, row_spacing=4.0, density=0.03,
                         replants=0.34, seed=5, posts=False, vehicle=False, bin=False, tree_height=3.0,
                         trunk_radius=0.05)
    o = simulate_orchard(p)
    assert o.tree_young.sum() == 2
    ratio = o.trunk_radius[o.tree_young] / np.median(o.trunk_radius[~o.tree_young])
    assert np.all((ratio > 0.25) & (ratio < 0.56))
    heights = np.array([_tree_points(o, k)[0][:, 2].max() for k in range(1, 7)])
    ratio = heights[o.tree_young] / np.median(heights[~o.tree_young])
