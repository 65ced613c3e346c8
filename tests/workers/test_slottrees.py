"""Trees on open slots in a tiled job: the block's decision and the tiles run again
(workers.slottrees)."""

from __future__ import annotations

import numpy as np

from pipeline.params import PipelineParams
from workers.slottrees import SLOT_KEY, block_slot_trees, same_trees, tiles_to_run_again, trees_in_tile


def _evidence(trunks, cands, full):
    cands = np.asarray(cands, float).reshape(-1, 2)
    return {"trunks": np.asarray(trunks, float).reshape(-1, 2), "xy": cands,
            "support": np.full(len(cands), 100.0), "full": np.asarray(full, bool)}


def test_the_block_decides_on_the_rows_no_tile_sees_whole():
    # a row at 1 m, slot 4 empty; each tile's core holds half the row: neither alone has
    # the row's trees on both sides of the slot with enough of a row around them
    west = _evidence([[0, 0], [1, 0], [2, 0]], [[3.02, 0.0]], [True])
    east = _evidence([[4, 0], [5, 0], [6, 0]], [], [])
    trees = block_slot_trees([{"slot_evidence": west}, {"slot_evidence": east}], PipelineParams())
    np.testing.assert_allclose(trees, [[3.02, 0.0, 0.0]])
    assert block_slot_trees([{"slot_evidence": west}], PipelineParams()).shape == (0, 3)


def test_trees_in_a_tile_are_those_in_its_buffered_box_in_the_local_frame():
    trees = np.array([[1.0, 1.0, 0.0], [12.0, 1.0, 1.0], [25.0, 1.0, 0.0]])
    tile = {"buffered": [100.0 - 5, 200.0 - 5, 100.0 + 15, 200.0 + 15]}  # input CRS
    np.testing.assert_array_equal(trees_in_tile(trees, tile, (100.0, 200.0, 0.0)), trees[:2])


def test_the_same_trees_match_within_a_few_mm_of_the_same_kind():
    a = np.array([[1.0, 1.0, 0.0], [3.0, 1.0, 1.0]])
    assert same_trees(a, a[::-1] + [0.01, -0.01, 0.0])
    assert not same_trees(a, a + [0.2, 0.0, 0.0])
    assert not same_trees(a, a[:1])
    assert not same_trees(a, np.c_[a[:, :2], 1.0 - a[:, 2]])  # a replant is no full tree
    assert not same_trees(np.array([[1.0, 1.0, 0.0], [1.01, 1.0, 0.0]]), np.array([[1.0, 1.0, 0.0], [5.0, 5.0, 0.0]]))
    assert same_trees(np.zeros((0, 3)), [])


def test_only_the_tiles_that_let_in_other_trees_than_the_block_run_again():
    origin = (0.0, 0.0, 0.0)
    tiles = [{"id": i, "buffered": [10.0 * i - 3, -3.0, 10.0 * i + 13, 13.0]} for i in range(3)]
    block = np.array([[9.0, 5.0, 0.0]])  # in the buffered boxes of tiles 0 and 1
    summaries = [
        {"tile_id": 0, SLOT_KEY: np.array([[9.004, 5.0, 0.0]])},  # decided as the block did
        {"tile_id": 1, SLOT_KEY: np.zeros((0, 3))},               # its rows did not let it in
        {"tile_id": 2, SLOT_KEY: np.array([[25.0, 5.0, 1.0]])},   # let in one the block did not
    ]
    assert [t["id"] for t in tiles_to_run_again(tiles, summaries, block, origin)] == [1, 2]
    # a tile without a result has not run: it is not run again (it runs with the block's trees)
    assert [t["id"] for t in tiles_to_run_again(tiles, summaries[:1], block, origin)] == []
