"""Planting slots along one row: the slot each tree holds, and the centres of slots.

A row's trees stand on a lattice of planting slots; a tree's slot number is its
address's ``position`` less one, and an empty slot's centre is where a replant or a
missing tree would stand (:mod:`pipeline.rows`, :mod:`pipeline.slots`).
"""

from __future__ import annotations

import numpy as np

#: a row's planting distance differs from the block's by at most this fraction ...
_SPACING_SLACK = 0.1
#: ... and is looked for in this many steps (0.1 % of the spacing)
_SPACING_STEPS = 201
#: an empty slot's centre is fitted by a quadratic (a gently curved row) to the row's
#: trees within this many slots of it, so each tree's own offset from its slot averages out
GAP_FIT_SLOTS = 8
#: the slot beyond a row's end lies a planting distance on along the line through the
#: trees within this many slots of it (a quadratic would swing out beyond the end)
END_FIT_SLOTS = 3


def row_steps(p: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distances [m] between consecutive trees of a row along its local direction: a
    zigzag of trees planted a little off the line would otherwise lengthen the row by a
    slot every few dozen trees."""
    mid = d[:-1] * np.sign(np.einsum("ij,ij->i", d[:-1], d[1:]))[:, None] + d[1:]
    mid /= np.hypot(mid[:, 0], mid[:, 1])[:, None]
    return np.abs(np.einsum("ij,ij->i", np.diff(p, axis=0), mid))


def row_slots(p: np.ndarray, d: np.ndarray, spacing: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Planting slot (0-based) of each tree of a row, in order along the row, the row's
    spacing [m], and which trees keep their slot. ``p`` are the trees' positions, ``d``
    their local row directions, ``spacing`` the block's typical step between
    neighbours [m].

    Strategy: the trees' distances along the row line from the first tree are fitted by
    a lattice of slots (spacing within 10 % of the block's, and offset) that most trees
    lie close to, the peak of their periodogram; every tree goes to its nearest slot, so
    one tree far off its slot does not shift the trees after it. Of two trees in one
    slot the one nearer its centre keeps it.
    """
    keep = np.ones(len(p), dtype=bool)
    if len(p) == 1:
        return np.zeros(1, dtype=np.int64), float("nan"), keep
    step = row_steps(p, d)
    arc = np.r_[0.0, np.cumsum(step)]
    if len(p) < 3:
        slot = np.r_[0, np.cumsum(np.maximum(1, np.rint(step / spacing)))].astype(np.int64)
        return slot, spacing, keep
    cand = spacing * (1.0 + np.linspace(-_SPACING_SLACK, _SPACING_SLACK, _SPACING_STEPS))
    phase = np.exp(2j * np.pi * arc[None, :] / cand[:, None])
    best = int(np.argmax(np.abs(phase.mean(axis=1))))
    s = float(cand[best])
    a0 = s * float(np.angle(phase[best].mean())) / (2 * np.pi)
    slot = np.rint((arc - a0) / s).astype(np.int64)
    off = np.abs(arc - a0 - slot * s)
    for value in np.unique(slot[np.r_[False, np.diff(slot) == 0]]):
        same = np.flatnonzero(slot == value)
        keep[same[same != same[np.argmin(off[same])]]] = False
    return slot, s, keep


def slot_centres(slots: np.ndarray, line: np.ndarray, query, spacing: float = float("nan")) -> np.ndarray:
    """Centres [m] of planting slots of one row, fitted to its trees so that one tree's
    own offset from its slot does not move them.

    - A slot between the trees: least squares of x and y against the slot number, a
      quadratic through the trees within :data:`GAP_FIT_SLOTS` slots (at least four;
      else the straight line between its two neighbours).
    - A slot beyond either end: the least-squares line through the trees within
      :data:`END_FIT_SLOTS` slots gives the direction, and the centre steps ``spacing``
      per slot along it from the trees' mean.

    Parameters
    ----------
    slots : (m,) int — the trees' slots, increasing (at least two)
    line : (m, 2) float64 — the trees' positions [m], in that order
    query : (q,) int — slots whose centres are wanted
    spacing : float — the row's planting distance [m]; NaN: the fitted line's own step

    Returns
    -------
    (q, 2) float64
    """
    slots = np.asarray(slots, np.float64)
    query = np.atleast_1d(np.asarray(query, np.float64))
    out = np.empty((len(query), 2))
    for i, q in enumerate(query):
        d = np.abs(slots - q)
        if slots[0] < q < slots[-1]:
            near = np.flatnonzero(d <= GAP_FIT_SLOTS)
            if len(near) < 4:
                out[i] = [np.interp(q, slots, line[:, 0]), np.interp(q, slots, line[:, 1])]
                continue
            k = slots[near] - q
            out[i] = np.linalg.lstsq(np.vander(k, 3, increasing=True), line[near], rcond=None)[0][0]
            continue
        near = np.flatnonzero(d <= END_FIT_SLOTS)
        if len(near) < 2:
            near = np.argsort(d, kind="stable")[:2]
        k = slots[near] - q
        p = line[near]
        step = np.linalg.lstsq(np.c_[np.ones(len(near)), k], p, rcond=None)[0][1]  # per slot [m]
        if np.isfinite(spacing) and np.hypot(*step) > 0:
            step = step * (spacing / np.hypot(*step))
        out[i] = (p - k[:, None] * step).mean(axis=0)
    return out
