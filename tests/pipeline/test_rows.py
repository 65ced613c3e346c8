"""Rows, addresses, empty slots and replants from trunk positions (pipeline.rows)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from simulator.scoring.addresses import address_scores, gap_scores
from pipeline.rows import RowParams, find_rows


def plan(n_rows=4, per_row=20, s=1.0, r=3.5, jitter=0.05, missing=(), angle=0.0, sag=0.0, seed=0, origin=(500000.0, 6950000.0)):
    """A planting plan: trunk xy, true row and slot (1-based), and empty slots' xy.

    Rows run along x before the rotation by ``angle`` degrees (counter-clockwise);
    ``missing`` lists (row, slot) pairs left empty; ``sag`` bows every row sideways [m].
    """
    rng = np.random.default_rng(seed)
    pts, rows, slots, empty = [], [], [], []
    length = (per_row - 1) * s
    for i in range(n_rows):
        for j in range(per_row):
            x = j * s
            y = i * r + sag * (1 - ((x - length / 2) / (length / 2)) ** 2)
            if (i + 1, j + 1) in missing:
                empty.append((x, y))
                continue
            pts.append(np.array([x, y]) + rng.normal(0, jitter, 2))
            rows.append(i + 1)
            slots.append(j + 1)
    a = np.radians(angle)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    xy = np.asarray(pts) @ rot.T + np.asarray(origin)
    gaps = np.asarray(empty, dtype=np.float64).reshape(-1, 2) @ rot.T + np.asarray(origin)
    return xy, np.asarray(rows), np.asarray(slots), gaps


def addresses(layout):
    return set(zip(layout.row.tolist(), layout.position.tolist()))


def test_one_straight_row_is_numbered_from_its_western_end():
    xy = np.c_[np.arange(6) * 2.0, np.zeros(6)][::-1]  # given east to west
    lay = find_rows(xy)
    assert lay.row.tolist() == [1] * 6
    assert lay.position.tolist() == [6, 5, 4, 3, 2, 1]
    assert lay.rows["n_trees"].tolist() == [6]
    assert lay.rows["n_gaps"].tolist() == [0]
    assert lay.rows["spacing_m"][0] == pytest.approx(2.0)
    assert lay.rows["length_m"][0] == pytest.approx(10.0)
    assert lay.rows["azimuth_deg"][0] == pytest.approx(90.0)  # positions increase eastwards
    assert len(lay.gaps["row"]) == 0


def test_a_row_with_two_gaps_keeps_the_numbers_of_the_trees_after_them():
    x = np.array([0, 1, 2, 4, 5, 7, 8, 9], dtype=float)  # slots 4 and 7 (1-based) empty
    lay = find_rows(np.c_[x, np.full(len(x), 10.0)])
    assert lay.position.tolist() == [1, 2, 3, 5, 6, 8, 9, 10]
    assert lay.gaps["position"].tolist() == [4, 7]
    assert lay.gaps["row"].tolist() == [1, 1]
    np.testing.assert_allclose(lay.gaps["x"], [3.0, 6.0])
    np.testing.assert_allclose(lay.gaps["y"], [10.0, 10.0])
    assert lay.rows["n_gaps"].tolist() == [2]


def test_north_south_rows_are_numbered_west_to_east_positions_south_to_north():
    xy, true_row, true_slot, _ = plan(n_rows=3, per_row=8, s=1.5, r=4.0, jitter=0.0, angle=90.0)
    # rotated by 90°: rows run north; the simulator's row 1 lies east, its slot 1 south
    lay = find_rows(xy)
    assert lay.row.tolist() == (4 - true_row).tolist()
    assert lay.position.tolist() == true_slot.tolist()
    az = lay.rows["azimuth_deg"]
    np.testing.assert_allclose(np.minimum(az, 360.0 - az), 0.0, atol=1e-6)  # positions increase northwards


def test_east_west_rows_are_numbered_south_to_north():
    xy, true_row, true_slot, _ = plan(n_rows=3, per_row=8, jitter=0.0)
    lay = find_rows(xy)
    assert lay.row.tolist() == true_row.tolist()
    assert lay.position.tolist() == true_slot.tolist()


def test_a_curved_row_is_one_row_with_its_slots():
    xy, true_row, true_slot, _ = plan(n_rows=3, per_row=60, s=1.0, r=3.0, sag=2.5, jitter=0.03, seed=3)
    lay = find_rows(xy)
    assert len(lay.rows["row"]) == 3
    assert lay.row.tolist() == true_row.tolist()
    assert lay.position.tolist() == true_slot.tolist()
    assert lay.rows["length_m"].min() > 59.0  # along the bow, not the chord


def test_a_replant_is_young_and_keeps_its_slot():
    xy, _, true_slot, _ = plan(n_rows=2, per_row=10, jitter=0.02)
    height = np.full(len(xy), 3.2)
    height[4] = 1.1  # a replant in row 1, slot 5
    lay = find_rows(xy, height)
    assert np.flatnonzero(lay.young).tolist() == [4]
    assert lay.position[4] == true_slot[4]


def test_without_heights_no_tree_is_young():
    xy, *_ = plan(n_rows=2, per_row=10)
    assert not find_rows(xy).young.any()


def test_two_blocks_of_different_row_direction_in_one_file():
    a, ra, sa, _ = plan(n_rows=4, per_row=25, s=1.0, r=3.5, seed=1)
    b, rb, sb, _ = plan(n_rows=6, per_row=15, s=2.0, r=4.5, angle=90.0, seed=2, origin=(500060.0, 6950000.0))
    lay = find_rows(np.r_[a, b])
    true = np.r_[ra, rb + 100]
    assert len(lay.rows["row"]) == 10
    for r in np.unique(lay.row):
        assert len(np.unique(true[lay.row == r])) == 1  # no row mixes the blocks
    assert set(lay.row[: len(a)]) == {1, 2, 3, 4}  # the western block first
    az = lay.rows["azimuth_deg"]
    assert np.allclose(az[:4], 90.0, atol=3.0)
    assert np.allclose(np.minimum(az[4:], 360 - az[4:]), 0.0, atol=3.0)


@pytest.mark.parametrize("angle", [0.0, 17.0, 45.0, 90.0, 133.0, 200.0, 301.0])
def test_addresses_are_right_at_any_rotation(angle):
    missing = {(1, 5), (2, 9), (2, 10), (3, 15)}
    xy, true_row, true_slot, gaps = plan(n_rows=4, per_row=24, s=1.2, r=3.5, angle=angle, missing=missing, seed=5)
    lay = find_rows(xy)
    s = address_scores(xy, true_row, true_slot, xy, lay.row, lay.position, match_distance=0.3)
    assert s["address_accuracy"] == 1.0
    g = gap_scores(gaps, np.c_[lay.gaps["x"], lay.gaps["y"]], match_distance=0.5)
    assert (g["gap_precision"], g["gap_recall"]) == (1.0, 1.0)


@pytest.mark.parametrize("spacing,row_spacing", [(0.8, 3.0), (1.5, 3.5), (2.5, 4.5), (5.0, 6.0), (8.0, 8.5)])
def test_any_spacing(spacing, row_spacing):
    xy, true_row, true_slot, _ = plan(n_rows=4, per_row=15, s=spacing, r=row_spacing, jitter=0.04 * spacing, seed=7)
    lay = find_rows(xy)
    assert lay.row.tolist() == true_row.tolist()
    assert lay.position.tolist() == true_slot.tolist()


def test_empty_and_single_tree_blocks():
    lay = find_rows(np.zeros((0, 2)))
    assert len(lay.row) == 0 and len(lay.rows["row"]) == 0 and len(lay.gaps["row"]) == 0
    lay = find_rows(np.array([[3.0, 4.0]]))
    assert lay.row.tolist() == [1] and lay.position.tolist() == [1]


def test_params_validate():
    with pytest.raises(ValueError):
        RowParams(lateral_tolerance=0.7)


def test_address_scores_forgive_the_numbering_rule_but_not_a_shift_within_a_row():
    xy, true_row, true_slot, _ = plan(n_rows=2, per_row=5, jitter=0.0)
    # reversed rows and positions, shifted: still right
    s = address_scores(xy, true_row, true_slot, xy, 10 - true_row, 7 - true_slot, match_distance=0.3)
    assert s["address_accuracy"] == 1.0
    pos = true_slot.copy()
    pos[3:5] += 1  # the last two trees of row 1 one slot off
    s = address_scores(xy, true_row, true_slot, xy, true_row, pos, match_distance=0.3)
    assert s["n_correct"] == 8


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(0, 120),
    seed=st.integers(0, 2**16),
    scale=st.floats(0.5, 50.0),
)
def test_every_tree_has_one_address_and_no_two_share_one(n, seed, scale):
    xy = np.random.default_rng(seed).uniform(0, scale, (n, 2))
    lay = find_rows(xy, np.random.default_rng(seed + 1).uniform(0.5, 4.0, n))
    assert lay.row.dtype == np.int32 and lay.position.dtype == np.int32
    assert len(lay.row) == n
    assert np.all(lay.row >= 1) and np.all(lay.position >= 1)
    assert len(addresses(lay)) == n
    assert sorted(set(lay.row.tolist())) == list(range(1, len(lay.rows["row"]) + 1))
    assert int(lay.rows["n_trees"].sum()) == n
    gap_addr = set(zip(lay.gaps["row"].tolist(), lay.gaps["position"].tolist()))
    assert not gap_addr & addresses(lay)  # an empty slot is not a tree's slot
    assert int(lay.rows["n_gaps"].sum()) == len(gap_addr) == len(lay.gaps["row"])


@settings(max_examples=25, deadline=None)
@given(angle=st.floats(0, 360), dx=st.floats(-1e4, 1e4), dy=st.floats(-1e4, 1e4), seed=st.integers(0, 1000))
def test_addresses_do_not_depend_on_the_order_of_the_trees(angle, dx, dy, seed):
    xy, *_ = plan(n_rows=3, per_row=12, angle=angle, seed=seed, origin=(500000.0 + dx, 6950000.0 + dy))
    lay = find_rows(xy)
    perm = np.random.default_rng(seed).permutation(len(xy))
    lay2 = find_rows(xy[perm])
    assert lay2.row.tolist() == lay.row[perm].tolist()
    assert lay2.position.tolist() == lay.position[perm].tolist()


def test_candidates_on_open_slots():
    from pipeline.slots import on_open_slot

    xy, _, _, gaps = plan(n_rows=3, per_row=12, s=1.0, r=3.5, jitter=0.0, missing={(2, 6)})
    cands = np.array([
        gaps[0] + [0.1, 0.05],          # on the empty slot: a replant
        xy[3] + [0.5, 0.0],             # between two trees of a row, no empty slot there
        xy[5] + [0.0, 1.75],            # half-way between rows 1 and 2
        xy[0] + [-1.0, 0.05],           # the slot beyond the west end of row 1
        xy[0] + [-3.0, 0.0],            # farther beyond: no slot
    ])
    slot = on_open_slot(xy, cands)
    assert (slot >= 0).tolist() == [True, False, False, True, False]
    assert slot[0] != slot[3]


def test_on_open_slot_without_rows_judges_nothing():
    from pipeline.slots import on_open_slot

    assert (on_open_slot(np.array([[0.0, 0.0], [5.0, 0.0]]), np.array([[2.5, 0.0]])) == -1).all()


def test_a_false_trunk_between_rows_does_not_renumber_the_rows():
    xy, true_row, true_slot, _ = plan(n_rows=3, per_row=10, s=2.5, r=4.5, jitter=0.03)
    false = xy[14] + [0.3, 1.3]  # foliage of row 2 touching down 1.3 m off its line
    lay = find_rows(np.r_[xy, [false]])
    assert lay.row[:-1].tolist() == true_row.tolist()
    assert lay.position[:-1].tolist() == true_slot.tolist()
    assert lay.off_row.tolist() == [False] * len(xy) + [True]
    assert lay.between_rows.tolist() == [False] * len(xy) + [True]
    assert lay.row[-1] == 4 and lay.position[-1] == 1  # a row of its own, after the rows


def test_a_lone_tree_beyond_the_rows_is_not_between_them():
    xy, true_row, _, _ = plan(n_rows=3, per_row=10, s=2.5, r=4.5, jitter=0.03)
    lone = np.array([[xy[:, 0].mean(), xy[:, 1].max() + 12.0]])  # a tree by the farm track
    lay = find_rows(np.r_[xy, lone])
    assert not lay.between_rows[-1]
    assert lay.row[:-1].tolist() == true_row.tolist() and lay.row[-1] == 4  # a row of its own


def test_a_false_trunk_just_beyond_an_outer_row_goes_like_one_between_rows():
    xy, true_row, _, _ = plan(n_rows=3, per_row=10, s=2.5, r=4.5, jitter=0.03)
    near = xy[25] + [0.4, 1.3]   # foliage of the outer row 3 touching down on the alley side
    lay = find_rows(np.r_[xy, [near]])
    assert lay.row[:-1].tolist() == true_row.tolist()
    assert lay.off_row[-1] and lay.between_rows[-1]
    far = xy[25] + [0.4, 3.5]    # 0.78 row spacings out: could be the start of a row
    lay = find_rows(np.r_[xy, [far]])
    assert not lay.between_rows[-1] and lay.row[-1] == 4


def test_a_second_trunk_in_one_slot_is_off_the_row():
    xy, true_row, true_slot, _ = plan(n_rows=2, per_row=12, s=1.5, r=3.5, jitter=0.02)
    twin = xy[5] + [0.15, 0.05]  # a split trunk, a sucker
    lay = find_rows(np.r_[xy, [twin]])
    assert lay.off_row.sum() == 1
    assert len(set(zip(lay.row.tolist(), lay.position.tolist()))) == len(xy) + 1
    assert lay.row[:-1].tolist() == true_row.tolist() or lay.off_row[5]


def test_a_long_empty_stretch_is_no_run_of_empty_slots():
    x = np.r_[np.arange(10) * 1.0, 30.0 + np.arange(5) * 1.0]  # 20 m without trees (a road)
    lay = find_rows(np.c_[x, np.zeros(len(x))])
    assert len(lay.rows["row"]) == 1
    assert lay.position.tolist() == list(range(1, 11)) + list(range(31, 36))
    assert len(lay.gaps["row"]) == 0  # more than max_gap_slots empty: not reported as gaps


def test_trunks_between_rows_give_their_material_to_the_nearest_tree():
    from pipeline.merge import GlobalTrunks
    from pipeline.params import PipelineParams
    from workers.outputs import without_trunks_between_rows

    xy, *_ = plan(n_rows=3, per_row=6, s=2.5, r=4.5, jitter=0.0, origin=(0.0, 0.0))
    false = xy[8] + [0.2, 1.3]
    trunks = np.c_[np.r_[xy, [false]], np.zeros(len(xy) + 1)]
    k = len(trunks)
    merged = GlobalTrunks(trunks, np.full(k, 0.1), np.ones(k), np.zeros(k, np.int64), {0: np.arange(k + 1)})
    out = without_trunks_between_rows(merged, PipelineParams())
    assert out.n_trees == k - 1
    assert out.id_maps[0].tolist() == list(range(k)) + [9]  # the false tree's points → tree 9 (xy[8])
    off = without_trunks_between_rows(merged, PipelineParams(rows={"drop_between_rows": False}))
    assert off is merged


def test_a_gap_centre_is_fitted_to_the_row_not_to_its_two_neighbours():
    # slot 5 (0-based 4) empty; the tree before it stands 0.4 m off the row line, the
    # others on it: the straight line between the two neighbours would put the slot
    # 0.2 m off, the row's fit much nearer the line
    from pipeline.rows import slot_centres

    slots = np.array([0, 1, 2, 3, 5, 6, 7, 8])
    line = np.c_[slots * 2.0, np.zeros(len(slots))]
    line[3, 1] = 0.4
    centre = slot_centres(slots, line, [4], spacing=2.0)[0]
    assert centre[0] == pytest.approx(8.0, abs=0.05)
    assert abs(centre[1]) < 0.15  # the neighbours' midpoint: 0.2


def test_slot_centres_follow_a_curved_row_and_step_on_beyond_its_ends():
    from pipeline.rows import slot_centres

    # trees on a circle of 40 m radius, 2 m apart, slot 6 empty
    angle = np.arange(12) * 2.0 / 40.0
    ring = np.c_[40.0 * np.sin(angle), 40.0 * (1.0 - np.cos(angle))]
    slots = np.r_[np.arange(6), np.arange(7, 12)]
    got = slot_centres(slots, ring[slots], [6, 12, -1], spacing=2.0)
    assert np.hypot(*(got[0] - ring[6])) < 0.02  # on the curve, not its chord's sagitta off
    beyond = np.c_[40.0 * np.sin([12 * 0.05, -0.05]), 40.0 * (1.0 - np.cos([12 * 0.05, -0.05]))]
    from pipeline.slots import SLOT_REACH

    assert np.hypot(*(got[1:] - beyond).T).max() < SLOT_REACH * 2.0  # a tree there is let in
    # a step of the row's spacing from its end tree
    assert np.hypot(*(got[1] - ring[11])) == pytest.approx(2.0, abs=0.05)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), angle=st.floats(0.0, 2 * np.pi))
def test_slot_centres_average_out_the_trees_jitter(seed, angle):
    # a straight row at any angle, trees jittered 0.15 m about their slots: the fitted
    # centre of an empty inner slot lies nearer its true centre than the jitter allows
    # the midpoint of its two neighbours to, on average over the row's gaps
    from pipeline.rows import slot_centres

    rng = np.random.default_rng(seed)
    u = np.array([np.cos(angle), np.sin(angle)])
    all_slots = np.arange(20)
    true = all_slots[:, None] * 2.5 * u
    empty = np.array([5, 11, 15])
    slots = np.setdiff1d(all_slots, empty)
    line = true[slots] + rng.normal(0.0, 0.15, (len(slots), 2))
    got = slot_centres(slots, line, empty, spacing=2.5)
    err = np.hypot(*(got - true[empty]).T)
    assert err.max() < 0.45  # six sigma of a mean of at least four trees
    assert np.isfinite(got).all()


def test_trees_of_a_stand_without_evident_rows_are_never_between_rows():
    # a stand planted 2.2 m x 2.5 m with 0.3 m of scatter: a tree 0.5 m off its line is one
    # of the stand's, not foliage touching down in an alley
    rng = np.random.default_rng(3)
    stand = np.array([[i * 2.2, j * 2.5] for j in range(6) for i in range(6)]) + rng.normal(0, 0.3, (36, 2))
    assert not find_rows(stand).between_rows.any()
    # an orchard planted to its lines keeps the prior: a trunk in the alley is flagged
    orchard = np.array([[i * 2.5, j * 4.5] for j in range(3) for i in range(8)]) + rng.normal(0, 0.05, (24, 2))
    flagged = find_rows(np.r_[orchard, [[8.8, 2.3]]]).between_rows
    assert flagged[-1] and not flagged[:-1].any()
