"""Orchard simulator: branching trees in rows, scanned from the alleys, with ground truth.

A generated block is the test bench for every accuracy figure, so it is built to be
hard in the ways real mobile captures are hard:

- rows of trees along x with jittered positions, on sloping, gently undulating ground
  with patchy grass and a few points below the ground;
- trees with a real branching structure (:mod:`pipeline.simforms`): open-centre vase
  trees whose crowns overlap their neighbours', tall-spindle apples (a thin leader with
  short laterals along the row) or a hedgerow wall of olive/almond trees; optionally
  drooping branches whose leaves hang down to 0.2-0.5 m above the ground (``low_foliage``);
- a planting layout (:mod:`pipeline.simlayout`): empty slots, young replants, rows of
  different length, rows bowed sideways and the whole block rotated;
- sampled as a mobile scanner driving every alley sees it: point density falls with
  range (1/r^2) and with the cosine of incidence, only surfaces facing the sensor are
  seen, and leaves occlude what lies behind them (Beer-Lambert attenuation through a
  coarse leaf-area grid);
- Gaussian noise, ghosting (each alley pass is offset by a small rigid shift, so
  surfaces seen from two passes are doubled), random outliers in the block volume,
  fence posts with a wire, a parked vehicle and a bin as distractors; optionally a
  trellis in every row (``trellis``: posts among the trees, wires along the row).

Everything is deterministic for a seed. Blocks are generated tree by tree
(:func:`iter_simulation`), so memory stays bounded whatever the block size.

All lengths are metres. The local frame has the first slot of the first row at the
origin; absolute coordinates add ``(easting, northing, elevation)``. The block is built in
a straight frame (rows along x) and mapped to the local frame by :func:`simlayout.place`
as each chunk is finished. The truth file's contract is in ``docs/simulator.md``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from typing import Iterable, Iterator, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.special import ndtri

from pipeline.simforms import _perpendicular, _unit, grow_tree
from pipeline.simlayout import Layout, make_layout, place, unplace_xy, young_scale

KIND = ("ground", "grass", "wood", "leaf", "post", "vehicle", "outlier", "twig")
"""Names of the per-point ``kind`` codes (index = code). Non-wood tree material is
``leaf`` (leaf discs) or ``twig`` (branches thinner than ``WOOD_RADIUS``); ``vehicle``
covers the vehicle and the bin."""
GROUND, GRASS, WOOD, LEAF, POST, VEHICLE, OUTLIER, TWIG = range(len(KIND))

WOOD_RADIUS = 0.015
"""Branches at least this thick [m] are wood; thinner twigs and leaves are not."""

_RANGE_REF = 1.0  # reference range [m] at which `_RHO` applies
_RANGE_MIN = 0.8  # closer than this the density stops growing [m]
_RHO = 20000.0  # points per m^2 (normal incidence, 1 m range) at density 1
_GROUND_RETURN = 0.3  # ground and grass return less (dark, grazing incidence, vehicle shadow)
_BLIND = 0.7  # ground closer than this to the path (laterally) is hidden by the vehicle [m]
_VOXEL = 0.25  # leaf-area grid cell [m]
_CLUMPING = 2.0  # a leaf cluster occludes about twice its sampled disc area (several leaves)
_HEADLAND = 7.0  # headland length beyond the first and last tree [m]
_MARGIN = 4.0  # block margin beyond the outer passes [m]


class SimulationParams(BaseModel):
    """Parameters of a generated orchard block (lengths in metres)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    form: Literal["vase", "spindle", "hedge"] = Field(
        "vase", description="tree form: vase (open-centre trees), spindle (tall-spindle apple: thin leader, short "
        "laterals along the row) or hedge (super-high-density olive/almond: a continuous wall)")
    rows: int = Field(2, ge=1, le=500, description="number of tree rows (rows run along x before any rotation)")
    trees_per_row: int = Field(5, ge=1, le=2000, description="planting slots in each row")
    spacing: float = Field(5.0, ge=0.8, le=20.0, description="distance between trees in a row [m]")
    row_spacing: float = Field(6.0, ge=2.0, le=30.0, description="distance between rows [m]")
    position_jitter: float | None = Field(None, ge=0.0, le=1.0, description="standard deviation of tree positions around the grid [m]; default vase 0.15, spindle and hedge 0.04 (planted to a line)")
    noise: float = Field(0.02, ge=0.0, le=0.1, description="standard deviation of the Gaussian range noise [m]")
    seed: int = Field(0, ge=0, le=2**32 - 1, description="random seed; the same seed gives the same block")
    density: float = Field(1.0, gt=0.0, le=1000.0, description="scale of the point density (1 = about 40-80 k points per tree)")
    crown_radius: float | None = Field(None, gt=0.2, le=15.0, description="crown radius along the row [m] (spindle: the longest lateral); default vase 0.55 x spacing, spindle 0.7, hedge 0.8 x spacing up to 1.6")
    tree_height: float | None = Field(None, gt=1.0, le=30.0, description="tree height [m]; default random per tree: vase 3.5-4.5, spindle 2.8-3.5, hedge 2.5-3.0")
    trunk_radius: float | None = Field(None, gt=0.01, le=1.0, description="trunk radius [m]; default random per tree: vase 0.06-0.15, spindle 0.015-0.025, hedge 0.04-0.06")
    low_foliage: bool = Field(False, description="drooping outer branches, leaves down to 0.2-0.5 m above the ground (vase and hedge)")
    slope: float = Field(0.04, ge=0.0, le=0.5, description="ground slope [m/m], in a random direction")
    undulation: float = Field(0.15, ge=0.0, le=2.0, description="amplitude of gentle ground undulations [m]")
    grass: float = Field(0.5, ge=0.0, le=1.0, description="fraction of the ground covered by grass patches (0-0.12 m, tufts to 0.25 m)")
    posts: bool = Field(True, description="fence posts with a wire along one long edge of the block")
    vehicle: bool = Field(True, description="a vehicle parked in a headland")
    bin: bool = Field(True, description="a 1.2 m fruit bin in the other headland")
    trellis: int = Field(0, ge=0, le=50, description="a trellis in every row: a post (2.8-3.2 m tall, 0.05-0.065 m radius) at both row ends and in every this many-th gap between trees, with wires at 0.8, 1.6 and 2.4 m along the row; 0 = none")
    ghosting: float = Field(0.01, ge=0.0, le=0.05, description="registration drift: rigid offset of each alley pass [m]")
    outliers: float = Field(0.002, ge=0.0, le=0.05, description="fraction of random outlier points in the block volume")
    occlusion: float = Field(1.0, ge=0.0, le=10.0, description="scale of the leaf optical depth (0 = no occlusion)")
    easting: float = Field(500000.0, ge=-1e7, le=1e7, description="x of the local origin (first tree) [m]")
    northing: float = Field(6950000.0, ge=-1e7, le=1e7, description="y of the local origin [m]")
    elevation: float = Field(100.0, ge=-1e4, le=1e4, description="ground height at the local origin [m]")
    epsg: int = Field(28356, ge=1024, le=999999, description="EPSG code of the coordinates")
    missing: float = Field(0.0, ge=0.0, le=0.5, description="fraction of the planting slots left empty (inner slots of the rows only)")
    replants: float = Field(0.0, ge=0.0, le=0.5, description="fraction of the planting slots holding a young replant (0.3-0.5 times a grown tree's height and trunk)")
    rotation: float = Field(0.0, ge=-360.0, le=360.0, description="rotation of the whole block about the first slot [degrees, counterclockwise from east]")
    row_curvature: float = Field(0.0, ge=-20.0, le=20.0, description="sideways bow (sagitta) of every row over its length [m]")
    ragged_rows: bool = Field(False, description="rows of different length: each row loses 0-3 slots at either end at random")

    @model_validator(mode="after")
    def _sizes(self) -> "SimulationParams":
        if self.rows * self.trees_per_row > 200_000:
            raise ValueError(f"{self.rows * self.trees_per_row} trees is too many (at most 200000)")
        if self.crown_radius is not None and self.crown_radius > 2.0 * self.spacing:
            raise ValueError(f"crown_radius ({self.crown_radius} m) above twice the spacing ({self.spacing} m)")
        if self.row_curvature and abs(self.row_curvature) > 0.25 * (self.trees_per_row - 1) * self.spacing:
            raise ValueError(f"row_curvature ({self.row_curvature} m) above a quarter of the row length "
                             f"({(self.trees_per_row - 1) * self.spacing:g} m): rows must stay gently curved")
        return self

    @property
    def jitter(self) -> float:
        """Standard deviation [m] of the tree positions: ``position_jitter`` or the form's default."""
        if self.position_jitter is not None:
            return self.position_jitter
        return 0.15 if self.form == "vase" else 0.04

    @property
    def n_trees(self) -> int:
        """Planting slots of the grid (the number of trees without ``missing`` or ``ragged_rows``)."""
        return self.rows * self.trees_per_row


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


# --------------------------------------------------------------------------- geometry


@dataclass
class _Ground:
    """Ground surface z(x, y) (local frame): plane + a sum of gentle waves."""

    slope_xy: np.ndarray  # (2,) dz/dx, dz/dy
    k: np.ndarray  # (w, 2) wave vectors [rad/m]
    phase: np.ndarray  # (w,)
    amp: np.ndarray  # (w,)
    grass_k: np.ndarray
    grass_phase: np.ndarray
    grass_level: float
    tuft_k: np.ndarray
    tuft_phase: np.ndarray

    @classmethod
    def make(cls, p: SimulationParams, rng: np.random.Generator) -> "_Ground":
        theta = rng.uniform(0, 2 * np.pi)
        n_w = 4
        wl = rng.uniform(8.0, 25.0, n_w)
        ang = rng.uniform(0, 2 * np.pi, n_w)
        k = np.c_[np.cos(ang), np.sin(ang)] * (2 * np.pi / wl)[:, None]
        amp = rng.uniform(0.5, 1.0, n_w)
        amp *= p.undulation / amp.sum()
        g_wl = rng.uniform(3.0, 8.0, 5)
        g_ang = rng.uniform(0, 2 * np.pi, 5)
        t_wl = rng.uniform(1.0, 2.5, 4)
        t_ang = rng.uniform(0, 2 * np.pi, 4)
        # level of the patch field whose exceedance covers ~ `grass` of the ground
        # (sum of 5 unit cosines has std sqrt(5/2)); map the fraction through a normal quantile
        frac = min(max(p.grass, 1e-6), 1 - 1e-6)
        level = float(-ndtri(frac) * np.sqrt(5 / 2)) if 0 < p.grass < 1 else (-1e9 if p.grass >= 1 else 1e9)
        return cls(
            slope_xy=p.slope * np.array([np.cos(theta), np.sin(theta)]),
            k=k,
            phase=rng.uniform(0, 2 * np.pi, n_w),
            amp=amp,
            grass_k=np.c_[np.cos(g_ang), np.sin(g_ang)] * (2 * np.pi / g_wl)[:, None],
            grass_phase=rng.uniform(0, 2 * np.pi, 5),
            grass_level=level,
            tuft_k=np.c_[np.cos(t_ang), np.sin(t_ang)] * (2 * np.pi / t_wl)[:, None],
            tuft_phase=rng.uniform(0, 2 * np.pi, 4),
        )

    def z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        out = self.slope_xy[0] * x + self.slope_xy[1] * y
        for (kx, ky), ph, a in zip(self.k, self.phase, self.amp):
            out = out + a * np.sin(kx * x + ky * y + ph)
        return out

    def _field(self, x, y, k, phase):
        out = np.zeros(np.shape(x))
        for (kx, ky), ph in zip(k, phase):
            out += np.cos(kx * x + ky * y + ph)
        return out

    def grass_height(self, x: np.ndarray, y: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Height of grass above the ground at (x, y), 0 outside the grass patches."""
        f = self._field(x, y, self.grass_k, self.grass_phase)
        in_patch = f > self.grass_level
        h = rng.uniform(0.0, 1.0, np.shape(x)) ** 0.7 * 0.12
        tuft = self._field(x, y, self.tuft_k, self.tuft_phase) > 2.6
        h = np.where(tuft, rng.uniform(0.1, 0.25, np.shape(x)), h)
        return np.where(in_patch, h, 0.0)


# --------------------------------------------------------------------------- the block plan


@dataclass
class _Plan:
    params: SimulationParams
    ground: _Ground
    tree_xy: np.ndarray  # (s, 2) every grid slot, straight frame
    layout: Layout
    bounds: tuple[float, float, float, float]  # x0, x1, y0, y1 local
    pass_y: np.ndarray  # (q,) alley centre lines
    pass_h: np.ndarray  # (q,) sensor height above ground
    pass_shift: np.ndarray  # (q, 3) ghosting offsets
    lad: np.ndarray  # (nx, ny, nh) leaf area density [m^2/m^3], flattened C order
    grid_shape: tuple[int, int, int]
    grid_origin: np.ndarray  # (3,) x, y, h
    trunks: np.ndarray  # (k, 3) local block frame
    trunk_radius: np.ndarray  # (k,)
    scale: np.ndarray  # (k,) size of each tree (1, or less for a replant)
    z_top: float  # highest tree point above ground (max)
    rho: float
    profile_x: np.ndarray  # (m,) along-track stations of the sensor height profiles
    pass_z: np.ndarray  # (q, m) sensor z of each pass at profile_x

    def offset(self) -> np.ndarray:
        return _offset(self.params)

    @cached_property
    def addresses(self) -> dict:
        """The truth of the block's layout, as :class:`Orchard` fields."""
        p, lay = self.params, self.layout
        trees, empty = lay.trees, lay.empty
        centre = np.c_[lay.col[empty] * p.spacing, lay.row[empty] * p.row_spacing, np.zeros(len(empty))]
        xy = place(p, centre)[:, :2] + self.offset()[:2]
        return dict(
            tree_row=lay.row[trees] + 1,
            tree_slot=lay.position[trees],
            tree_young=lay.young[trees],
            empty_slots=np.c_[lay.row[empty] + 1, lay.position[empty], xy].astype(np.float64),
            spacing=p.spacing,
            row_spacing=p.row_spacing,
        )


def _offset(p: SimulationParams) -> np.ndarray:
    """Absolute coordinates of the block's local origin."""
    return np.array([p.easting, p.northing, p.elevation])


def _tree_rng(seed: int, i: int) -> np.random.Generator:
    return np.random.default_rng([seed, 1, i])


def _plan(p: SimulationParams) -> _Plan:
    rng = np.random.default_rng([p.seed, 0])
    ground = _Ground.make(p, rng)
    r_idx, t_idx = np.divmod(np.arange(p.n_trees), p.trees_per_row)
    tree_xy = np.c_[t_idx * p.spacing, r_idx * p.row_spacing] + rng.normal(0.0, p.jitter, (p.n_trees, 2))
    x0, x1 = -_HEADLAND, (p.trees_per_row - 1) * p.spacing + _HEADLAND
    y0, y1 = -0.5 * p.row_spacing - _MARGIN, (p.rows - 0.5) * p.row_spacing + _MARGIN
    pass_y = (np.arange(p.rows + 1) - 0.5) * p.row_spacing
    pass_h = rng.uniform(1.0, 1.8, p.rows + 1)
    shift = _unit(rng.normal(size=(p.rows + 1, 3)) * np.array([1.0, 1.0, 0.5]))
    shift *= p.ghosting * rng.uniform(0.5, 1.0, (p.rows + 1, 1))

    h_max = (p.tree_height * 1.05 if p.tree_height else 4.5) + 1.5
    h0 = -1.0
    shape = (
        int(np.ceil((x1 - x0) / _VOXEL)) + 1,
        int(np.ceil((y1 - y0) / _VOXEL)) + 1,
        int(np.ceil((h_max - h0) / _VOXEL)) + 1,
    )
    origin = np.array([x0, y0, h0])
    lad = np.zeros(int(np.prod(shape)), dtype=np.float32)
    layout = make_layout(p)
    slots = layout.trees
    scale = np.array([young_scale(p, i) if layout.young[i] else 1.0 for i in slots])
    trunks = np.empty((len(slots), 3))
    trunk_r = np.empty(len(slots))
    z_top = 0.0
    # a tree's random stream is that of its slot: removing a tree leaves the others unchanged
    for k, i in enumerate(slots):
        tree = grow_tree(_tree_rng(p.seed, i), p, tree_xy[i], ground, scale=scale[k])
        trunks[k] = place(p, tree.base[None], tree.base[:2])[0]
        trunk_r[k] = tree.trunk_radius
        z_top = max(z_top, tree.top - tree.base[2])
        c = tree.leaf_c
        h = c[:, 2] - ground.z(c[:, 0], c[:, 1])
        flat = _grid_index(np.c_[c[:, :2], h], origin, shape)
        lad += np.bincount(flat, weights=np.pi * tree.leaf_r**2, minlength=lad.size).astype(np.float32)
    lad /= _VOXEL**3
    profile_x = np.arange(x0 - 2.0, x1 + 2.0, 0.1)
    pass_z = np.stack([ground.z(profile_x, np.full(len(profile_x), yk)) + hk for yk, hk in zip(pass_y, pass_h)])
    return _Plan(p, ground, tree_xy, layout, (x0, x1, y0, y1), pass_y, pass_h, shift, lad, shape, origin, trunks,
                 trunk_r, scale, z_top, _RHO * p.density, profile_x, pass_z)


def _grid_index(q: np.ndarray, origin: np.ndarray, shape) -> np.ndarray:
    i = np.clip(((q - origin) / _VOXEL).astype(np.int64), 0, np.array(shape) - 1)
    return (i[:, 0] * shape[1] + i[:, 1]) * shape[2] + i[:, 2]


# --------------------------------------------------------------------------- scanning


def _sensor(plan: _Plan, x: np.ndarray, k: int) -> np.ndarray:
    """Sensor positions (n, 3) of pass ``k`` at the along-track coordinates ``x``
    (the scan plane is perpendicular to the driving direction)."""
    x = np.asarray(x, dtype=np.float64)
    z = np.interp(x, plan.profile_x, plan.pass_z[k])
    return np.c_[x, np.full(len(x), plan.pass_y[k]), z]


def _range_factor(r: np.ndarray) -> np.ndarray:
    return (_RANGE_REF / np.maximum(r, _RANGE_MIN)) ** 2


def _transmittance(plan: _Plan, pts: np.ndarray, k: int, h_p: np.ndarray | None = None) -> np.ndarray:
    """Probability that the ray from each point to its sensor position is not blocked by
    leaves: exp(-occlusion * 0.5 * integral of leaf area density).

    Strategy: the scan plane is perpendicular to the driving direction, so every ray lies
    in the plane x = const. Rays are sorted by length; step k then only touches the
    prefix of rays still longer than the step, so the loop runs over steps (at most
    ~60), never over points.
    """
    n = len(pts)
    if n == 0 or plan.params.occlusion == 0:
        return np.ones(n)
    if h_p is None:
        h_p = pts[:, 2] - plan.ground.z(pts[:, 0], pts[:, 1])
    nx, ny, nh = plan.grid_shape
    ox, oy, oh = plan.grid_origin
    # ray ends in grid units, clamped into the grid (rays are segments, so every step stays inside)
    gy0 = np.clip((pts[:, 1] - oy) / _VOXEL, 0.0, ny - 1e-6)
    gh0 = np.clip((h_p - oh) / _VOXEL, 0.0, nh - 1e-6)
    gy1 = min(max((plan.pass_y[k] - oy) / _VOXEL, 0.0), ny - 1e-6)
    gh1 = min(max((plan.pass_h[k] - oh) / _VOXEL, 0.0), nh - 1e-6)
    length = np.hypot(plan.pass_y[k] - pts[:, 1], plan.pass_h[k] - h_p)
    order = np.argsort(-length, kind="stable")
    L = length[order]
    gy0, gh0 = gy0[order], gh0[order]
    dgy, dgh = gy1 - gy0, gh1 - gh0
    cell0 = np.clip(((pts[order, 0] - ox) / _VOXEL).astype(np.int64), 0, nx - 1) * (ny * nh)
    step = 0.6 * _VOXEL
    start = 0.15
    tau = np.zeros(n)
    neg_L = -L
    j = 0
    while True:
        s = start + (j + 0.5) * step
        m = int(np.searchsorted(neg_L, -s, side="left"))
        if m == 0:
            break
        f = s / L[:m]
        iy = (gy0[:m] + f * dgy[:m]).astype(np.int64)
        ih = (gh0[:m] + f * dgh[:m]).astype(np.int64)
        tau[:m] += plan.lad[cell0[:m] + iy * nh + ih]
        j += 1
    out = np.empty(n)
    out[order] = np.exp(-plan.params.occlusion * _CLUMPING * 0.5 * step * tau)
    return out


def _passes_for(plan: _Plan, y: float) -> np.ndarray:
    """Passes that see an object at lateral position ``y``: those within one row spacing."""
    return np.flatnonzero(np.abs(plan.pass_y - y) <= plan.params.row_spacing * 1.0001)


def _sample_cylinders(rng, plan: _Plan, k: int, a, b, ra, rb):
    """Points on the sensor-facing halves of cylinder segments seen from pass ``k``.

    Density per projected area is rho * (1/r^2); the angle around the axis is drawn
    with density proportional to the cosine of incidence. Returns points (n,3), the
    local radius (n,) and the segment index (n,).
    """
    axis = b - a
    L = np.linalg.norm(axis, axis=1)
    ok = L > 1e-6
    u = axis / np.maximum(L, 1e-12)[:, None]
    c = 0.5 * (a + b)
    v = _sensor(plan, c[:, 0], k) - c
    r_c = np.linalg.norm(v, axis=1)
    sin_t = np.linalg.norm(v - np.sum(v * u, axis=1, keepdims=True) * u, axis=1) / np.maximum(r_c, 1e-9)
    lam = plan.rho * _range_factor(r_c) * (ra + rb) * L * sin_t * ok
    cnt = rng.poisson(lam)
    idx = np.repeat(np.arange(len(a)), cnt)
    t = rng.random(len(idx))
    axis_pt = a[idx] + t[:, None] * axis[idx]
    rad = ra[idx] + t * (rb[idx] - ra[idx])
    ui = u[idx]
    vi = _sensor(plan, axis_pt[:, 0], k) - axis_pt
    vp = vi - np.sum(vi * ui, axis=1, keepdims=True) * ui
    e1 = _unit(vp)
    e2 = np.cross(ui, e1)
    phi = np.arcsin(2.0 * rng.random(len(idx)) - 1.0)
    pts = axis_pt + rad[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    r_p = np.linalg.norm(vi, axis=1)
    keep = rng.random(len(idx)) < np.minimum(1.0, _range_factor(r_p) / _range_factor(r_c[idx]))
    return pts[keep], rad[keep], idx[keep]


def _sample_discs(rng, plan: _Plan, k: int, c, n, r, *, two_sided=True):
    """Points on planar discs (leaves, wheel faces) seen from pass ``k``."""
    v = _sensor(plan, c[:, 0], k) - c
    r_c = np.linalg.norm(v, axis=1)
    cos_i = np.sum(v * n, axis=1) / np.maximum(r_c, 1e-9)
    cos_i = np.abs(cos_i) if two_sided else np.maximum(cos_i, 0.0)
    cnt = rng.poisson(plan.rho * _range_factor(r_c) * np.pi * r**2 * cos_i)
    idx = np.repeat(np.arange(len(c)), cnt)
    ni = n[idx]
    e1 = _perpendicular(ni, rng)
    e2 = np.cross(ni, e1)
    rho = r[idx] * np.sqrt(rng.random(len(idx)))
    psi = rng.uniform(0, 2 * np.pi, len(idx))
    pts = c[idx] + rho[:, None] * (np.cos(psi)[:, None] * e1 + np.sin(psi)[:, None] * e2)
    return pts, idx


def _sample_rects(rng, plan: _Plan, k: int, corner, u, v):
    """Points on opaque rectangles ``corner + s*u + t*v`` (s, t in [0, 1]) whose normal
    u x v faces the sensor of pass ``k``; large faces must be pre-split into tiles."""
    nrm = np.cross(u, v)
    area = np.linalg.norm(nrm, axis=1)
    nrm = nrm / np.maximum(area, 1e-12)[:, None]
    c = corner + 0.5 * (u + v)
    w = _sensor(plan, c[:, 0], k) - c
    r_c = np.linalg.norm(w, axis=1)
    cos_i = np.maximum(np.sum(w * nrm, axis=1) / np.maximum(r_c, 1e-9), 0.0)
    cnt = rng.poisson(plan.rho * _range_factor(r_c) * area * cos_i)
    idx = np.repeat(np.arange(len(c)), cnt)
    s, t = rng.random(len(idx)), rng.random(len(idx))
    return corner[idx] + s[:, None] * u[idx] + t[:, None] * v[idx]


@dataclass
class _Chunk:
    xyz: list = field(default_factory=list)
    tree_id: list = field(default_factory=list)
    is_wood: list = field(default_factory=list)
    kind: list = field(default_factory=list)

    def add(self, plan, rng, k, pts, tree_id, is_wood, kind, h=None):
        """Occlusion test, then noise and the pass's ghosting shift. ``h``: heights of
        the points above the ground, when known."""
        if len(pts) == 0:
            return
        keep = rng.random(len(pts)) < _transmittance(plan, pts, k, h)
        n = int(keep.sum())
        pts = pts[keep] + plan.pass_shift[k] + rng.normal(0.0, plan.params.noise, (n, 3))
        self.xyz.append(pts)
        self.tree_id.append(np.broadcast_to(np.asarray(tree_id, dtype=np.int64), keep.shape)[keep])
        self.is_wood.append(np.broadcast_to(np.asarray(is_wood, dtype=bool), keep.shape)[keep])
        self.kind.append(np.broadcast_to(np.asarray(kind, dtype=np.uint8), keep.shape)[keep])

    def finish(self, plan: _Plan, rng, base_xy: np.ndarray | None = None) -> Orchard:
        """The chunk's points in absolute block coordinates, with outliers; ``base_xy``:
        the trunk position of the tree the chunk holds (it moves rigidly with its row)."""
        p = plan.params
        xyz = np.concatenate(self.xyz) if self.xyz else np.empty((0, 3))
        tid = np.concatenate(self.tree_id) if self.tree_id else np.empty(0, np.int64)
        wood = np.concatenate(self.is_wood) if self.is_wood else np.empty(0, bool)
        kind = np.concatenate(self.kind) if self.kind else np.empty(0, np.uint8)
        n_out = int(rng.poisson(p.outliers * len(xyz)))
        if n_out:
            x0, x1, y0, y1 = plan.bounds
            ox = rng.uniform(x0, x1, n_out)
            oy = rng.uniform(y0, y1, n_out)
            oz = plan.ground.z(ox, oy) + rng.uniform(-0.5, plan.z_top + 2.0, n_out)
            xyz = np.vstack([xyz, np.c_[ox, oy, oz]])
            tid = np.concatenate([tid, np.zeros(n_out, np.int64)])
            wood = np.concatenate([wood, np.zeros(n_out, bool)])
            kind = np.concatenate([kind, np.full(n_out, OUTLIER, np.uint8)])
        xyz = place(p, xyz, base_xy)
        return Orchard(xyz + plan.offset(), tid, wood, kind, plan.trunks + plan.offset(), plan.trunk_radius.copy(),
                       p.epsg, **plan.addresses)


def _tree_chunk(plan: _Plan, t: int) -> Orchard:
    """Points of tree ``t`` (0-based; id ``t + 1``)."""
    p = plan.params
    i = int(plan.layout.trees[t])
    tree = grow_tree(_tree_rng(p.seed, i), p, plan.tree_xy[i], plan.ground, scale=plan.scale[t])
    rng = np.random.default_rng([p.seed, 2, i])
    ch = _Chunk()
    for k in _passes_for(plan, tree.base[1]):
        pts, rad, _ = _sample_cylinders(rng, plan, k, tree.cyl_a, tree.cyl_b, tree.cyl_ra, tree.cyl_rb)
        h = pts[:, 2] - plan.ground.z(pts[:, 0], pts[:, 1])
        above = h >= 0.0  # the trunk starts below the ground
        pts, rad, h = pts[above], rad[above], h[above]
        wood = rad >= WOOD_RADIUS
        ch.add(plan, rng, k, pts, t + 1, wood, np.where(wood, WOOD, TWIG), h=h)
        pts, _ = _sample_discs(rng, plan, k, tree.leaf_c, tree.leaf_n, tree.leaf_r)
        ch.add(plan, rng, k, pts, t + 1, False, LEAF)
    return ch.finish(plan, rng, tree.base[:2])


def _ground_chunk(plan: _Plan, k: int, xa: float, xb: float, j: int) -> Orchard:
    """Ground and grass seen from pass ``k`` between along-track coordinates xa and xb.

    Strategy: on flat ground the density at lateral offset d from the path is
    rho * h / (d^2 + h^2)^(3/2) (1/r^2 times the cosine of incidence), whose integral
    F(d) = d / (h sqrt(d^2 + h^2)) inverts in closed form, so offsets are drawn exactly.
    """
    p = plan.params
    rng = np.random.default_rng([p.seed, 3, k, j])
    x0, x1, y0, y1 = plan.bounds
    yk = plan.pass_y[k]
    h = plan.pass_h[k]
    lo = max(y0 - yk, -p.row_spacing)
    hi = min(y1 - yk, p.row_spacing)
    ch = _Chunk()

    def F(d):
        return d / (h * np.sqrt(d * d + h * h))

    def Finv(f):
        q = np.clip(f * h, -0.999999, 0.999999)
        return h * q / np.sqrt(1.0 - q * q)

    for a, b in ((lo, -_BLIND), (_BLIND, hi)):
        if b <= a:
            continue
        mass = _GROUND_RETURN * plan.rho * _RANGE_REF**2 * (F(b) - F(a)) * (xb - xa)
        n = int(rng.poisson(mass))
        x = rng.uniform(xa, xb, n)
        d = Finv(rng.uniform(F(a), F(b), n))
        y = yk + d
        z = plan.ground.z(x, y)
        gh = plan.ground.grass_height(x, y, rng)
        pts = np.c_[x, y, z + gh]
        ch.add(plan, rng, k, pts, 0, False, np.where(gh > 0, GRASS, GROUND).astype(np.uint8), h=gh)
    # a few isolated points below the ground
    n_low = int(rng.poisson(2e-4 * sum(len(a) for a in ch.xyz)))
    if n_low:
        x = rng.uniform(xa, xb, n_low)
        y = rng.uniform(max(y0, yk - p.row_spacing), min(y1, yk + p.row_spacing), n_low)
        ch.xyz.append(np.c_[x, y, plan.ground.z(x, y) - rng.uniform(0.3, 1.2, n_low)])
        ch.tree_id.append(np.zeros(n_low, np.int64))
        ch.is_wood.append(np.zeros(n_low, bool))
        ch.kind.append(np.full(n_low, OUTLIER, np.uint8))
    return ch.finish(plan, rng)


def _box_faces(centre, size, yaw=0.0, tile=0.25):
    """Side and top faces of a box (bottom centre ``centre``, size (lx, ly, lz)) as
    outward-facing rectangle tiles: (corner, u, v) arrays with u x v outward."""
    lx, ly, lz = size
    c, s = np.cos(yaw), np.sin(yaw)
    ex, ey, ez = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
    faces = [  # (origin offset in box frame, u, v) with u x v outward
        ((lx / 2, -ly / 2, 0), ey * ly, ez * lz),  # +x
        ((-lx / 2, ly / 2, 0), -ey * ly, ez * lz),  # -x
        ((lx / 2, ly / 2, 0), -ex * lx, ez * lz),  # +y
        ((-lx / 2, -ly / 2, 0), ex * lx, ez * lz),  # -y
        ((-lx / 2, -ly / 2, lz), ex * lx, ey * ly),  # top
    ]
    corners, us, vs = [], [], []
    for (ox, oy, oz), u, v in faces:
        o = centre + ox * ex + oy * ey + oz * ez
        nu = max(1, int(np.ceil(np.linalg.norm(u) / tile)))
        nv = max(1, int(np.ceil(np.linalg.norm(v) / tile)))
        ii, jj = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
        corners.append(o + (ii.reshape(-1, 1) / nu) * u + (jj.reshape(-1, 1) / nv) * v)
        us.append(np.tile(u / nu, (nu * nv, 1)))
        vs.append(np.tile(v / nv, (nu * nv, 1)))
    return np.concatenate(corners), np.concatenate(us), np.concatenate(vs)


#: heights of a trellis's wires above the ground [m]
TRELLIS_WIRES = (0.8, 1.6, 2.4)


def _add_trellis(ch: _Chunk, plan: _Plan) -> None:
    """Trellis posts and wires in every row (``params.trellis``), as points of kind post."""
    p = plan.params
    rng = np.random.default_rng([p.seed, 5])  # its own stream: blocks without a trellis are unchanged
    for r in range(p.rows):
        # the row's planted slots (an empty slot keeps its place in the trellis)
        row = plan.tree_xy[r * p.trees_per_row : (r + 1) * p.trees_per_row][plan.layout.planted[plan.layout.row == r]]
        gaps = np.arange(0, len(row) - 1, p.trellis)
        xs = np.concatenate([[row[0, 0] - p.spacing / 2], (row[gaps, 0] + row[gaps + 1, 0]) / 2, [row[-1, 0] + p.spacing / 2]])
        # on the row's line through its trees
        ys = (np.interp(xs, row[:, 0], row[:, 1]) if len(row) > 1 else np.full(len(xs), row[0, 1]))
        ys = ys + rng.normal(0, 0.03, len(xs))
        ht = rng.uniform(2.8, 3.2, len(xs))
        rp = rng.uniform(0.05, 0.065, len(xs))
        _add_posts(ch, plan, rng, xs, ys, ht, rp, wires=TRELLIS_WIRES, y=float(np.mean(ys)))


def _add_posts(ch: _Chunk, plan: _Plan, rng, xs, ys, height, radius, *, wires, y: float) -> None:
    """Posts of ``height`` and ``radius`` (p,) [m] standing at ``xs``, ``ys`` (p,) (tops
    leaning by about 2 cm), wires at ``wires`` [m] above the ground between consecutive
    posts, seen from the passes near ``y``; points of kind post."""
    g = plan.ground
    zb = g.z(xs, ys)
    a = np.c_[xs, ys, zb - 0.05]
    b = np.c_[xs + rng.normal(0, 0.02, len(xs)), ys + rng.normal(0, 0.02, len(xs)), zb + height]
    wa = np.vstack([np.c_[xs[:-1], ys[:-1], zb[:-1] + h] for h in wires])
    wb = np.vstack([np.c_[xs[1:], ys[1:], zb[1:] + h] for h in wires])
    ca, cb = np.vstack([a, wa]), np.vstack([b, wb])
    cr = np.concatenate([radius, np.full(len(wa), 0.002)])
    for k in _passes_for(plan, y):
        pts, _, _ = _sample_cylinders(rng, plan, k, ca, cb, cr, cr)
        pts = pts[pts[:, 2] >= g.z(pts[:, 0], pts[:, 1])]
        ch.add(plan, rng, k, pts, 0, False, POST)


def _objects_chunk(plan: _Plan) -> Orchard:
    """Fence posts and wire, trellis posts and wires (when asked for), the vehicle and the bin."""
    p = plan.params
    rng = np.random.default_rng([p.seed, 4])
    g = plan.ground
    x0, x1, y0, y1 = plan.bounds
    ch = _Chunk()
    if p.posts:
        y_f = plan.pass_y[0] - 2.5
        xs = np.arange(x0 + 1.0, x1 - 0.5, 3.0) + rng.normal(0, 0.08, len(np.arange(x0 + 1.0, x1 - 0.5, 3.0)))
        ys = y_f + rng.normal(0, 0.03, len(xs))
        ht = rng.uniform(1.2, 1.8, len(xs))
        rp = rng.uniform(0.04, 0.06, len(xs))
        _add_posts(ch, plan, rng, xs, ys, ht, rp, wires=(1.0,), y=y_f)  # one wire ~1.0 m high
    if p.trellis:
        _add_trellis(ch, plan)
    boxes = []
    if p.vehicle:  # parked in the far headland beside the first inner alley's path
        k_al = min(1, len(plan.pass_y) - 1)
        vx = x1 - _HEADLAND / 2
        vy = plan.pass_y[k_al] + 2.2
        boxes.append((np.array([vx, vy]), (3.5, 1.7, 1.35), 0.45, True))
    if p.bin:
        bx = x0 + _HEADLAND / 2
        by = plan.pass_y[0] + 1.8
        boxes.append((np.array([bx, by]), (1.2, 1.2, 1.2), 0.0, False))
    for xy, size, lift, wheels in boxes:
        yaw = rng.normal(0, 0.05)
        zb = float(g.z(xy[0], xy[1]))
        corner, u, v = _box_faces(np.array([xy[0], xy[1], zb + lift]), size, yaw)
        if wheels:
            wr, ww = 0.35, 0.22
            c, s = np.cos(yaw), np.sin(yaw)
            ex, ey = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
            centres = np.array([np.r_[xy, zb + wr] + sx * 1.2 * ex + sy * (size[1] / 2 - ww / 2 + 0.02) * ey
                                for sx in (-1, 1) for sy in (-1, 1)])
            axis_dir = np.array([sy * ey for sx in (-1, 1) for sy in (-1, 1)])
            wa = centres - axis_dir * ww / 2
            wb = centres + axis_dir * ww / 2
        for k in _passes_for(plan, xy[1]):
            pts = _sample_rects(rng, plan, k, corner, u, v)
            ch.add(plan, rng, k, pts, 0, False, VEHICLE)
            if wheels:
                pts, _, _ = _sample_cylinders(rng, plan, k, wa, wb, np.full(4, wr), np.full(4, wr))
                ch.add(plan, rng, k, pts, 0, False, VEHICLE)
                pts, _ = _sample_discs(rng, plan, k, wb, axis_dir, np.full(4, wr), two_sided=False)
                ch.add(plan, rng, k, pts, 0, False, VEHICLE)
    return ch.finish(plan, rng)


# --------------------------------------------------------------------------- public API


def iter_simulation(params: SimulationParams, *, ground_chunk_length: float = 25.0) -> Iterator[Orchard]:
    """Generate a block chunk by chunk: one chunk per tree, then ground strips, then
    the distractors. Memory is bounded by one chunk (plus a coarse leaf-area grid).

    Parameters
    ----------
    params : SimulationParams
    ground_chunk_length : float
        Along-track length [m] of one ground chunk.

    Yields
    ------
    Orchard
        A chunk of points; ``trunks`` and ``trunk_radius`` are those of the whole block
        in every chunk. Concatenating the chunks gives :func:`simulate_orchard`'s block.
    """
    plan = _plan(params)
    for t in range(len(plan.trunks)):
        yield _tree_chunk(plan, t)
    x0, x1, _, _ = plan.bounds
    edges = np.arange(x0, x1, ground_chunk_length).tolist() + [x1]
    for k in range(len(plan.pass_y)):
        for j, (xa, xb) in enumerate(zip(edges[:-1], edges[1:])):
            yield _ground_chunk(plan, k, xa, xb, j)
    yield _objects_chunk(plan)


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


def simulate_orchard(params: SimulationParams | None = None) -> Orchard:
    """Generate a whole block in memory (see the module docstring for the model).

    Parameters
    ----------
    params : SimulationParams, optional
        Defaults to ``SimulationParams()`` (2 rows of 5 trees, 5 m x 6 m).

    Returns
    -------
    Orchard
        Points (n, 3) in absolute coordinates [m] with per-point truth and trunk bases.
    """
    return concatenate(iter_simulation(params or SimulationParams()))


def ground_height(params: SimulationParams, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The simulated ground's true height [m] at (x, y), in the block's absolute
    coordinates (those of :func:`simulate_orchard`'s points).

    For benchmarks that hand a peer the true terrain, e.g. a ground mesh for
    raycloudtools' ``rayextract trees``. The ground is the first thing the block's plan
    draws, so it is rebuilt here from the seed without growing the trees.
    """
    ground = _Ground.make(params, np.random.default_rng([params.seed, 0]))
    off = _offset(params)
    # the ground is bent and turned with the rows: look it up in the straight frame
    xs, ys = unplace_xy(params, np.asarray(x, dtype=np.float64) - off[0], np.asarray(y, dtype=np.float64) - off[1])
    return ground.z(xs, ys) + off[2]


# --------------------------------------------------------------------------- files

TRUTH_COLUMNS = ("point_index", "tree_id", "is_wood", "kind")


def write_simulation(source: Orchard | SimulationParams | Iterable[Orchard], las_path: str, truth_path: str) -> dict:
    """Write a block as LAS/LAZ (``.laz`` compresses) and its truth as Parquet.

    Parameters
    ----------
    source : Orchard, SimulationParams or iterable of Orchard chunks
        A block in memory, or parameters / chunks to stream (bounded memory).
    las_path, truth_path : str
        Outputs; written to temporary names and renamed, so nothing partial is left.

    Returns
    -------
    dict
        ``n_points``, ``n_trees``, ``crs_epsg``.

    Notes
    -----
    The truth file has one row per point in file order: ``point_index`` (uint64),
    ``tree_id`` (int64, 0 = not a tree), ``is_wood`` (bool), ``kind`` (uint8 code into
    :data:`KIND`). Its key-value metadata holds ``orchard:trunks`` (JSON list of absolute
    [x, y, z] trunk bases, tree ``k`` at position ``k-1``), ``orchard:trunk_radius``,
    ``orchard:kinds`` and ``orchard:crs_epsg``; for a generated block also the layout
    (:func:`read_truth_layout`): ``orchard:tree_rows``, ``orchard:tree_slots``,
    ``orchard:tree_young``, ``orchard:empty_slots``, ``orchard:spacing`` and
    ``orchard:row_spacing``.
    """
    from pipeline.io import LasBlockWriter, TruthParquetWriter

    if isinstance(source, Orchard):
        chunks: Iterable[Orchard] = [source]
    elif isinstance(source, SimulationParams):
        chunks = iter_simulation(source)
    else:
        chunks = source
    truth = None
    n = 0
    n_trees = 0
    epsg = None
    las = None
    try:
        for ch in chunks:
            if las is None:
                epsg = ch.crs_epsg
                n_trees = len(ch.trunks)
                offsets = tuple(float(np.floor(v)) for v in ch.trunks.min(axis=0)) if n_trees else (0.0, 0.0, 0.0)
                las = LasBlockWriter(las_path, crs_epsg=ch.crs_epsg, offsets=offsets)
                truth = TruthParquetWriter(
                    truth_path,
                    metadata={
                        "orchard:trunks": json.dumps(np.round(ch.trunks, 6).tolist()),
                        "orchard:trunk_radius": json.dumps(np.round(ch.trunk_radius, 6).tolist()),
                        "orchard:kinds": json.dumps(list(KIND)),
                        "orchard:crs_epsg": str(ch.crs_epsg),
                        **_layout_metadata(ch),
                    },
                )
            m = ch.n_points
            if m == 0:
                continue
            las.write(ch.xyz)
            truth.write(np.arange(n, n + m, dtype=np.uint64), ch.tree_id, ch.is_wood, ch.kind)
            n += m
        if las is None:
            raise ValueError("nothing to write: the simulation produced no chunks")
        if n == 0:  # a file no command reads (`orchard process` refuses it as empty)
            from pipeline.errors import ParameterError

            raise ParameterError("the simulation made no points (density too low); raise --density")
        truth.close()
        las.close()
    except BaseException:
        for w in (truth, las):
            if w is not None:
                w.abort()
        raise
    return {"n_points": n, "n_trees": n_trees, "crs_epsg": epsg}


def read_truth(path: str) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Read a truth file written by :func:`write_simulation`.

    Returns
    -------
    columns : dict of str to ndarray
        ``point_index`` (n,) uint64, ``tree_id`` (n,) int64, ``is_wood`` (n,) bool,
        ``kind`` (n,) uint8, sorted by point_index; plus ``trunk_radius`` (k,) float64.
    trunks : (k, 3) float64
        Absolute trunk base centres [m]; tree ``k`` is ``trunks[k-1]``.
    """
    from pipeline.errors import InputError
    from pipeline.io import read_parquet_columns

    table, meta = read_parquet_columns(path, what="truth file")
    if b"orchard:trunks" not in meta or any(c not in table for c in TRUTH_COLUMNS):
        raise InputError(f"{path} is not an orchard truth file (run `orchard simulate --truth ...`)")
    cols = {c: table[c] for c in TRUTH_COLUMNS}
    if len(cols["point_index"]) and np.any(np.diff(cols["point_index"].astype(np.int64)) < 0):
        order = np.argsort(cols["point_index"], kind="stable")
        cols = {c: v[order] for c, v in cols.items()}
    trunks = np.asarray(json.loads(meta[b"orchard:trunks"]), dtype=np.float64).reshape(-1, 3)
    cols["trunk_radius"] = np.asarray(json.loads(meta.get(b"orchard:trunk_radius", b"[]")), dtype=np.float64)
    return cols, trunks


def _layout_metadata(o: Orchard) -> dict[str, str]:
    """The truth file's layout keys (none for a block without a layout)."""
    out = {}
    if o.tree_row is not None:
        out["orchard:tree_rows"] = json.dumps(np.asarray(o.tree_row, dtype=np.int64).tolist())
    if o.tree_slot is not None:
        out["orchard:tree_slots"] = json.dumps(np.asarray(o.tree_slot, dtype=np.int64).tolist())
    if o.tree_young is not None:
        out["orchard:tree_young"] = json.dumps(np.asarray(o.tree_young, dtype=bool).tolist())
    if o.empty_slots is not None:
        e = np.asarray(o.empty_slots, dtype=np.float64).reshape(-1, 4)
        out["orchard:empty_slots"] = json.dumps([[int(r), int(s), round(float(x), 6), round(float(y), 6)] for r, s, x, y in e])
    if o.spacing is not None:
        out["orchard:spacing"] = json.dumps(float(o.spacing))
    if o.row_spacing is not None:
        out["orchard:row_spacing"] = json.dumps(float(o.row_spacing))
    return out


def read_truth_layout(path: str) -> dict:
    """The planting layout stored in a truth file by :func:`write_simulation`.

    Returns
    -------
    dict
        ``tree_row`` (k,) int64 and ``tree_slot`` (k,) int64 (1-based; tree ``k`` at
        position ``k-1``), ``tree_young`` (k,) bool, ``empty_slots`` (e, 4) float64 rows of
        ``[row, slot, x, y]`` (absolute slot centre [m]), ``spacing`` and ``row_spacing``
        [m]. Keys a file lacks (written before layouts were recorded) are ``None``, and
        ``empty_slots`` is then an empty (0, 4) array.

    Raises
    ------
    InputError
        The file is missing, not Parquet, or not a truth file.
    """
    from pipeline.errors import InputError
    from pipeline.io import read_parquet_columns

    _, meta = read_parquet_columns(path, [], what="truth file")
    if b"orchard:trunks" not in meta:
        raise InputError(f"{path} is not an orchard truth file (run `orchard simulate --truth ...`)")

    def get(key, dtype):
        raw = meta.get(key.encode())
        return None if raw is None else np.asarray(json.loads(raw), dtype=dtype)

    empty = get("orchard:empty_slots", np.float64)
    spacing = get("orchard:spacing", np.float64)
    row_spacing = get("orchard:row_spacing", np.float64)
    return {
        "tree_row": get("orchard:tree_rows", np.int64),
        "tree_slot": get("orchard:tree_slots", np.int64),
        "tree_young": get("orchard:tree_young", bool),
        "empty_slots": np.empty((0, 4)) if empty is None else empty.reshape(-1, 4),
        "spacing": None if spacing is None else float(spacing),
        "row_spacing": None if row_spacing is None else float(row_spacing),
    }
