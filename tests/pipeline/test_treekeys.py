"""Tree keys, statuses and addresses of a capture against the block's state."""

import numpy as np

from pipeline.coverage import Coverage, occupied_cells
from pipeline.registration import RigidTransform
from pipeline.treekeys import BlockState, Trees, assign_keys, first_keys, match_trees

IDENTITY = RigidTransform(0.0, 0.0, 0.0, 0.0, 0.0)


def _trees(xy, row, pos, height=None, trunk=None):
    n = len(xy)
    return Trees(np.asarray(xy, float), np.asarray(row), np.asarray(pos),
                 np.full(n, 3.0) if height is None else np.asarray(height, float), np.full(n, 2.0),
                 np.full(n, 0.04) if trunk is None else np.asarray(trunk, float))


def _state(n_per_row=6, rows=2):
    r, c = np.divmod(np.arange(rows * n_per_row), n_per_row)
    trees = _trees(np.c_[c * 1.5, r * 4.0], r + 1, c + 1)
    n = len(r)
    return BlockState("a", "2025-03-01", np.arange(1, n + 1) * 10, trees, np.full(n, "a", object),
                      np.full(n, "2025-03-01", object), np.zeros((0, 2), np.int64), 1000)


def test_first_capture_keys_follow_tree_ids():
    k = first_keys(_trees(np.zeros((3, 2)), [1, 1, 1], [1, 2, 3]))
    assert k.key.tolist() == [1, 2, 3] and set(k.status) == {"new"} and k.next_key == 4


def test_matching_is_one_to_one():
    prev = np.array([[0.0, 0.0], [1.0, 0.0]])
    cur = np.array([[0.45, 0.0], [0.55, 0.0], [5.0, 5.0]])
    assert sorted(match_trees(cur, prev, 0.6).tolist()) == [-1, 0, 1]


def test_a_removed_a_new_and_a_replanted_tree():
    state = _state()
    keep = np.ones(12, bool)
    keep[[2, 8]] = False  # both cut; slot 8 (row 2, position 3) replanted with a young tree
    xy = state.trees.xy[keep]
    # this capture numbers its rows from the other end and misses row 1's first tree: its own
    # positions are shifted, which the block's addresses must not be
    keep[0] = False
    xy = state.trees.xy[keep]
    row = np.where(state.trees.row[keep] == 1, 2, 1)
    pos = state.trees.position[keep] - np.where(state.trees.row[keep] == 1, 1, 0)
    young_xy = state.trees.xy[[8]] + [0.05, 0.0]
    new_xy = [[9.0, 4.0]]  # a tree planted beyond row 2's end, slot 7
    cur = _trees(np.r_[xy, young_xy, new_xy], np.r_[row, [1], [1]], np.r_[pos, [3], [7]],
                 height=np.r_[np.full(len(xy), 3.2), [1.2], [1.1]], trunk=np.r_[np.full(len(xy), 0.045), [0.015], [0.01]])
    covered = np.ones(12, bool)
    covered[0] = False  # row 1's first tree: this capture did not see its ground
    k = assign_keys(cur, state, transform=IDENTITY, gate=0.5, covered=covered)
    n = len(xy)
    assert k.key[:n].tolist() == state.key[keep].tolist()
    assert k.row[:n].tolist() == state.trees.row[keep].tolist()
    assert k.position[:n].tolist() == state.trees.position[keep].tolist()
    assert k.status[n] == "replanted" and (k.row[n], k.position[n]) == (2, 3)
    assert k.status[n + 1] == "new" and (k.row[n + 1], k.position[n + 1]) == (2, 7)
    assert k.key[n:].tolist() == [1000, 1001] and k.next_key == 1002
    assert state.key[k.removed].tolist() == [30, 90]  # slots 2 and 8
    assert state.key[k.unseen].tolist() == [10]  # not covered: kept, not removed


def test_a_tree_cut_and_replanted_between_two_captures():
    state = _state()
    cur = _trees(state.trees.xy, state.trees.row, state.trees.position, height=np.r_[np.full(11, 3.2), [1.1]],
                 trunk=np.r_[np.full(11, 0.045), [0.015]])
    k = assign_keys(cur, state, transform=IDENTITY, gate=0.5, covered=np.ones(12, bool))
    assert k.status[-1] == "replanted" and k.key[-1] == 1000
    assert state.key[k.removed].tolist() == [120]


def test_half_coverage_removes_nothing_outside():
    state = _state(n_per_row=10)
    half = state.trees.xy[:, 0] < 7.0
    cells = occupied_cells(np.mgrid[-3:7:0.5, -3:8:0.5].reshape(2, -1).T, (0.0, 0.0))
    covered = Coverage.from_cells(cells).covered(state.trees.xy)
    assert not covered[~half].any()
    cur = _trees(state.trees.xy[half], state.trees.row[half], state.trees.position[half])
    k = assign_keys(cur, state, transform=IDENTITY, gate=0.5, covered=covered)
    assert len(k.removed) == 0
    assert sorted(state.key[k.unseen].tolist()) == sorted(state.key[~half].tolist())


def test_a_trunk_placed_far_off_is_matched_again_when_its_height_agrees():
    state = _state()
    xy = state.trees.xy.copy()
    xy[3] += [0.6, 0.0]  # beyond the gate (0.5 m), within 1.4 gates; a neighbour is 1.5 m away
    cur = _trees(xy, state.trees.row, state.trees.position, height=np.full(12, 3.2))
    k = assign_keys(cur, state, transform=IDENTITY, gate=0.5, covered=np.ones(12, bool))
    assert k.key.tolist() == state.key.tolist() and len(k.removed) == 0
    low = _trees(xy, state.trees.row, state.trees.position, height=np.r_[np.full(3, 3.2), [1.0], np.full(8, 3.2)])
    k = assign_keys(low, state, transform=IDENTITY, gate=0.5, covered=np.ones(12, bool))
    assert k.status[3] == "replanted" and state.key[k.removed].tolist() == [40]  # a young tree in a cut one's slot
