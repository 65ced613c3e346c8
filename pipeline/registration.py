"""Registration of one capture of a block onto the block's previous capture: the 2-D
rigid transform (shift and heading) that GNSS/SLAM drift puts between two scans, found
from the trees' trunk positions and sizes.

Rows are periodic: shifted by one tree spacing, most trunks of one capture land on a
trunk of the other, so a nearest-trunk match locks onto the wrong tree as soon as the
drift exceeds half the spacing. The transform is therefore chosen among candidates
(rotations within ``max_rotation_deg``, translations voted by every pair of trunks
closer than ``max_shift``) by a score that the true alignment wins and a one-tree-off
one loses: inliers weighted by how consistent the trees' size ratios are (a tree's
height and crown change with the season by a ratio shared by its neighbours; the
neighbour one slot along is a different tree), less a penalty for every previous tree
the capture saw the ground of but matched nothing (a row end uncovered by the shift).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree

from pipeline.errors import NoOverlapError


class RegistrationParams(BaseModel):
    """How far two captures may drift apart and how the candidates are searched."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_shift: float = Field(2.5, gt=0.0, le=20.0, description="largest shift searched [m]")
    max_rotation_deg: float = Field(2.5, ge=0.0, le=20.0, description="largest heading change searched [degrees]")
    rotation_step_deg: float = Field(0.5, gt=0.0, le=5.0, description="step of the rotations tried [degrees]")
    vote_bin: float = Field(0.2, gt=0.0, le=2.0, description="bin of the translation votes [m]")
    peaks: int = Field(6, ge=1, le=50, description="translations scored per rotation")
    gate_fraction: float = Field(0.35, gt=0.0, lt=0.5, description="match gate as a fraction of the in-row spacing")
    gate_min: float = Field(0.15, gt=0.0, le=5.0, description="smallest match gate [m]")
    gate_max: float = Field(1.0, gt=0.0, le=5.0, description="largest match gate [m]")
    uncovered_penalty: float = Field(1.0, ge=0.0, le=10.0, description="score lost per previous tree inside the "
                                     "capture's coverage left unmatched")
    size_sigma: tuple[float, float, float] = Field((0.06, 0.12, 0.25), description="spread of the log size ratios "
                                                   "(height, crown size, trunk) of one alignment's true matches")
    min_matched: int = Field(3, ge=2, le=1000, description="fewest matched trees of a credible transform")
    min_matched_fraction: float = Field(0.2, ge=0.0, le=1.0, description="fewest matched trees as a fraction of the "
                                        "smaller of the two captures' trees")


@dataclass(frozen=True)
class RigidTransform:
    """``p -> R(rotation) (p - centre) + centre + (dx, dy)``, metres and degrees (counter-clockwise)."""

    dx: float
    dy: float
    rotation_deg: float
    cx: float
    cy: float

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) points mapped by the transform [m]."""
        c = np.array([self.cx, self.cy])
        return _rotate(np.asarray(xy, np.float64).reshape(-1, 2) - c, self.rotation_deg) + c + np.array([self.dx, self.dy])

    def inverse(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) points mapped back (the inverse transform) [m]."""
        c = np.array([self.cx, self.cy])
        return _rotate(np.asarray(xy, np.float64).reshape(-1, 2) - c - np.array([self.dx, self.dy]), -self.rotation_deg) + c


@dataclass(frozen=True)
class Registration:
    """The transform from the capture's frame to the previous capture's, and how well it fits.

    Attributes
    ----------
    transform : RigidTransform
    residual_m : float
        RMS distance of the matched trunks the transform was fitted to [m] (the trimmed
        pairs: a trunk placed more than three times the median distance off is left out
        of the fit and of this figure).
    residual_all_m : float
        RMS distance of all matched trunks [m], the misplaced ones included.
    n_matched : int
        Trunk pairs matched within the gate.
    gate : float
        The match gate used [m] (a fraction of the in-row spacing).
    """

    transform: RigidTransform
    residual_m: float
    n_matched: int
    gate: float
    residual_all_m: float = float("nan")

    def record(self) -> dict:
        """The registration as stored with a capture (``orchard:capture``)."""
        t = self.transform
        return {"dx": t.dx, "dy": t.dy, "rotation_deg": t.rotation_deg, "cx": t.cx, "cy": t.cy,
                "residual_m": self.residual_m, "n_matched": self.n_matched, "residual_all_m": self.residual_all_m}


def _rotate(xy: np.ndarray, deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    return xy @ np.array([[c, s], [-s, c]])


def in_row_spacing(xy: np.ndarray) -> float:
    """Median distance from a trunk to its nearest neighbour (the in-row spacing) [m]."""
    if len(xy) < 2:
        return 5.0
    d, _ = cKDTree(xy).query(xy, k=2)
    return float(np.median(d[:, 1]))


def size_descriptors(height, crown_volume, trunk_diameter) -> np.ndarray:
    """(n, 3) log sizes of trees (height, crown's linear size, trunk); NaN where unknown."""
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.log(np.where(np.asarray(height, float) > 0, height, np.nan))
        v = np.log(np.where(np.asarray(crown_volume, float) > 0, crown_volume, np.nan)) / 3.0
        t = np.log(np.where(np.asarray(trunk_diameter, float) > 0, trunk_diameter, np.nan))
    return np.c_[h, v, t]


def _similarity(a: np.ndarray, b: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """(p,) in [0, 1]: how consistent each pair's size ratios are with the alignment's
    common ratio (the season's growth: the median ratio of all pairs)."""
    r = a - b
    if len(r) == 0:
        return np.zeros(0)
    known = np.isfinite(r)
    for c in range(r.shape[1]):  # the common ratio: each size's median over the pairs that have it
        if known[:, c].any():
            r[:, c] -= np.median(r[known[:, c], c])
    s = np.where(known, np.exp(-0.5 * (np.where(known, r, 0.0) / sigma) ** 2), 0.0)
    n = known.sum(axis=1)
    return np.where(n > 0, s.sum(axis=1) / np.maximum(n, 1), 0.5)


def kabsch_2d(src: np.ndarray, dst: np.ndarray, centre: np.ndarray) -> RigidTransform:
    """Least-squares rigid transform (about ``centre``) taking ``src`` onto ``dst`` (both (p, 2))."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    h = a.T @ b
    angle = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    deg = float(np.rad2deg(angle))
    # dst = R (src - c) + c + t  with R (ms - c) + c + t = md
    t = md - _rotate((ms - centre)[None], deg)[0] - centre
    return RigidTransform(float(t[0]), float(t[1]), deg, float(centre[0]), float(centre[1]))


def _pairs(prev_tree: cKDTree, moved: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest pairs (cur index, prev index, distance) within ``gate``."""
    d, j = prev_tree.query(moved, distance_upper_bound=gate)
    ok = np.isfinite(d)
    i, j, d = np.flatnonzero(ok), j[ok], d[ok]
    if len(i) == 0:
        return i, j, d
    # one current tree per previous tree: the nearest
    order = np.lexsort((d, j))
    first = np.r_[True, j[order][1:] != j[order][:-1]]
    keep = order[first]
    return i[keep], j[keep], d[keep]


def register(
    cur_xy: np.ndarray,
    prev_xy: np.ndarray,
    *,
    cur_size: np.ndarray | None = None,
    prev_size: np.ndarray | None = None,
    covered=None,
    names: tuple[str, str] = ("capture", "previous capture"),
    params: RegistrationParams = RegistrationParams(),
) -> Registration:
    """Register a capture's trunks onto the previous capture's.

    Parameters
    ----------
    cur_xy : (n, 2) float64
        Trunk positions of this capture [m], its own frame.
    prev_xy : (m, 2) float64
        Trunk positions of the previous capture's trees [m], its frame.
    cur_size, prev_size : (n, 3), (m, 3) float64, optional
        :func:`size_descriptors` of the trees (NaN where unknown).
    covered : callable, optional
        ``covered(xy)`` → (p,) bool: whether points of this capture's frame lie in the
        area it saw; previous trees there that match nothing cost score.
    names : (str, str)
        This capture's and the previous one's ids, for the error.
    params : RegistrationParams

    Returns
    -------
    Registration
        The transform maps this capture's frame onto the previous one's.

    Raises
    ------
    NoOverlapError
        No candidate transform matches enough trees (the captures do not overlap).
    """
    # Strategy: for each rotation on a grid, vote for translations with every trunk pair
    # closer than max_shift (a Hough vote), score the strongest few by size-weighted
    # inliers less uncovered previous trees, then refine the best by least squares.
    cur_xy = np.asarray(cur_xy, np.float64).reshape(-1, 2)
    prev_xy = np.asarray(prev_xy, np.float64).reshape(-1, 2)
    n, m = len(cur_xy), len(prev_xy)
    need = max(params.min_matched, int(np.ceil(params.min_matched_fraction * min(n, m))))
    if n < params.min_matched or m < params.min_matched:
        raise _no_overlap(names, 0, need)
    cur_size = np.full((n, 3), np.nan) if cur_size is None else np.asarray(cur_size, np.float64).reshape(n, -1)
    prev_size = np.full((m, 3), np.nan) if prev_size is None else np.asarray(prev_size, np.float64).reshape(m, -1)
    search = _Search(cur_xy, prev_xy, params)
    candidates = search.candidates(covered)
    if not candidates or max(c[1] for c in candidates) < need:
        raise _no_overlap(names, max((c[1] for c in candidates), default=0), need)
    best = search.choose(candidates, cur_size, prev_size, need)
    if best is None:
        raise _no_overlap(names, 0, need)
    transform = search.refine(*best)
    i, j, d = search.pairs(transform)
    if len(i) < need:
        raise _no_overlap(names, len(i), need)
    return Registration(transform, float(np.sqrt(np.mean(d[_fitted(d)] ** 2))), int(len(i)), gate=search.gate,
                        residual_all_m=float(np.sqrt(np.mean(d**2))))


class _Search:
    """The steps of one registration and what they share: both captures' trunks, the
    previous capture's KD-tree, the centre rotations turn about and the match gate.

    A candidate is ``(score, inliers, rotation, translation)``: the trunks matched within
    the gate less the uncovered-tree penalty, the trunks matched, the rotation [degrees]
    about ``centre`` and the translation [m] applied after it.
    """

    def __init__(self, cur_xy: np.ndarray, prev_xy: np.ndarray, params: RegistrationParams):
        self.cur_xy, self.prev_xy, self.params = cur_xy, prev_xy, params
        self.centre = cur_xy.mean(axis=0)
        self.rel = cur_xy - self.centre
        spacing = in_row_spacing(prev_xy)
        self.gate = float(np.clip(params.gate_fraction * spacing, params.gate_min, params.gate_max))
        self.prev_tree = cKDTree(prev_xy)

    def candidates(self, covered) -> list[tuple]:
        """The strongest translations voted at each rotation of the grid, scored."""
        steps = int(round(self.params.max_rotation_deg / self.params.rotation_step_deg))
        angles = np.arange(-steps, steps + 1) * self.params.rotation_step_deg
        candidates = []
        for deg in angles:
            candidates.extend(self._voted(deg, covered))
        return candidates

    def _voted(self, deg, covered) -> list[tuple]:
        """The ``peaks`` translations most trunk pairs vote for at one rotation (a Hough
        vote over bins of ``vote_bin``), each scored by its matches."""
        params, prev_xy, centre = self.params, self.prev_xy, self.centre
        rc = _rotate(self.rel, deg) + centre
        pairs = self.prev_tree.sparse_distance_matrix(cKDTree(rc), params.max_shift, output_type="ndarray")
        if len(pairs) == 0:
            return []
        diff = prev_xy[pairs["i"]] - rc[pairs["j"]]
        cell = np.floor(diff / params.vote_bin).astype(np.int64)
        key = (cell[:, 0] << 32) + (cell[:, 1] & 0xFFFFFFFF)
        uniq, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
        top = np.argsort(-counts, kind="stable")[: params.peaks]
        out = []
        for u in top:
            if counts[u] < 2 and len(self.cur_xy) > 2:
                break
            t = diff[inv == u].mean(axis=0)
            i, j, _ = _pairs(self.prev_tree, rc + t, self.gate)
            out.append((len(i) - _uncovered(j, deg, t, prev_xy, covered, centre, params.uncovered_penalty),
                        len(i), deg, t))
        return out

    def choose(self, candidates, cur_size, prev_size, need) -> tuple | None:
        """``(rotation, translation)`` of the candidate whose matched trees' sizes agree
        best, among those near the best score; None when none matches ``need`` trees."""
        # the sizes decide among the candidates close to the best count (a one-tree-off
        # alignment matches about as many trunks as the true one)
        sigma = np.asarray(self.params.size_sigma, np.float64)[: cur_size.shape[1]]
        top = max(c[0] for c in candidates)
        best = None
        for base, n_in, deg, t in candidates:
            if base < top - max(3.0, 0.3 * abs(top)) or n_in < need:
                continue
            rc = _rotate(self.rel, deg) + self.centre + t
            i, j, _ = _pairs(self.prev_tree, rc, self.gate)
            score = float(_similarity(cur_size[i], prev_size[j], sigma).sum()) - (len(i) - base)
            if best is None or score > best[0]:
                best = (score, deg, t)
        return None if best is None else best[1:]

    def refine(self, deg, t) -> RigidTransform:
        """The chosen candidate refined by least squares on its (trimmed) mutual matches."""
        centre = self.centre
        transform = RigidTransform(float(t[0]), float(t[1]), float(deg), float(centre[0]), float(centre[1]))
        for _ in range(4):  # the mutual matches may change as the fit converges
            i, j, d = self.pairs(transform)
            if len(i) < 2:
                break
            transform = kabsch_2d(self.cur_xy[i[_fitted(d)]], self.prev_xy[j[_fitted(d)]], centre)
        return transform

    def pairs(self, transform: RigidTransform) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mutual nearest pairs (cur index, prev index, distance) under ``transform``."""
        return _pairs(self.prev_tree, transform.apply(self.cur_xy), self.gate)


def _fitted(d: np.ndarray) -> np.ndarray:
    """The pairs a fit uses: a trunk placed badly in one capture (a thin stem, a lean, two
    trees merged) would pull it, so pairs beyond three median distances are trimmed."""
    if len(d) < 6:
        return np.ones(len(d), bool)
    return d <= max(3.0 * float(np.median(d)), 0.02)


def _uncovered(j, deg, t, prev_xy, covered, centre, penalty) -> float:
    """The penalty for previous trees inside this capture's coverage that matched nothing."""
    if covered is None or penalty <= 0:
        return 0.0
    unmatched = np.ones(len(prev_xy), bool)
    unmatched[j] = False
    if not unmatched.any():
        return 0.0
    back = _rotate(prev_xy[unmatched] - t - centre, -deg) + centre  # into this capture's frame
    return penalty * float(np.count_nonzero(covered(back)))


def _no_overlap(names, matched: int, need: int) -> NoOverlapError:
    cur, prev = names
    return NoOverlapError(
        f"capture {cur} does not overlap the previous capture {prev}: no shift within the drift searched "
        f"matches enough trees ({matched} of the {need} needed); ",
        hint="check that both are captures of the same block",
        capture=cur, previous=prev, n_matched=matched, value=matched, limit=need,
    )
