"""The planting layout: empty slots, replants, ragged, rotated and curved rows."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from simulator.orchard import GROUND, POST
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard
from simulator.terrain import ground_height
from synthetic_blocks import LAYOUT, SMALL


def _tree_points(o, k):
    m = o.tree_id == k
    return o.xyz[m] - o.trunks[k - 1], m


def test_missing_trees_and_replants_are_counted_exactly(gappy):
    n = len(gappy.trunks)
    assert n == 30 - 3  # round(0.1 x 30) empty slots
    assert set(np.unique(gappy.tree_id)) == set(range(n + 1))  # ids stay 1..n
    assert gappy.tree_young.sum() == 3 and len(gappy.empty_slots) == 3
    for arr in (gappy.tree_row, gappy.tree_slot, gappy.tree_young, gappy.trunk_radius):
        assert len(arr) == n
    # every slot of every row holds one tree or is empty, never both; empty slots lie between trees
    taken = {(int(r), int(s)) for r, s in zip(gappy.tree_row, gappy.tree_slot)}
    empty = {(int(r), int(s)) for r, s, _, _ in gappy.empty_slots}
    assert len(taken) == n and not taken & empty
    assert taken | empty == {(r, s) for r in (1, 2, 3) for s in range(1, 11)}
    for r, s in empty:
        row = gappy.tree_slot[gappy.tree_row == r]
        assert row.min() < s < row.max()
    # trees in row-major order: rows, then slots, ascending
    assert np.all(np.diff(gappy.tree_row * 100 + gappy.tree_slot) > 0)


def test_empty_slots_sit_on_the_grid_between_their_neighbours(gappy):
    for r, s, x, y in gappy.empty_slots:
        assert x == pytest.approx(LAYOUT.easting + (s - 1) * LAYOUT.spacing)  # no ragged rows: slot 1 at x = 0
        assert y == pytest.approx(LAYOUT.northing + (r - 1) * LAYOUT.row_spacing)
        row = gappy.tree_row == r
        for step in (-1, 1):  # a neighbour one slot away, when that slot holds a tree (jitter 0.04 m)
            nb = gappy.trunks[row & (gappy.tree_slot == s + step)]
            if len(nb):
                assert np.hypot(nb[0, 0] - x - step * LAYOUT.spacing, nb[0, 1] - y) < 0.2


def test_replants_are_much_smaller_than_their_neighbours(gappy):
    heights = np.array([_tree_points(gappy, k)[0][:, 2].max() for k in range(1, len(gappy.trunks) + 1)])
    young, old = gappy.tree_young, ~gappy.tree_young
    assert np.all(heights[young] < 0.6 * np.median(heights[old]))
    assert np.all(gappy.trunk_radius[young] < 0.6 * np.median(gappy.trunk_radius[old]))
    assert np.all(heights[young] > 0.25 * np.median(heights[old]))


def test_other_trees_stay_when_a_slot_is_emptied(gappy):
    """A tree's random stream is its slot's: the full block holds the same trees."""
    full = simulate_orchard(LAYOUT.model_copy(update={"missing": 0.0, "replants": 0.0}))
    slot = (gappy.tree_row - 1) * LAYOUT.trees_per_row + gappy.tree_slot - 1
    same = ~gappy.tree_young
    assert np.allclose(full.trunks[slot[same]], gappy.trunks[same])
    assert np.allclose(full.trunk_radius[slot[same]], gappy.trunk_radius[same])


def test_ragged_rows_lose_up_to_three_slots_at_either_end():
    from simulator.planting import make_layout

    p = SimulationParams(rows=4, trees_per_row=8, spacing=1.2, form="hedge", ragged_rows=True, seed=3,
                         density=0.02, posts=False, vehicle=False, bin=False)
    o = simulate_orchard(p)
    lengths = set()
    for r in range(1, 5):
        slots = o.tree_slot[o.tree_row == r]
        assert slots[0] == 1 and np.array_equal(slots, np.arange(1, len(slots) + 1))
        assert 2 <= len(slots) <= 8
        lengths.add(len(slots))
        # the first tree stands 0-3 slots from the grid's first slot
        x0 = o.trunks[o.tree_row == r][0, 0] - p.easting
        assert -0.5 < x0 < 3 * 1.2 + 0.5
    assert len(lengths) > 1
    cuts = set()
    for seed in range(30):
        lay = make_layout(p.model_copy(update={"seed": seed}))
        for r in range(4):
            planted = lay.col[(lay.row == r) & lay.planted]
            assert np.array_equal(planted, np.arange(planted[0], planted[-1] + 1))
            cuts |= {int(planted[0]), int(p.trees_per_row - 1 - planted[-1])}
    assert cuts == {0, 1, 2, 3}


def _rot(xy, deg):
    a = np.deg2rad(deg)
    return np.c_[np.cos(a) * xy[:, 0] - np.sin(a) * xy[:, 1], np.sin(a) * xy[:, 0] + np.cos(a) * xy[:, 1]]


def test_rotation_turns_the_whole_block_about_the_first_slot():
    p = SimulationParams(form="spindle", rows=2, trees_per_row=6, spacing=1.0, row_spacing=3.5, density=0.03, seed=2,
                         position_jitter=0.0)
    straight = simulate_orchard(p)
    turned = simulate_orchard(p.model_copy(update={"rotation": 35.0}))
    origin = np.array([p.easting, p.northing])
    assert np.allclose(_rot(straight.trunks[:, :2] - origin, 35.0) + origin, turned.trunks[:, :2], atol=1e-6)
    assert np.allclose(straight.trunks[:, 2], turned.trunks[:, 2])
    assert np.allclose(_rot(straight.xyz[:, :2] - origin, 35.0) + origin, turned.xyz[:, :2], atol=1e-6)
    assert np.array_equal(straight.tree_id, turned.tree_id)
    # each row's direction is the rotation
    for r in (1, 2):
        t = turned.trunks[turned.tree_row == r, :2]
        t = t - t.mean(axis=0)
        direction = np.linalg.svd(t, full_matrices=False)[2][0]
        azimuth = np.rad2deg(np.arctan2(direction[1], direction[0])) % 180.0
        assert abs(azimuth - 35.0) < 0.5
    # the ground turns with the block
    g = turned.kind == GROUND
    assert np.percentile(np.abs(turned.xyz[g, 2] - ground_height(turned_p := p.model_copy(update={"rotation": 35.0}),
                                                                   turned.xyz[g, 0], turned.xyz[g, 1])), 95) < 0.06
    assert turned_p.rotation == 35.0


def test_curved_rows_bow_sideways_and_keep_their_trees_whole():
    p = SimulationParams(form="spindle", rows=2, trees_per_row=9, spacing=1.0, row_spacing=3.5, density=0.03, seed=2,
                         trellis=2)
    straight = simulate_orchard(p)
    bowed = simulate_orchard(p.model_copy(update={"row_curvature": 1.0}))
    u = (straight.trunks[:, 0] - p.easting) / 8.0
    assert np.allclose(bowed.trunks[:, 1] - straight.trunks[:, 1], 4.0 * u * (1 - u), atol=1e-6)
    assert np.allclose(bowed.trunks[:, [0, 2]], straight.trunks[:, [0, 2]])
    mid = bowed.tree_slot == 5
    assert np.all(np.abs(bowed.trunks[mid, 1] - straight.trunks[mid, 1] - 1.0) < 0.05)
    # a tree moves as one rigid body: distances between its points are kept
    for k in (1, 5, 9):
        a = straight.xyz[straight.tree_id == k][:200]
        b = bowed.xyz[bowed.tree_id == k][:200]
        da = np.linalg.norm(a[:, None] - a[None], axis=2)
        db = np.linalg.norm(b[:, None] - b[None], axis=2)
        assert np.allclose(da, db, atol=1e-6)
    # the trellis follows the rows: post points near the middle of row 1 bowed by ~1 m
    post = (bowed.kind == POST) & (np.abs(bowed.xyz[:, 0] - p.easting - 4.0) < 1.2)
    row1 = np.abs(bowed.xyz[:, 1] - p.northing - 1.0) < 0.4
    assert np.count_nonzero(post & row1) > 20
    assert ground_height(p.model_copy(update={"row_curvature": 1.0}), np.array([p.easting + 4.0]),
                         np.array([p.northing + 1.0]))[0] == pytest.approx(
        ground_height(p, np.array([p.easting + 4.0]), np.array([p.northing]))[0])


def test_curvature_must_stay_gentle():
    with pytest.raises(ValidationError):
        SimulationParams(trees_per_row=5, spacing=1.0, row_curvature=1.5)
    SimulationParams(trees_per_row=5, spacing=1.0, row_curvature=-1.0)


def test_a_block_without_options_has_a_full_layout(small):
    assert np.array_equal(small.tree_row, np.repeat([1, 2], 3))
    assert np.array_equal(small.tree_slot, np.tile([1, 2, 3], 2))
    assert not small.tree_young.any() and small.empty_slots.shape == (0, 4)
    assert small.spacing == SMALL.spacing and small.row_spacing == SMALL.row_spacing


def test_the_cli_takes_the_new_options():
    import argparse

    from service.commands import simulate as cmd

    parser = argparse.ArgumentParser()
    cmd.add_arguments(parser)
    args = parser.parse_args(["--out", "b.laz", "--truth", "t.parquet", "--form", "hedge", "--spacing", "0.8",
                              "--missing", "0.1", "--replants", "0.05", "--rotation", "-20", "--row-curvature",
                              "0.5", "--ragged-rows"])
    p = cmd.params_from_args(args)
    assert (p.form, p.spacing, p.missing, p.replants, p.rotation, p.row_curvature, p.ragged_rows) == (
        "hedge", 0.8, 0.1, 0.05, -20.0, 0.5, True)
    with pytest.raises(SystemExit):
        parser.parse_args(["--out", "b.laz", "--truth", "t.parquet", "--form", "pyramid"])


_layouts = dict(
    rows=st.integers(1, 6), trees_per_row=st.integers(1, 15), missing=st.floats(0.0, 0.5),
    replants=st.floats(0.0, 0.5), ragged_rows=st.booleans(), seed=st.integers(0, 2**32 - 1),
)


@settings(max_examples=150, deadline=None)
@given(**_layouts)
def test_every_slot_is_a_tree_an_empty_slot_or_off_the_row(**kw):
    from simulator.planting import make_layout

    p = SimulationParams(**kw)
    lay = make_layout(p)
    n = p.rows * p.trees_per_row
    assert not (lay.present & ~lay.planted).any() and not (lay.young & ~lay.present).any()
    for r in range(p.rows):
        planted = np.flatnonzero(lay.planted & (lay.row == r))
        assert len(planted) >= min(2, p.trees_per_row)
        assert np.array_equal(np.diff(planted), np.ones(len(planted) - 1))  # one unbroken run
        assert lay.present[planted[0]] and lay.present[planted[-1]]  # rows end in trees
        assert np.array_equal(lay.position[planted], np.arange(1, len(planted) + 1))
        if not p.ragged_rows:
            assert len(planted) == p.trees_per_row
    inner = sum(max(np.count_nonzero(lay.planted & (lay.row == r)) - 2, 0) for r in range(p.rows))
    assert len(lay.empty) == min(round(p.missing * n), inner)
    assert np.count_nonzero(lay.young) == min(round(p.replants * n), len(lay.trees))


@settings(max_examples=100, deadline=None)
@given(rotation=st.floats(-360, 360), bow=st.floats(-1.0, 1.0), tpr=st.integers(2, 30),
       xyz=st.lists(st.tuples(st.floats(-20, 60), st.floats(-10, 40), st.floats(-2, 5)), min_size=1, max_size=20))
def test_the_block_frame_maps_back_to_the_straight_frame(rotation, bow, tpr, xyz):
    from simulator.planting import place, unplace_xy

    p = SimulationParams(trees_per_row=tpr, spacing=1.0, rotation=rotation, row_curvature=bow * 0.25 * (tpr - 1))
    pts = np.array(xyz, dtype=np.float64)
    out = place(p, pts)
    assert np.array_equal(out[:, 2], pts[:, 2])
    x, y = unplace_xy(p, out[:, 0], out[:, 1])
    assert np.allclose(np.c_[x, y], pts[:, :2], atol=1e-7)
    # a tree moves rigidly: distances between its points are kept
    tree = place(p, pts, pts[0, :2])
    d0 = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    assert np.allclose(np.linalg.norm(tree[:, None] - tree[None], axis=2), d0, atol=1e-7)
    assert np.allclose(tree[0], out[0], atol=1e-9)  # the trunk base lands where the ground under it does
