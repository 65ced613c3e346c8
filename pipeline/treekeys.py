"""Tree identity across the captures of a block: keys, statuses, addresses and change.

After registration (:mod:`pipeline.registration`) a capture's trees are matched one to
one to the living trees of the block's state (the previous capture's trees and those it
carried unseen), each pair closer than a gate, a fraction of the in-row spacing. A
matched tree keeps its key and its address (row, position), whatever this capture's
own row analysis numbers it; a tree that matched nothing gets a new key (keys are never
reused: the state carries the next one) and an address in the previous numbering,
from how this capture's row maps onto the previous one. A previous tree that matched
nothing is *removed* when this capture saw the ground around it, else carried as
unseen. A young tree in a slot that was empty or lost its tree is *replanted*; so is a
match that shrank far beyond any pruning (a tree cut and replanted in one season).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import date

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from pipeline.registration import RigidTransform

#: A match whose height fell below this ratio, with a trunk that thinned below
#: :data:`REPLACED_TRUNK_RATIO` (or unmeasured), is a replant in a cut tree's slot.
REPLACED_HEIGHT_RATIO = 0.65
REPLACED_TRUNK_RATIO = 0.75
#: a second pass matches trees both left unmatched within this many gates, when their
#: heights agree (a trunk placed far off in one capture: a thin stem, a lean)
SECOND_GATE = 1.4
SECOND_HEIGHT_RATIO = (0.8, 1.5)


@dataclass
class Trees:
    """One capture's trees, in ``tree_id`` order (input CRS, metres).

    Attributes
    ----------
    xy : (n, 2) float64
    row, position : (n,) int64 — this capture's own addresses (0: none)
    height, volume, trunk : (n,) float64 — height [m], crown volume [m3], trunk diameter [m]
    """

    xy: np.ndarray
    row: np.ndarray
    position: np.ndarray
    height: np.ndarray
    volume: np.ndarray
    trunk: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)


@dataclass
class BlockState:
    """The block as its latest capture left it: its living trees (seen by that capture,
    or carried unseen from an earlier one), positions in the latest capture's frame.

    Attributes
    ----------
    capture_id, captured_at : str — the latest capture and its ISO date
    key : (m,) int64
    trees : Trees — the living trees' positions, addresses and sizes (last seen)
    last_capture, last_date : (m,) object — the capture that last saw each tree, and its date
    empty_slots : (e, 2) int64 — (row, position) of slots without a tree: the latest
        capture's gaps and every slot a removed tree stood in
    next_key : int — the next unused key
    """

    capture_id: str
    captured_at: str
    key: np.ndarray
    trees: Trees
    last_capture: np.ndarray
    last_date: np.ndarray
    empty_slots: np.ndarray
    next_key: int


@dataclass
class RowMap:
    """This capture's row numbering onto the previous one: row ``r`` → (row, sign, offset),
    position ``p`` → ``sign * p + offset``."""

    rows: dict = field(default_factory=dict)

    def address(self, row: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, position) arrays in the previous numbering (rows it cannot map: unchanged)."""
        given = np.asarray(row, np.int64)
        row, position = given.copy(), np.asarray(position, np.int64).copy()
        for r, (pr, sign, off) in self.rows.items():
            at = given == r
            row[at], position[at] = pr, sign * position[at] + off
        return row, position


@dataclass
class KeyAssignment:
    """What :func:`assign_keys` decided, per current tree and per state tree.

    Attributes
    ----------
    key : (n,) int64
    status : (n,) object — ``same``, ``new`` or ``replanted``
    row, position : (n,) int64 — addresses in the block's numbering
    prev : (n,) int64 — the state tree each matched tree is (-1: none)
    removed, unseen : (r,), (u,) int64 — state trees found gone / not covered
    next_key : int
    row_map : RowMap
    """

    key: np.ndarray
    status: np.ndarray
    row: np.ndarray
    position: np.ndarray
    prev: np.ndarray
    removed: np.ndarray
    unseen: np.ndarray
    next_key: int
    row_map: RowMap

    def counts(self) -> dict:
        return {"same": int(np.sum(self.status == "same")), "new": int(np.sum(self.status == "new")),
                "replanted": int(np.sum(self.status == "replanted")), "removed": int(len(self.removed))}


def first_keys(trees: Trees) -> KeyAssignment:
    """Keys of a block's first capture: 1..n in ``tree_id`` order, every tree new."""
    n = len(trees)
    return KeyAssignment(np.arange(1, n + 1, dtype=np.int64), np.full(n, "new", object),
                         np.asarray(trees.row, np.int64), np.asarray(trees.position, np.int64),
                         np.full(n, -1, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), n + 1, RowMap())


def match_trees(moved: np.ndarray, prev_xy: np.ndarray, gate: float) -> np.ndarray:
    """One-to-one matching of trees closer than ``gate`` [m], least total distance.

    Parameters
    ----------
    moved : (n, 2) — this capture's trunks registered into the previous frame [m]
    prev_xy : (m, 2) — the state's trunks [m]

    Returns
    -------
    (n,) int64 — the matched state tree of each current tree, -1 for none
    """
    # Strategy: the gated pairs form a sparse bipartite graph; each connected component
    # (one pair, mostly) is assigned on its own by linear_sum_assignment, so the cost
    # stays linear in the trees.
    n, m = len(moved), len(prev_xy)
    out = np.full(n, -1, np.int64)
    if n == 0 or m == 0:
        return out
    d = cKDTree(moved).sparse_distance_matrix(cKDTree(prev_xy), gate, output_type="ndarray")
    if len(d) == 0:
        return out
    i, j, w = d["i"].astype(np.int64), d["j"].astype(np.int64), d["v"]
    graph = coo_matrix((np.ones(len(i)), (i, n + j)), shape=(n + m, n + m))
    _, label = connected_components(graph, directed=False)
    comp = label[i]
    order = np.argsort(comp, kind="stable")
    starts = np.flatnonzero(np.r_[True, comp[order][1:] != comp[order][:-1]])
    ends = np.r_[starts[1:], len(order)]
    for a, b in zip(starts, ends):
        e = order[a:b]
        if len(e) == 1:
            out[i[e[0]]] = j[e[0]]
            continue
        ui, ri = np.unique(i[e], return_inverse=True)
        uj, rj = np.unique(j[e], return_inverse=True)
        cost = np.full((len(ui), len(uj)), 1e6)
        cost[ri, rj] = w[e]
        # imported here: scipy.optimize costs 0.1 s of CPU at start-up, and only a capture
        # matched against a previous one gets here (python -X importtime)
        from scipy.optimize import linear_sum_assignment

        r, c = linear_sum_assignment(cost)
        ok = cost[r, c] < 1e6
        out[ui[r[ok]]] = uj[c[ok]]
    return out


def assign_keys(cur: Trees, state: BlockState, *, transform: RigidTransform, gate: float,
                covered: np.ndarray) -> KeyAssignment:
    """Keys, statuses and addresses of a capture's trees against the block's state.

    Parameters
    ----------
    cur : Trees — this capture's trees (its frame)
    state : BlockState — the block before this capture (the previous capture's frame)
    transform : RigidTransform — this capture's frame onto the previous one's
    gate : float — largest distance of a match [m]
    covered : (m,) bool — state trees inside the area this capture saw

    Returns
    -------
    KeyAssignment
    """
    n = len(cur)
    moved = transform.apply(cur.xy)
    prev = match_trees(moved, state.trees.xy, gate)
    left = np.flatnonzero(prev < 0)
    free = np.setdiff1d(np.arange(len(state.key)), prev[prev >= 0])
    if len(left) and len(free):
        again = match_trees(moved[left], state.trees.xy[free], SECOND_GATE * gate)
        ok = again >= 0
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = cur.height[left[ok]] / state.trees.height[free[again[ok]]]
        agree = (ratio >= SECOND_HEIGHT_RATIO[0]) & (ratio <= SECOND_HEIGHT_RATIO[1])
        prev[left[ok][agree]] = free[again[ok]][agree]
    has = prev >= 0
    replaced = np.zeros(n, bool)
    if has.any():
        with np.errstate(divide="ignore", invalid="ignore"):
            hr = cur.height[has] / state.trees.height[prev[has]]
            tr = cur.trunk[has] / state.trees.trunk[prev[has]]
        replaced[has] = (hr < REPLACED_HEIGHT_RATIO) & ~(tr >= REPLACED_TRUNK_RATIO)
    matched = has & ~replaced
    taken = np.zeros(len(state.key), bool)
    taken[prev[matched]] = True
    gone_slot = prev[replaced]  # a cut tree's slot, its replant standing in it
    row_map = _row_map(cur, state, prev, matched)
    row, position = row_map.address(cur.row, cur.position)
    row[matched], position[matched] = state.trees.row[prev[matched]], state.trees.position[prev[matched]]
    row[replaced], position[replaced] = state.trees.row[gone_slot], state.trees.position[gone_slot]
    key = np.zeros(n, np.int64)
    key[matched] = state.key[prev[matched]]
    fresh = ~matched
    key[fresh] = state.next_key + np.arange(int(fresh.sum()))
    removed = np.flatnonzero(~taken & covered)
    removed = np.union1d(removed, gone_slot).astype(np.int64)
    unseen = np.flatnonzero(~taken & ~covered & ~np.isin(np.arange(len(state.key)), gone_slot))
    empty = {(int(r), int(p)) for r, p in np.asarray(state.empty_slots, np.int64).reshape(-1, 2)}
    empty |= {(int(state.trees.row[k]), int(state.trees.position[k])) for k in removed}
    status = np.where(matched, "same", "new").astype(object)
    for t in np.flatnonzero(fresh):
        if replaced[t] or (row[t] > 0 and (int(row[t]), int(position[t])) in empty):
            status[t] = "replanted"
    prev_out = np.where(matched, prev, -1)
    return KeyAssignment(key, status, row, position, prev_out, removed, unseen.astype(np.int64),
                         state.next_key + int(fresh.sum()), row_map)


def _row_map(cur: Trees, state: BlockState, prev: np.ndarray, matched: np.ndarray) -> RowMap:
    """How this capture's rows and positions map onto the state's, from its matched trees;
    a row with no matched tree becomes a new row, numbered after the block's rows."""
    rows = {}
    cur_row = np.asarray(cur.row, np.int64)
    for r in np.unique(cur_row[cur_row > 0]):
        sel = matched & (cur_row == r)
        if not sel.any():
            continue
        pr = state.trees.row[prev[sel]]
        target = int(np.bincount(pr[pr > 0]).argmax()) if np.any(pr > 0) else 0
        if target == 0:
            continue
        on = sel.copy()
        on[sel] = pr == target
        pp = state.trees.position[prev[on]]
        cp = np.asarray(cur.position, np.int64)[on]
        best = None
        for sign in (1, -1):
            vals, counts = np.unique(pp - sign * cp, return_counts=True)
            k = int(counts.argmax())
            if best is None or counts[k] > best[2]:
                best = (sign, int(vals[k]), int(counts[k]))
        rows[int(r)] = (target, best[0], best[1])
    top = int(max(np.max(state.trees.row, initial=0), np.max(np.asarray(state.empty_slots).reshape(-1, 2)[:, 0], initial=0)))
    for r in np.unique(cur_row[cur_row > 0]):
        if int(r) not in rows:
            top += 1
            rows[int(r)] = (top, 1, 0)
    return RowMap(rows)


def change(cur_values: np.ndarray, prev_values: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """(n,) float64: this capture's value less the matched state tree's; NaN without a match."""
    out = np.full(len(prev), np.nan)
    has = prev >= 0
    out[has] = np.asarray(cur_values, np.float64)[has] - np.asarray(prev_values, np.float64)[prev[has]]
    return out


def days_between(later: str, earlier: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """(n,) float64: days from each matched tree's last capture date to ``later``; NaN without."""
    out = np.full(len(prev), np.nan)
    end = date.fromisoformat(later)
    for t in np.flatnonzero(prev >= 0):
        out[t] = float((end - date.fromisoformat(str(earlier[prev[t]]))).days)
    return out
