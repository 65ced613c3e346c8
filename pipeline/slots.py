"""Open planting slots, and the trees let in on them: the row model as a prior.

Two kinds of tree stand on a row's open slots that the trunk tests alone turn down.

- A replant, a young tree planted into a gap of an old row, stands a third to half as
  tall as its neighbours, below the height that tells a tree from a post, a bin or
  foliage touching the ground (``min_tree_height``): a contact group on an open slot (an
  empty slot between two trees of a row, or the slot beyond a row's end) that is tall
  enough for a nursery tree and passes the tests of a trunk but its height and width
  (a young tree with foliage to the ground is as wide as its foliage).
- A full-grown tree whose contact group has a tree's height and a trunk's foot but was
  taken for a satellite of a stronger neighbour, or found too wide (on dense rows with
  foliage to the ground one tree may drain two or three times what its neighbour does),
  on an open slot.

A young tree that fails only the branch test of a block whose size floors follow its
young trees (a whip whose few side shoots the scan missed) counts as a replant.

Either must drain a share of what the block's typical trunk does: a crown fragment or a
branch touching down near an empty slot, or a weed, drains far less.

The decision takes the block's rows: a tile's own rows end at its buffer. A tile first
decides on its own rows and reports its core's evidence (:func:`slot_evidence`); the
job decides once on the whole block (:func:`trees_on_slots`) and runs again the tiles
that decided otherwise, giving them the block's trees (:func:`let_in`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.params import PipelineParams, RowParams
from pipeline.rows import RowLayout, find_rows
from pipeline.rowslots import slot_centres
from pipeline.trunks import TrunkDetection

#: a nursery tree planted into a gap stands at least this tall [m]; grass and weeds stay lower
MIN_REPLANT_HEIGHT = 0.7
#: a tree let in stands within this fraction of the in-row spacing of its slot's centre
SLOT_REACH = 0.2
#: a replant may stand this far off (hand-planted into a gap, and the slot beyond a row's
#: end is extrapolated), and a full tree draining much on an empty slot between two trees
FAR_REACH = 0.3
#: a full-grown tree let in drains at least this share of the block's median trunk: a
#: crown fragment or branch touching down near an empty slot drains far less
MIN_FULL_SHARE = 0.2
#: a full-grown tree beyond SLOT_REACH of a slot between two trees drains at least this
#: share (beyond a row's end it is as likely a fragment of the end tree's crown)
MIN_FAR_FULL_SHARE = 0.4
#: a replant drains at least this share (a shoot or weed in the grass drains less)
MIN_REPLANT_SHARE = 0.1
#: trees let in at a row's end open the slot beyond them: rounds of letting in, at most
SLOT_ROUNDS = 5
#: contact nodes within this distance [m] of a tree let in seed it in segmentation
SOURCE_RADIUS = 0.2
#: a tile's contact group is the block's group a tree was let in as when their centres
#: lie this close [m] (the same voxels; tiles' ground models differ by mm)
SAME_GROUP = 0.05


#: a row is evidence of a planting lattice from this many trees on (two trees with a gap
#: between them are as likely two trees of an irregular stand)
MIN_LATTICE_TREES = 4
#: ... and so is a shorter row of at least MIN_SHORT_LATTICE_TREES trees in a block with
#: such a row, where each step between its trees is a whole number of the long rows'
#: spacing, within SLOT_REACH of it (a mature row a third replanted keeps three trees of six)
MIN_SHORT_LATTICE_TREES = 3
#: ... and a row of two trees a whole number of at least this many such spacings apart
#: (a row half replanted keeps two, one slot apart as often as more)
MIN_GAPPED_LATTICE_SLOTS = 1
#: in a block without a row of MIN_LATTICE_TREES, this many rows of MIN_SHORT_LATTICE_TREES
#: trees on one lattice are its evidence (two rows of six slots half replanted keep three
#: grown trees each)
MIN_SHORT_LATTICE_ROWS = 2


def open_slots(layout: RowLayout) -> np.ndarray:
    """(o, 2) float64 centres [m] of the slots a tree could still stand in, in rows of at
    least :data:`MIN_LATTICE_TREES` trees (or of fewer on the block's lattice,
    :func:`_lattice_rows`): the empty slots between two trees of the row,
    and the slot beyond each of its ends (:func:`pipeline.rowslots.slot_centres`)."""
    return _open_slots(layout)[0]


def _lattice_rows(layout: RowLayout) -> np.ndarray:
    """(r,) bool: the rows that are evidence of a planting lattice (:data:`MIN_LATTICE_TREES`,
    :data:`MIN_SHORT_LATTICE_TREES`, :data:`MIN_GAPPED_LATTICE_SLOTS`, :data:`MIN_SHORT_LATTICE_ROWS`)."""
    n = layout.rows["n_trees"]
    long = n >= MIN_LATTICE_TREES
    spacing = layout.rows["spacing_m"][long]
    spacing = spacing[np.isfinite(spacing)]
    if not spacing.size:
        # no row of four: rows of three on one lattice (a block half replanted)
        short = (n >= MIN_SHORT_LATTICE_TREES) & np.isfinite(layout.rows["spacing_m"])
        if short.sum() < MIN_SHORT_LATTICE_ROWS:
            return long
        s = float(np.median(layout.rows["spacing_m"][short]))
        lattice = np.array([bool(short[r]) and _on_lattice(layout.lines[r], s, 1) for r in range(len(n))])
        if lattice.sum() < MIN_SHORT_LATTICE_ROWS:
            return long
        long, spacing = lattice, np.array([s])
    s = float(np.median(spacing))
    for r in np.flatnonzero(~long & (n >= 2)):
        least = 1 if n[r] >= MIN_SHORT_LATTICE_TREES else MIN_GAPPED_LATTICE_SLOTS
        long[r] = _on_lattice(layout.lines[r], s, least)
    return long


def _on_lattice(line: np.ndarray, spacing: float, least: int) -> bool:
    """Whether every step between the trees of a row's ``line`` (in slot order) [m] is a
    whole number of at least ``least`` ``spacing`` [m], within :data:`SLOT_REACH` of it."""
    steps = np.hypot(*np.diff(line, axis=0).T) / spacing
    return bool(np.all((np.rint(steps) >= least) & (np.abs(steps - np.rint(steps)) <= SLOT_REACH)))


def _open_slots(layout: RowLayout) -> tuple[np.ndarray, np.ndarray]:
    """:func:`open_slots` and (o,) bool: which of them lie beyond a row's end."""
    long = _lattice_rows(layout)
    in_long = np.isin(layout.gaps["row"], layout.rows["row"][long])
    pts = [np.c_[layout.gaps["x"][in_long], layout.gaps["y"][in_long]]]
    # a row's line runs through its trees in slot order (a canopy row has no trees)
    for number, line, s, is_long in zip(layout.rows["row"], layout.lines, layout.rows["spacing_m"], long):
        if is_long:
            slots = np.sort(layout.position[layout.row == number]).astype(np.int64)
            pts.append(slot_centres(slots, line, [slots[-1] + 1, slots[0] - 1], s))
    pts = np.concatenate(pts).reshape(-1, 2)
    return pts, np.arange(len(pts)) >= int(in_long.sum())


def on_open_slot(tree_xy: np.ndarray, cand_xy: np.ndarray, *, params: RowParams | None = None,
                 reach: float | np.ndarray = SLOT_REACH, end_reach: float | np.ndarray | None = None) -> np.ndarray:
    """Which open slot (:func:`open_slots`) of the rows of ``tree_xy`` each candidate
    stands on: a candidate there is more likely a tree (a replant, a thin trunk) than
    one elsewhere.

    Parameters
    ----------
    tree_xy : (k, 2) float64
        Trunks accepted so far [m].
    cand_xy : (c, 2) float64
        Candidates [m].
    params : RowParams, optional
    reach : float or (c,) float
        A candidate stands on a slot within this fraction of the block's spacing (one
        for all, or each candidate's own).
    end_reach : float or (c,) float, optional
        The same for the slots beyond a row's end (default ``reach``).

    Returns
    -------
    (c,) int64 index of the open slot, -1 where none (or fewer than three trees).
    """
    cand_xy = np.asarray(cand_xy, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(cand_xy), -1, dtype=np.int64)
    tree_xy = np.asarray(tree_xy, dtype=np.float64).reshape(-1, 2)
    if len(cand_xy) == 0 or len(tree_xy) < 3:
        return out
    lay = find_rows(tree_xy, params=params or RowParams())
    slots, beyond_end = _open_slots(lay)
    spacing = np.nanmedian(lay.rows["spacing_m"]) if np.isfinite(lay.rows["spacing_m"]).any() else np.nan
    if not len(slots) or not np.isfinite(spacing):
        return out
    d, j = cKDTree(slots).query(cand_xy)
    r = np.where(beyond_end[j], reach if end_reach is None else end_reach, reach)
    return np.where(d <= r * spacing, j, -1)


def slot_evidence(det: TrunkDetection, *, params: PipelineParams) -> dict:
    """What the decision on trees on open slots (:func:`trees_on_slots`) needs of one
    detection: its trunks, and the contact groups it turned down that may be trees there.

    A replant candidate is tall enough for a nursery tree and passes the tests of a
    trunk but its height and width; a full-tree candidate has a tree's height and a trunk's foot
    (``fits``, ``foot``) but was taken for a neighbour's satellite or found too wide.

    Returns
    -------
    dict with ``trunks`` (k, 2) [m] and ``trunk_support`` (k,) float64 (what each drains),
    ``xy`` (c, 2) [m], ``support`` (c,) float64 and ``full`` (c,) bool (a full-tree
    candidate; else a replant candidate).
    """
    trunks = np.asarray(det.xy, np.float64).reshape(-1, 2)
    trunk_support = np.asarray(det.support, np.float64).reshape(-1)
    cand = det.candidates
    none = {"trunks": trunks, "trunk_support": trunk_support, "xy": np.zeros((0, 2)), "support": np.zeros(0),
            "full": np.zeros(0, bool)}
    if not params.rows.enabled or cand is None or not len(cand["x"]):
        return none
    tp = params.trunks.at_floors(*(det.floors or (None, None)))  # the size floors the detection used
    rejected = ~np.asarray(cand["accepted"], bool)
    replant = (
        rejected
        & (cand["top"] >= MIN_REPLANT_HEIGHT)
        & (cand["top"] < tp.min_tree_height)
        & (cand["planar"] <= tp.max_planar_fraction)
    )  # no width test: a young tree with foliage to the ground is as wide as its foliage
    # a young tree whose few side shoots the scan missed fails only the branch test: a replant to the rows
    replant |= rejected & np.asarray(cand.get("unbranched", False), bool)
    full = rejected & np.asarray(cand["fits"], bool) & (np.asarray(cand["foot"]) >= tp.min_foot_ratio) & ~replant
    pick = replant | full
    return {
        "trunks": trunks,
        "trunk_support": trunk_support,
        "xy": np.c_[cand["x"], cand["y"]][pick].astype(np.float64),
        "support": np.asarray(cand["support"], np.float64)[pick],
        "full": full[pick],
    }


def trees_on_slots(evidence: dict, *, params: RowParams) -> np.ndarray:
    """The trees the rows let in: the evidence's candidates on an open slot of the rows
    of its trunks (an empty slot between two trees, or the slot beyond a row's end), one
    per slot: a full tree before a replant, then the group with the most material.

    A full tree stands within :data:`SLOT_REACH` spacings of the slot's centre and drains
    at least :data:`MIN_FULL_SHARE` of the median trunk, or, on an empty slot between
    two trees, within :data:`FAR_REACH` draining :data:`MIN_FAR_FULL_SHARE`; a replant
    stands within :data:`FAR_REACH`, draining :data:`MIN_REPLANT_SHARE` (no share is
    asked without trunk supports).

    Parameters
    ----------
    evidence : dict
        :func:`slot_evidence` of the block (or the tile deciding for itself).
    params : RowParams

    Returns
    -------
    (f, 3) float64: x, y [m] and young (1.0 a replant, 0.0 a full tree), by slot.
    """
    trunks, xy, support, full = evidence["trunks"], evidence["xy"], evidence["support"], evidence["full"]
    if not params.enabled or not len(xy) or len(trunks) < 3:
        return np.zeros((0, 3))
    full = np.asarray(full, bool)
    ref = evidence.get("trunk_support")
    share = np.full(len(xy), np.inf)
    if ref is not None and len(ref) and np.median(ref) > 0:
        share = np.asarray(support, np.float64) / np.median(ref)
    enough = np.where(full, share >= MIN_FULL_SHARE, share >= MIN_REPLANT_SHARE)
    xy, support, full, share = xy[enough], support[enough], full[enough], share[enough]
    taken = np.zeros(len(xy), bool)
    picked = []  # by round, each round's by slot
    for _ in range(SLOT_ROUNDS):
        # a tree let in at a row's end opens the slot beyond it (replants at a row's end)
        rest = np.flatnonzero(~taken)
        slot = on_open_slot(np.r_[trunks, xy[taken]], xy[rest], params=params,
                            reach=np.where(full[rest] & (share[rest] < MIN_FAR_FULL_SHARE), SLOT_REACH, FAR_REACH),
                            end_reach=np.where(full[rest], SLOT_REACH, FAR_REACH))
        on = np.flatnonzero(slot >= 0)
        if not on.size:
            break
        order = on[np.lexsort((-support[rest][on], ~full[rest][on], slot[on]))]
        first = rest[order[np.r_[True, np.diff(slot[order]) != 0]]]
        taken[first] = True
        picked.append(first)
    if not picked:
        return np.zeros((0, 3))
    first = np.concatenate(picked)
    return np.c_[xy[first], (~full[first]).astype(np.float64)]


def let_in(det: TrunkDetection, trees: np.ndarray, nodes: np.ndarray, node_height: np.ndarray, *,
           contact_top: float) -> TrunkDetection:
    """``det`` with the trees on open slots (:func:`trees_on_slots`) appended (trunks
    ``k..``), replants marked ``young`` (exempt from the height test after segmentation).
    Each takes the measurements of the contact group it was found as where this
    detection has it (a tile's buffer may cut a group at its edge).

    Parameters
    ----------
    det : TrunkDetection
    trees : (f, 3) float64 — x, y [m], young (1.0 / 0.0)
    nodes : (m, 3) float64 — node positions [m]
    node_height : (m,) float64 — height of each node above the ground [m]
    contact_top : float — nodes below this height [m] are ground contacts

    Returns
    -------
    TrunkDetection; ``det`` itself when no tree is added.
    """
    trees = np.asarray(trees, np.float64).reshape(-1, 3)
    if not len(trees):
        return det
    xy = trees[:, :2]
    support, width = np.zeros(len(xy)), np.zeros(len(xy))
    cand = det.candidates
    if cand is not None and len(cand["x"]):
        d, j = cKDTree(np.c_[cand["x"], cand["y"]]).query(xy)
        same = d <= SAME_GROUP
        support[same] = np.asarray(cand["support"], np.float64)[j[same]]
        width[same] = np.asarray(cand["width"], np.float64)[j[same]]
    # each seeded by the contact nodes within SOURCE_RADIUS of it (else the nearest within
    # twice that; a tree without any is left out)
    contact = np.flatnonzero(node_height < contact_top)
    if not contact.size:
        return det
    tree = cKDTree(nodes[contact, :2])
    src, src_t, keep = [], [], []
    for j, c in enumerate(xy):
        near = tree.query_ball_point(c, SOURCE_RADIUS)
        if not near:
            d, n = tree.query(c)
            near = [n] if d <= 2 * SOURCE_RADIUS else []
        if near:
            src.append(contact[np.asarray(near, dtype=np.int64)])
            src_t.append(np.full(len(near), det.k + len(keep), dtype=np.int64))
            keep.append(j)
    if not keep:
        return det
    keep = np.asarray(keep)
    nodes_new = np.concatenate(src)
    trunk_new = np.concatenate(src_t)
    taken = np.isin(nodes_new, det.source_nodes)  # a node seeds one trunk
    return TrunkDetection(
        np.r_[det.xy, xy[keep]],
        np.r_[det.support, support[keep]],
        np.r_[det.width, width[keep]],
        np.r_[det.source_nodes, nodes_new[~taken]],
        np.r_[det.source_trunk, trunk_new[~taken]],
        det.candidates,
        det.spacing,
        np.r_[np.zeros(det.k, bool) if det.young is None else det.young, trees[keep, 2] > 0],
        np.r_[np.zeros(det.k, bool) if det.on_slot is None else det.on_slot, np.ones(len(keep), bool)],
        det.floors,
        # a tree on a slot stands on its row: the row prior has no say over it
        np.r_[np.zeros(det.k, bool) if det.own_stem is None else det.own_stem, np.zeros(len(keep), bool)],
    )
