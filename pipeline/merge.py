"""Merging per-tile results into one block result.

Each tile reports the trunks it found in its buffered points, which of them lie in its
core (it *owns* those), and labels for its core points in tile-local tree ids. The
merge keeps every owned trunk, reconciles detections of the same trunk by neighbouring
tiles (a trunk on a core border can be owned by both, a hair apart), numbers the
trunks deterministically by position, and maps every tile's local ids to global ones.
Same block → same ids, whatever the tiling or the number of workers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: a tile's local trunk takes the id of the nearest global trunk within this distance [m]
#: (one detection of a trunk by two tiles differs by far less; neighbouring trees are farther)
MATCH_DISTANCE = 1.0


@dataclass(frozen=True)
class TileTrunks:
    """The trunks one tile found.

    Attributes
    ----------
    tile_id : int
    trunks : (k, 3) float64
        Trunk bases [m], block-local frame; tile-local tree ``j`` is ``trunks[j-1]``.
    support : (k,) float64
        Detection confidence (graph nodes draining into the trunk).
    diameter : (k,) float64
        Trunk diameter [m], NaN when not measured.
    owned : (k,) bool
        True where the trunk base lies in the tile's core.
    """

    tile_id: int
    trunks: np.ndarray
    support: np.ndarray
    diameter: np.ndarray
    owned: np.ndarray


@dataclass(frozen=True)
class GlobalTrunks:
    """Reconciled trunks of the block.

    Attributes
    ----------
    trunks : (K, 3) float64
        Trunk bases [m]; global tree ``i`` is ``trunks[i-1]``, ordered by (x, y) to 1 mm.
    diameter : (K,) float64
        From the owning tile's detection [m].
    support : (K,) float64
    owner : (K,) int64
        Tile that owns each trunk.
    id_maps : dict tile_id → (k_t + 1,) int64
        ``id_maps[t][j]`` is the global id of tile ``t``'s local tree ``j`` (0 → 0: no tree).
    """

    trunks: np.ndarray
    diameter: np.ndarray
    support: np.ndarray
    owner: np.ndarray
    id_maps: dict

    @property
    def n_trees(self) -> int:
        return int(self.trunks.shape[0])


def position_order(xy: np.ndarray) -> np.ndarray:
    """Permutation sorting points (k, 2+) by x, then y, each rounded to 1 mm."""
    if len(xy) == 0:
        return np.zeros(0, dtype=np.int64)
    kx = np.round(xy[:, 0] * 1000.0).astype(np.int64)
    ky = np.round(xy[:, 1] * 1000.0).astype(np.int64)
    return np.lexsort((ky, kx))


def reconcile_trunks(
    tiles: list[TileTrunks],
    *,
    cluster_radius: float,
    fallback_radius: float,
    match_distance: float = MATCH_DISTANCE,
    dead_zones: np.ndarray | None = None,
) -> GlobalTrunks:
    """Reconcile the trunks of all tiles and map local tree ids to global ones.

    Parameters
    ----------
    tiles : list of TileTrunks
    cluster_radius : float
        Owned trunks of *different* tiles closer than this [m] are one trunk: the
        detection with the higher support is kept (tie → lower tile id).
    fallback_radius : float
        A tile's local trunk with no global trunk within ``match_distance`` takes the id
        of the nearest one within this distance [m] (the widest crown); else 0.
    match_distance : float
        A tile's local trunk (owned or in its buffer) takes the id of the nearest global
        trunk within this distance [m].
    dead_zones : (f, 4) float64, optional
        Boxes ``(x0, y0, x1, y1)`` (same frame) where no tile reported: the cores of
        failed tiles. A local trunk there with no global trunk within ``match_distance``
        is a tree nobody owns, not part of its neighbour: its points map to 0.

    Returns
    -------
    GlobalTrunks
    """
    # Strategy: candidates = owned detections sorted by (-support, tile, x, y); a greedy
    # pass keeps a candidate unless a kept one from another tile lies within the radius.
    tiles = sorted(tiles, key=lambda t: t.tile_id)
    pos, sup, diam, tid = [], [], [], []
    for t in tiles:
        own = np.asarray(t.owned, dtype=bool)
        pos.append(np.asarray(t.trunks, dtype=np.float64).reshape(-1, 3)[own])
        sup.append(np.asarray(t.support, dtype=np.float64)[own])
        diam.append(np.asarray(t.diameter, dtype=np.float64)[own])
        tid.append(np.full(int(own.sum()), t.tile_id, dtype=np.int64))
    pos = np.concatenate(pos) if pos else np.zeros((0, 3))
    sup = np.concatenate(sup) if sup else np.zeros(0)
    diam = np.concatenate(diam) if diam else np.zeros(0)
    tid = np.concatenate(tid) if tid else np.zeros(0, np.int64)
    order = np.lexsort((pos[:, 1], pos[:, 0], tid, -sup)) if len(pos) else np.zeros(0, np.int64)
    keep = np.zeros(len(pos), dtype=bool)
    if len(pos):
        tree = cKDTree(pos[:, :2])
        neighbours = tree.query_ball_point(pos[:, :2], r=cluster_radius)
        for i in order:
            if not any(keep[j] and tid[j] != tid[i] for j in neighbours[i]):
                keep[i] = True
    kept = np.flatnonzero(keep)
    kept = kept[position_order(pos[kept])]
    g_pos, g_sup, g_diam, g_owner = pos[kept], sup[kept], diam[kept], tid[kept]

    id_maps = {}
    g_tree = cKDTree(g_pos[:, :2]) if len(g_pos) else None
    for t in tiles:
        local = np.asarray(t.trunks, dtype=np.float64).reshape(-1, 3)
        mp = np.zeros(len(local) + 1, dtype=np.int64)
        if g_tree is not None and len(local):
            d, j = g_tree.query(local[:, :2], k=1)
            ok = d <= max(match_distance, fallback_radius)
            if dead_zones is not None and len(dead_zones):
                ok &= (d <= match_distance) | ~_in_boxes(local[:, :2], np.asarray(dead_zones, dtype=np.float64))
            mp[1:][ok] = j[ok] + 1
        id_maps[t.tile_id] = mp
    return GlobalTrunks(g_pos, g_diam, g_sup, g_owner, id_maps)


def _in_boxes(xy: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(k,) bool: the point lies in one of the half-open boxes (x0, y0, x1, y1)."""
    x, y = xy[:, 0:1], xy[:, 1:2]
    return ((boxes[:, 0] <= x) & (x < boxes[:, 2]) & (boxes[:, 1] <= y) & (y < boxes[:, 3])).any(axis=1)
