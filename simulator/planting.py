"""Planting layout of a generated block: which slots hold a tree, and where the rows lie.

The simulator builds every block in a *straight frame*: rows along x, row ``r`` at
``y = r * row_spacing``, slot ``c`` at ``x = c * spacing``. This module decides

- which grid slots are planted (``ragged_rows`` trims 0-3 slots at either end of a row),
  which planted slots are empty (``missing``) and which hold a young tree (``replants``);
- how the straight frame maps to the block: every row bowed sideways by a parabola of
  sagitta ``row_curvature`` over its length, then the whole block rotated by ``rotation``
  about the local origin (the first slot of the first row).

A tree is carried rigidly by the bow (translated with its base and turned with the row's
local direction), so its trunk stays round; the ground, posts and wires are bent point by
point. The random draws use their own stream, so these options leave the rest of a block
(its ground, trees and points) unchanged. All lengths are metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Layout:
    """Slots of the ``rows x trees_per_row`` grid in row-major order.

    Attributes
    ----------
    row, col : (s,) int64
        0-based row and grid column of each slot.
    planted : (s,) bool
        Inside its row's planted extent (not trimmed by ``ragged_rows``).
    present : (s,) bool
        Holds a tree (planted and not missing).
    young : (s,) bool
        Holds a replant.
    first_col : (rows,) int64
        Grid column of each row's first planted slot.
    """

    row: np.ndarray
    col: np.ndarray
    planted: np.ndarray
    present: np.ndarray
    young: np.ndarray
    first_col: np.ndarray

    @property
    def trees(self) -> np.ndarray:
        """Slot index of each tree; tree ``k`` (1-based id) stands in slot ``trees[k-1]``."""
        return np.flatnonzero(self.present)

    @property
    def position(self) -> np.ndarray:
        """1-based planting slot of every grid slot along its row, counted from the row's
        first planted slot (trimmed slots get 0 or less)."""
        return self.col - self.first_col[self.row] + 1

    @property
    def empty(self) -> np.ndarray:
        """Slot indices of the empty planting slots (planted extent, no tree)."""
        return np.flatnonzero(self.planted & ~self.present)


def make_layout(p) -> Layout:
    """The planting layout of ``p`` (a SimulationParams).

    Missing trees are drawn among the inner slots of each row only: a missing tree at a
    row's end would just make the row shorter, which is what ``ragged_rows`` is for. The
    counts are exact: ``round(missing * slots)`` empty slots (at most every inner slot) and
    ``round(replants * slots)`` young trees (at most every tree).
    """
    n = p.rows * p.trees_per_row
    row, col = np.divmod(np.arange(n), p.trees_per_row)
    planted = np.ones(n, bool)
    first = np.zeros(p.rows, np.int64)
    young = np.zeros(n, bool)
    if not (p.ragged_rows or p.missing or p.replants):
        return _season(p, Layout(row, col, planted, planted.copy(), young, first))
    rng = np.random.default_rng([p.seed, 6])
    last = np.full(p.rows, p.trees_per_row - 1, np.int64)
    if p.ragged_rows:
        cut = rng.integers(0, 4, (p.rows, 2))
        # keep at least one slot per row (two where there are two)
        keep = min(2, p.trees_per_row)
        lo = np.minimum(cut[:, 0], p.trees_per_row - keep)
        hi = np.minimum(cut[:, 1], p.trees_per_row - keep - lo)
        first, last = lo, p.trees_per_row - 1 - hi
        planted = (col >= first[row]) & (col <= last[row])
    present = planted.copy()
    inner = np.flatnonzero(planted & (col > first[row]) & (col < last[row]))
    n_miss = min(int(round(p.missing * n)), len(inner))
    if n_miss:
        present[rng.choice(inner, n_miss, replace=False)] = False
    trees = np.flatnonzero(present)
    n_young = min(int(round(p.replants * n)), len(trees))
    if n_young:
        young[rng.choice(trees, n_young, replace=False)] = True
    return _season(p, Layout(row, col, planted, present, young, first))


def _season(p, layout: Layout) -> Layout:
    """``layout`` with the trees a series of captures cut (``cut``) and replanted (``young_slots``)."""
    if not (p.cut or p.young_slots):
        return layout
    present, young = layout.present.copy(), layout.young.copy()
    present[list(p.cut)] = False
    young[list(p.cut)] = False
    present[list(p.young_slots)] = True
    young[list(p.young_slots)] = True
    return Layout(layout.row, layout.col, layout.planted | present, present, young, layout.first_col)


def young_scale(p, slot: int) -> float:
    """Size of a replant relative to its grown neighbours (0.3-0.5, one per slot)."""
    return float(np.random.default_rng([p.seed, 7, slot]).uniform(0.3, 0.5))


def _bow(p, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lateral offset [m] of the rows at ``x`` and its slope dy/dx: a parabola through the
    rows' end slots with its vertex ``row_curvature`` to the side at mid-row."""
    length = (p.trees_per_row - 1) * p.spacing
    if length <= 0:
        return np.zeros_like(x), np.zeros_like(x)
    u = x / length
    return 4.0 * p.row_curvature * u * (1.0 - u), 4.0 * p.row_curvature * (1.0 - 2.0 * u) / length


def is_straight(p) -> bool:
    """True when the block frame is the straight frame (no bow, no rotation)."""
    return p.row_curvature == 0 and p.rotation == 0


def place(p, xyz: np.ndarray, base_xy: np.ndarray | None = None) -> np.ndarray:
    """Map points (n, 3) from the straight frame to the block's local frame.

    Parameters
    ----------
    p : SimulationParams
    xyz : (n, 3) float64
        Points in the straight frame [m].
    base_xy : (2,) float, optional
        The trunk base of the tree the points belong to: the tree moves rigidly with the
        row there. Without it every point is bent on its own (ground, posts, wires).

    Returns
    -------
    (n, 3) float64
        ``xyz`` itself when the frames coincide, else new points.
    """
    if is_straight(p):
        return xyz
    out = np.array(xyz, dtype=np.float64, copy=True)
    if p.row_curvature:
        if base_xy is None:
            out[:, 1] += _bow(p, out[:, 0])[0]
        else:
            off, slope = _bow(p, np.array([float(base_xy[0])]))
            out[:, :2] = _rotate(out[:, :2] - base_xy, float(np.arctan(slope[0]))) + base_xy
            out[:, 1] += off[0]
    if p.rotation:
        out[:, :2] = _rotate(out[:, :2], np.deg2rad(p.rotation))
    return out


def unplace_xy(p, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`place` for ground points: block-frame (x, y) to the straight frame."""
    if is_straight(p):
        return x, y
    xy = np.c_[np.ravel(x), np.ravel(y)]
    if p.rotation:
        xy = _rotate(xy, -np.deg2rad(p.rotation))
    if p.row_curvature:
        xy[:, 1] -= _bow(p, xy[:, 0])[0]
    return xy[:, 0].reshape(np.shape(x)), xy[:, 1].reshape(np.shape(y))


def _rotate(xy: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.c_[c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1]]
