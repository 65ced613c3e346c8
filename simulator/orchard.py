"""A generated block: its points with per-point truth, and the codes of the point kinds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

KIND = ("ground", "grass", "wood", "leaf", "post", "vehicle", "outlier", "twig")
"""Names of the per-point ``kind`` codes (index = code). Non-wood tree material is
``leaf`` (leaf discs) or ``twig`` (branches thinner than ``WOOD_RADIUS``); ``vehicle``
covers the vehicle and the bin."""
GROUND, GRASS, WOOD, LEAF, POST, VEHICLE, OUTLIER, TWIG = range(len(KIND))

WOOD_RADIUS = 0.015
"""Branches at least this thick [m] are wood; thinner twigs and leaves are not."""


@dataclass
class Orchard:
    """A generated block (or a chunk of one) with its ground truth.

    Attributes
    ----------
    xyz : (n, 3) float64
        Absolute point coordinates [m] in ``crs_epsg``.
    tree_id : (n,) int64
        1-based tree of each point (tree ``k`` has its base at ``trunks[k-1]``); 0 = not a tree.
    is_wood : (n,) bool
        Trunk and branches at least ``WOOD_RADIUS`` thick.
    kind : (n,) uint8
        Code into :data:`KIND`.
    trunks : (k, 3) float64
        Absolute trunk base centres (trunk axis at ground level) [m].
    trunk_radius : (k,) float64
        Trunk radius 0.3 m above the base [m].
    crs_epsg : int
    tree_row, tree_slot : (k,) int64, optional
        1-based row of each tree (rows counted from the simulator's first row) and its
        1-based planting slot along the row (counted from the row's first planted slot).
    tree_young : (k,) bool, optional
        The tree is a replant.
    empty_slots : (e, 4) float64, optional
        ``[row, slot, x, y]`` of every empty planting slot, ``x, y`` the absolute slot centre [m].
    spacing, row_spacing : float, optional
        The block's in-row and between-row spacing [m].
    """

    xyz: np.ndarray
    tree_id: np.ndarray
    is_wood: np.ndarray
    kind: np.ndarray
    trunks: np.ndarray
    trunk_radius: np.ndarray
    crs_epsg: int = 28356
    tree_row: np.ndarray | None = None
    tree_slot: np.ndarray | None = None
    tree_young: np.ndarray | None = None
    empty_slots: np.ndarray | None = None
    spacing: float | None = None
    row_spacing: float | None = None

    @property
    def n_points(self) -> int:
        return int(self.xyz.shape[0])


def concatenate(chunks: Iterable[Orchard]) -> Orchard:
    """One :class:`Orchard` from chunks of the same block."""
    chunks = list(chunks)
    first = chunks[0]
    return Orchard(
        xyz=np.concatenate([c.xyz for c in chunks]),
        tree_id=np.concatenate([c.tree_id for c in chunks]),
        is_wood=np.concatenate([c.is_wood for c in chunks]),
        kind=np.concatenate([c.kind for c in chunks]),
        trunks=first.trunks,
        trunk_radius=first.trunk_radius,
        crs_epsg=first.crs_epsg,
        tree_row=first.tree_row,
        tree_slot=first.tree_slot,
        tree_young=first.tree_young,
        empty_slots=first.empty_slots,
        spacing=first.spacing,
        row_spacing=first.row_spacing,
    )
