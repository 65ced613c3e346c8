"""The row prior at the merge (workers.outputs): a trunk between two rows is dropped as
foliage or a weed touching down, unless the tile that found it saw a stem of its own;
the flag travels from the detection through the tile summaries."""

from __future__ import annotations

import numpy as np

from pipeline.merge import GlobalTrunks, TileTrunks, reconcile_trunks
from pipeline.params import PipelineParams
from pipeline.trunks import TrunkDetection, drop_trunks
from workers.outputs import own_stems, without_trunks_between_rows


def _grid() -> np.ndarray:
    """3 rows of 6 trunks, 2.5 m apart in the row, rows 4.5 m apart (y = 0, 4.5, 9)."""
    return np.array([[2.5 * j, 4.5 * i] for i in range(3) for j in range(6)], dtype=float)


def test_the_prior_keeps_a_trunk_with_a_stem_of_its_own_and_drops_one_without():
    # two trunks in the alleys, 1.3 m off rows 1 and 2 (a fifth of the row spacing is the
    # off-row limit: 0.9 m); only the first was found with a stem of its own
    grid = _grid()
    alley = np.array([[5.2, 1.3], [7.7, 5.8]])  # beside tree 3 (5.0, 0) and tree 10 (7.5, 4.5)
    xy = np.r_[grid, alley]
    k = len(xy)
    merged = GlobalTrunks(np.c_[xy, np.zeros(k)], np.full(k, 0.1), np.ones(k), np.zeros(k, np.int64),
                          {0: np.arange(k + 1)})
    flag = np.zeros(k, bool)
    flag[18] = True
    out = without_trunks_between_rows(merged, PipelineParams(), own_stem=flag)
    assert out.n_trees == k - 1
    np.testing.assert_allclose(out.trunks[:, :2], xy[:19])  # the flagged one kept, the other gone
    assert out.id_maps[0].tolist() == list(range(20)) + [10]  # its points → tree 10, at (7.5, 4.5)
    # without the flag both go, the first to tree 3 at (5.0, 0.0)
    both = without_trunks_between_rows(merged, PipelineParams())
    assert both.n_trees == k - 2
    assert both.id_maps[0][-2:].tolist() == [3, 10]


def _tile(tile_id, xy, owned, own_stem):
    xy = np.asarray(xy, float)
    return {"tile_id": tile_id, "trunks": np.c_[xy, np.zeros(len(xy))], "support": np.full(len(xy), 10.0),
            "diameter": np.full(len(xy), 0.2), "owned": np.asarray(owned, bool), "own_stem": np.asarray(own_stem, bool)}


def test_a_trunk_has_the_flag_its_owning_tile_gave_it():
    # tile 0 owns (1, 1) and (3, 1) and sees (5.02, 1) in its buffer, with a stem of its
    # own; tile 1 owns (5, 1), without, and sees (3, 1) in its buffer, with
    tiles = [_tile(0, [[1, 1], [3, 1], [5.02, 1]], [True, True, False], [False, False, True]),
             _tile(1, [[3, 1], [5, 1]], [False, True], [True, False])]
    merged = reconcile_trunks([TileTrunks(t["tile_id"], t["trunks"], t["support"], t["diameter"], t["owned"])
                               for t in tiles], cluster_radius=0.5, fallback_radius=2.0)
    assert merged.n_trees == 3
    assert own_stems(tiles, merged).tolist() == [False, False, False]
    tiles[0]["own_stem"] = np.array([False, True, True])
    assert own_stems(tiles, merged).tolist() == [False, True, False]
    del tiles[0]["own_stem"]  # a summary of an earlier release: no flag
    assert own_stems(tiles, merged).tolist() == [False, False, False]


def test_dropping_trunks_keeps_each_one_s_flag():
    det = TrunkDetection(np.arange(8.0).reshape(4, 2), np.ones(4), np.ones(4), np.arange(4), np.arange(4),
                         own_stem=np.array([True, False, False, True]))
    assert drop_trunks(det, np.array([0, 2])).own_stem.tolist() == [False, True]
