"""Orchard simulator: branching trees in rows, scanned from the alleys, with ground truth.

A generated block is the test bench for every accuracy figure, so it is built to be
hard in the ways real mobile captures are hard:

- rows of trees along x with jittered positions, on sloping, gently undulating ground
  with patchy grass and a few points below the ground;
- trees with a real branching structure: a slightly leaning trunk that branches low
  (0.4-0.9 m), 3-5 scaffolds and 3 recursive sub-levels tapering to ~1 cm twigs that
  reach a crown envelope wide enough for neighbouring crowns to overlap; leaf clusters
  (small discs) fill mostly the outer shell of the crown; optionally drooping branches
  whose leaves hang down to 0.2-0.5 m above the ground (``low_foliage``);
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

All lengths are metres. The local frame has the first tree of the first row at the
origin; absolute coordinates add ``(easting, northing, elevation)``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.special import ndtri

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

    rows: int = Field(2, ge=1, le=500, description="number of tree rows (rows run along x)")
    trees_per_row: int = Field(5, ge=1, le=2000, description="trees in each row")
    spacing: float = Field(5.0, ge=1.0, le=20.0, description="distance between trees in a row [m]")
    row_spacing: float = Field(6.0, ge=2.0, le=30.0, description="distance between rows [m]")
    position_jitter: float = Field(0.15, ge=0.0, le=1.0, description="standard deviation of tree positions around the grid [m]")
    noise: float = Field(0.02, ge=0.0, le=0.1, description="standard deviation of the Gaussian range noise [m]")
    seed: int = Field(0, ge=0, le=2**32 - 1, description="random seed; the same seed gives the same block")
    density: float = Field(1.0, gt=0.0, le=1000.0, description="scale of the point density (1 = about 40-80 k points per tree)")
    crown_radius: float | None = Field(None, gt=0.2, le=15.0, description="crown radius along the row [m]; default 0.55 x spacing")
    tree_height: float | None = Field(None, gt=1.0, le=30.0, description="tree height [m]; default random 3.5-4.5 per tree")
    trunk_radius: float | None = Field(None, gt=0.01, le=1.0, description="trunk radius [m]; default random 0.06-0.15 per tree")
    low_foliage: bool = Field(False, description="drooping outer branches, leaves down to 0.2-0.5 m above the ground")
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

    @model_validator(mode="after")
    def _sizes(self) -> "SimulationParams":
        if self.rows * self.trees_per_row > 200_000:
            raise ValueError(f"{self.rows * self.trees_per_row} trees is too many (at most 200000)")
        if self.crown_radius is not None and self.crown_radius > 2.0 * self.spacing:
            raise ValueError(f"crown_radius ({self.crown_radius} m) above twice the spacing ({self.spacing} m)")
        return self

    @property
    def n_trees(self) -> int:
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
    """

    xyz: np.ndarray
    tree_id: np.ndarray
    is_wood: np.ndarray
    kind: np.ndarray
    trunks: np.ndarray
    trunk_radius: np.ndarray
    crs_epsg: int = 28356

    @property
    def n_points(self) -> int:
        return int(self.xyz.shape[0])


# --------------------------------------------------------------------------- geometry


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def _perpendicular(u: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random unit vectors perpendicular to the unit vectors ``u`` (m, 3)."""
    r = rng.normal(size=u.shape)
    r -= np.sum(r * u, axis=1, keepdims=True) * u
    bad = np.linalg.norm(r, axis=1) < 1e-6
    if bad.any():
        r[bad] = np.cross(u[bad], [1.0, 0.0, 0.0])
    return _unit(r)


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


@dataclass
class _Envelope:
    """Crown envelope: two half-ellipsoids (upper, lower) sharing their equator."""

    centre: np.ndarray  # (3,)
    rx: float
    ry: float
    c_up: float
    c_lo: float

    def inside(self, q: np.ndarray) -> np.ndarray:
        d = q - self.centre
        c = np.where(d[..., 2] > 0, self.c_up, self.c_lo)
        return (d[..., 0] / self.rx) ** 2 + (d[..., 1] / self.ry) ** 2 + (d[..., 2] / c) ** 2 <= 1.0

    def distance(self, p: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Distance [m] from points ``p`` (m,3) along unit directions ``d`` to the envelope
        (0 for points outside). The envelope is convex, so bisection is exact."""
        lo = np.zeros(len(p))
        hi = np.full(len(p), 2.5 * max(self.rx, self.ry, self.c_up + self.c_lo))
        inside0 = self.inside(p)
        for _ in range(24):
            mid = 0.5 * (lo + hi)
            ins = self.inside(p + mid[:, None] * d)
            lo = np.where(ins, mid, lo)
            hi = np.where(ins, hi, mid)
        return np.where(inside0, lo, 0.0)


# --------------------------------------------------------------------------- trees


@dataclass
class _Tree:
    """Surface elements of one tree (local frame)."""

    cyl_a: np.ndarray  # (m, 3) segment start
    cyl_b: np.ndarray  # (m, 3) segment end
    cyl_ra: np.ndarray  # (m,) radius at start
    cyl_rb: np.ndarray  # (m,) radius at end
    leaf_c: np.ndarray  # (q, 3) leaf disc centres
    leaf_n: np.ndarray  # (q, 3) unit normals
    leaf_r: np.ndarray  # (q,) disc radii
    base: np.ndarray  # (3,) trunk centre at ground level
    trunk_radius: float  # at 0.3 m above base
    top: float  # highest z


@dataclass
class _Branches:
    a: list = field(default_factory=list)
    b: list = field(default_factory=list)
    ra: list = field(default_factory=list)
    rb: list = field(default_factory=list)

    def add(self, a, b, ra, rb):
        self.a.append(a)
        self.b.append(b)
        self.ra.append(ra)
        self.rb.append(rb)

    def arrays(self):
        return (np.concatenate(self.a), np.concatenate(self.b), np.concatenate(self.ra), np.concatenate(self.rb))


def _polylines(rng, p0, d, length, r0, r1, *, n_sub=3, bend=0.12, lift=0.0):
    """Branches as bent polylines. Returns nodes (m, n_sub+1, 3) and radii (m, n_sub+1)."""
    m = len(p0)
    nodes = np.empty((m, n_sub + 1, 3))
    nodes[:, 0] = p0
    cur = d.copy()
    step = (length / n_sub)[:, None]
    for k in range(n_sub):
        cur = _unit(cur + bend * rng.normal(size=(m, 3)) + np.array([0.0, 0.0, lift]))
        nodes[:, k + 1] = nodes[:, k] + step * cur
    frac = np.linspace(0.0, 1.0, n_sub + 1)
    radii = r0[:, None] + (r1 - r0)[:, None] * frac[None, :]
    return nodes, radii


def _add_polylines(br: _Branches, nodes, radii):
    br.add(
        nodes[:, :-1].reshape(-1, 3),
        nodes[:, 1:].reshape(-1, 3),
        radii[:, :-1].reshape(-1),
        radii[:, 1:].reshape(-1),
    )


def _points_on(nodes, radii, owner, t):
    """Position, direction and radius at fraction ``t`` along polylines ``owner``."""
    n_sub = nodes.shape[1] - 1
    s = np.clip(t, 0.0, 1.0 - 1e-9) * n_sub
    k = s.astype(np.int64)
    f = (s - k)[:, None]
    a = nodes[owner, k]
    b = nodes[owner, k + 1]
    pos = a + f * (b - a)
    rad = radii[owner, k] + f[:, 0] * (radii[owner, k + 1] - radii[owner, k])
    return pos, _unit(b - a), rad


def _children(rng, env, axis_xy, nodes, radii, *, n_lateral, t_min, angle, reach, radius_factor,
              out_bias, up_bias, min_len=0.08):
    """Spawn an apical and ``n_lateral`` (per parent) lateral children on parent polylines."""
    m = nodes.shape[0]
    owner = np.concatenate([np.arange(m), np.repeat(np.arange(m), n_lateral)])
    t = np.concatenate([np.ones(m), rng.uniform(t_min, 0.95, int(n_lateral.sum()))])
    pos, pdir, prad = _points_on(nodes, radii, owner, t)
    n = len(owner)
    apical = np.arange(n) < m
    alpha = np.where(apical, np.deg2rad(rng.uniform(0, 15, n)), np.deg2rad(rng.uniform(*angle, n)))
    w = _perpendicular(pdir, rng)
    d = np.cos(alpha)[:, None] * pdir + np.sin(alpha)[:, None] * w
    out = np.zeros((n, 3))
    out[:, :2] = pos[:, :2] - axis_xy
    out = _unit(out)
    d = _unit(d + out_bias * out + np.array([0.0, 0.0, up_bias]))
    dist = env.distance(pos, d)
    length = np.maximum(rng.uniform(*reach, n) * dist, min_len)
    r0 = np.maximum(prad * rng.uniform(*radius_factor, n), 0.004)
    return pos, d, length, r0


def _grow_tree(rng: np.random.Generator, p: SimulationParams, base_xy: np.ndarray, ground: _Ground) -> _Tree:
    """Branching structure and leaves of one tree (local frame)."""
    gz = float(ground.z(base_xy[0], base_xy[1]))
    base = np.array([base_xy[0], base_xy[1], gz])
    height = (p.tree_height * rng.uniform(0.95, 1.05)) if p.tree_height else rng.uniform(3.5, 4.5)
    r_t = (p.trunk_radius * rng.uniform(0.9, 1.1)) if p.trunk_radius else rng.uniform(0.06, 0.15)
    r_crown = (p.crown_radius if p.crown_radius else 0.55 * p.spacing) * rng.uniform(0.95, 1.05)
    # the envelope is slightly wider than the crown radius: twigs and leaves fill it only sparsely at the rim
    rx = 1.12 * r_crown
    ry = 1.08 * min(r_crown, 0.36 * p.row_spacing) * rng.uniform(0.95, 1.05)
    h_branch = rng.uniform(0.4, 0.9)
    crown_base = h_branch - 0.15  # envelope bottom just below the branching point
    # lean
    lean = np.deg2rad(rng.uniform(0.0, 4.0))
    az = rng.uniform(0, 2 * np.pi)
    d0 = np.array([np.sin(lean) * np.cos(az), np.sin(lean) * np.sin(az), np.cos(lean)])
    trunk_len = (h_branch + 0.1) / d0[2]
    a0 = base - 0.1 / d0[2] * d0
    top0 = a0 + trunk_len * d0
    zc = gz + crown_base + 0.45 * (height - crown_base)
    env = _Envelope(centre=np.array([top0[0], top0[1], zc]), rx=rx, ry=ry, c_up=gz + height - zc, c_lo=zc - gz - crown_base)
    axis_xy = top0[:2]

    br = _Branches()
    ra_t, rb_t = r_t * 1.08, r_t * 0.85
    br.add(a0[None], top0[None], np.array([ra_t]), np.array([rb_t]))
    trunk_radius_03 = ra_t + (rb_t - ra_t) * (0.1 + 0.3) / (trunk_len * d0[2])

    # level 1: scaffolds (+ optional central leader)
    n_s = int(rng.integers(3, 6))
    # orchard trees are trained along the row: two scaffolds point along +x and -x (into
    # the neighbours' crowns), the others across the row
    side = rng.choice([-1.0, 1.0]) * np.pi / 2
    across = side + np.pi * np.arange(n_s - 2) + rng.uniform(-0.6, 0.6, n_s - 2)
    azs = np.concatenate([[0.0, np.pi], across]) + rng.normal(0, 0.2, n_s)
    pol = np.deg2rad(rng.uniform(30, 60, n_s))
    d1 = np.c_[np.sin(pol) * np.cos(azs), np.sin(pol) * np.sin(azs), np.cos(pol)]
    p1 = top0[None] + d0[None] * rng.uniform(-0.08, 0.15, n_s)[:, None]
    r1 = rb_t * rng.uniform(0.55, 0.75, n_s)
    if rng.random() < 0.6:  # central leader
        d1 = np.vstack([d1, _unit(np.array([[0, 0, 1.0]]) + rng.normal(0, 0.05, (1, 3)))])
        p1 = np.vstack([p1, top0[None]])
        r1 = np.append(r1, rb_t * rng.uniform(0.6, 0.75))
    len1 = np.maximum(env.distance(p1, d1) * rng.uniform(0.5, 0.7, len(p1)), 0.2)
    nodes1, rad1 = _polylines(rng, p1, d1, len1, r1, r1 * 0.6, bend=0.1, lift=0.05)
    _add_polylines(br, nodes1, rad1)

    # levels 2-3: recursive sub-branching towards the envelope
    nodes, rad = nodes1, rad1
    level_spec = [
        dict(n_lat=(3, 6), t_min=0.2, angle=(30, 65), reach=(0.5, 0.8), rf=(0.55, 0.75), out=0.25, up=0.1),
        dict(n_lat=(2, 5), t_min=0.25, angle=(30, 70), reach=(0.7, 0.95), rf=(0.5, 0.7), out=0.15, up=0.05),
    ]
    level_nodes = []
    for spec in level_spec:
        n_lat = rng.integers(spec["n_lat"][0], spec["n_lat"][1], len(nodes))
        pos, d, length, r0 = _children(rng, env, axis_xy, nodes, rad, n_lateral=n_lat, t_min=spec["t_min"],
                                       angle=spec["angle"], reach=spec["reach"], radius_factor=spec["rf"],
                                       out_bias=spec["out"], up_bias=spec["up"])
        nodes, rad = _polylines(rng, pos, d, length, r0, r0 * 0.6, bend=0.15)
        _add_polylines(br, nodes, rad)
        level_nodes.append((nodes, rad))

    # level 4: terminal twigs (not wood) reaching the envelope
    n_lat = rng.integers(2, 5, len(nodes))
    pos, d, length, _ = _children(rng, env, axis_xy, nodes, rad, n_lateral=n_lat, t_min=0.2, angle=(30, 75),
                                  reach=(0.92, 1.08), radius_factor=(1, 1), out_bias=0.1, up_bias=0.0, min_len=0.1)
    r_tw = rng.uniform(0.006, 0.011, len(pos))
    twig_nodes, twig_rad = _polylines(rng, pos, d, length, r_tw, np.full(len(pos), 0.004), n_sub=2, bend=0.2)
    _add_polylines(br, twig_nodes, twig_rad)

    # leaves along the outer parts of twigs and of the finest branches
    leaf_sets = [(twig_nodes, twig_rad, 0.1, 6.0), (level_nodes[-1][0], level_nodes[-1][1], 0.4, 2.0)]

    if p.low_foliage:
        # drooping shoots hanging from the lower, outer parts of the crown
        n3, r3 = level_nodes[-1]
        owner = np.arange(len(n3))
        pos, _, _ = _points_on(n3, r3, owner, rng.uniform(0.5, 1.0, len(owner)))
        horiz = np.hypot(pos[:, 0] - axis_xy[0], pos[:, 1] - axis_xy[1]) / max(rx, ry)
        ok = (pos[:, 2] < zc + 0.3) & (horiz > 0.35)
        cand = np.flatnonzero(ok)
        n_p = min(len(cand), int(rng.integers(18, 30)))
        if n_p:
            pick = rng.choice(cand, n_p, replace=False)
            start = pos[pick]
            out = np.zeros((n_p, 3))
            out[:, :2] = start[:, :2] - axis_xy
            out = _unit(out)
            dd = _unit(out * rng.uniform(0.25, 0.6, (n_p, 1)) + np.array([0.0, 0.0, -1.0]) + rng.normal(0, 0.12, (n_p, 3)))
            target = ground.z(start[:, 0], start[:, 1]) + rng.uniform(0.2, 0.5, n_p)
            length = np.maximum((start[:, 2] - target) / np.maximum(-dd[:, 2], 0.3), 0.1)
            pn, pr = _polylines(rng, start, dd, length, np.full(n_p, 0.009), np.full(n_p, 0.004), bend=0.08)
            # keep the shoot above its target height (the bends can push it lower)
            pn[:, :, 2] = np.maximum(pn[:, :, 2], target[:, None])
            _add_polylines(br, pn, pr)
            leaf_sets.append((pn, pr, 0.1, 15.0))

    leaf_scale = min(1.0, np.sqrt(min(rx, ry) / 2.5))
    lc, ln, lr = [], [], []
    for nd, rd, t0, rate in leaf_sets:
        seg_len = np.linalg.norm(np.diff(nd, axis=1), axis=2).sum(axis=1)
        # narrow crowns pack the same twigs into less room: fewer leaves per twig there
        cnt = rng.poisson(rate * leaf_scale * seg_len * (1.0 - t0))
        owner = np.repeat(np.arange(len(nd)), cnt)
        t = rng.uniform(t0, 1.0, len(owner))
        pos, _, _ = _points_on(nd, rd, owner, t)
        lc.append(pos + rng.normal(0.0, 0.07, pos.shape))
        ln.append(_unit(rng.normal(size=pos.shape) + np.array([0.0, 0.0, 0.4])))
        lr.append(rng.uniform(0.03, 0.06, len(owner)))
    a, b, ra, rb = br.arrays()
    leaf_c = np.concatenate(lc)
    top = float(max(np.max(b[:, 2]), np.max(leaf_c[:, 2]) if len(leaf_c) else -np.inf))
    return _Tree(a, b, ra, rb, leaf_c, np.concatenate(ln), np.concatenate(lr), base, float(trunk_radius_03), top)


# --------------------------------------------------------------------------- the block plan


@dataclass
class _Plan:
    params: SimulationParams
    ground: _Ground
    tree_xy: np.ndarray  # (k, 2) local
    bounds: tuple[float, float, float, float]  # x0, x1, y0, y1 local
    pass_y: np.ndarray  # (q,) alley centre lines
    pass_h: np.ndarray  # (q,) sensor height above ground
    pass_shift: np.ndarray  # (q, 3) ghosting offsets
    lad: np.ndarray  # (nx, ny, nh) leaf area density [m^2/m^3], flattened C order
    grid_shape: tuple[int, int, int]
    grid_origin: np.ndarray  # (3,) x, y, h
    trunks: np.ndarray  # (k, 3) local
    trunk_radius: np.ndarray  # (k,)
    z_top: float  # highest tree point above ground (max)
    rho: float
    profile_x: np.ndarray  # (m,) along-track stations of the sensor height profiles
    pass_z: np.ndarray  # (q, m) sensor z of each pass at profile_x

    def offset(self) -> np.ndarray:
        return _offset(self.params)


def _offset(p: SimulationParams) -> np.ndarray:
    """Absolute coordinates of the block's local origin."""
    return np.array([p.easting, p.northing, p.elevation])


def _tree_rng(seed: int, i: int) -> np.random.Generator:
    return np.random.default_rng([seed, 1, i])


def _plan(p: SimulationParams) -> _Plan:
    rng = np.random.default_rng([p.seed, 0])
    ground = _Ground.make(p, rng)
    r_idx, t_idx = np.divmod(np.arange(p.n_trees), p.trees_per_row)
    tree_xy = np.c_[t_idx * p.spacing, r_idx * p.row_spacing] + rng.normal(0.0, p.position_jitter, (p.n_trees, 2))
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
    trunks = np.empty((p.n_trees, 3))
    trunk_r = np.empty(p.n_trees)
    z_top = 0.0
    for i in range(p.n_trees):
        tree = _grow_tree(_tree_rng(p.seed, i), p, tree_xy[i], ground)
        trunks[i] = tree.base
        trunk_r[i] = tree.trunk_radius
        z_top = max(z_top, tree.top - tree.base[2])
        c = tree.leaf_c
        h = c[:, 2] - ground.z(c[:, 0], c[:, 1])
        flat = _grid_index(np.c_[c[:, :2], h], origin, shape)
        lad += np.bincount(flat, weights=np.pi * tree.leaf_r**2, minlength=lad.size).astype(np.float32)
    lad /= _VOXEL**3
    profile_x = np.arange(x0 - 2.0, x1 + 2.0, 0.1)
    pass_z = np.stack([ground.z(profile_x, np.full(len(profile_x), yk)) + hk for yk, hk in zip(pass_y, pass_h)])
    return _Plan(p, ground, tree_xy, (x0, x1, y0, y1), pass_y, pass_h, shift, lad, shape, origin, trunks, trunk_r,
                 z_top, _RHO * p.density, profile_x, pass_z)


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

    def finish(self, plan: _Plan, rng) -> Orchard:
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
        return Orchard(xyz + plan.offset(), tid, wood, kind, plan.trunks + plan.offset(), plan.trunk_radius.copy(),
                       p.epsg)


def _tree_chunk(plan: _Plan, i: int) -> Orchard:
    p = plan.params
    tree = _grow_tree(_tree_rng(p.seed, i), p, plan.tree_xy[i], plan.ground)
    rng = np.random.default_rng([p.seed, 2, i])
    ch = _Chunk()
    for k in _passes_for(plan, tree.base[1]):
        pts, rad, _ = _sample_cylinders(rng, plan, k, tree.cyl_a, tree.cyl_b, tree.cyl_ra, tree.cyl_rb)
        h = pts[:, 2] - plan.ground.z(pts[:, 0], pts[:, 1])
        above = h >= 0.0  # the trunk starts below the ground
        pts, rad, h = pts[above], rad[above], h[above]
        wood = rad >= WOOD_RADIUS
        ch.add(plan, rng, k, pts, i + 1, wood, np.where(wood, WOOD, TWIG), h=h)
        pts, _ = _sample_discs(rng, plan, k, tree.leaf_c, tree.leaf_n, tree.leaf_r)
        ch.add(plan, rng, k, pts, i + 1, False, LEAF)
    return ch.finish(plan, rng)


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
        row = plan.tree_xy[r * p.trees_per_row : (r + 1) * p.trees_per_row]
        gaps = np.arange(0, p.trees_per_row - 1, p.trellis)
        xs = np.concatenate([[row[0, 0] - p.spacing / 2], (row[gaps, 0] + row[gaps + 1, 0]) / 2, [row[-1, 0] + p.spacing / 2]])
        # on the row's line through its trees
        ys = (np.interp(xs, row[:, 0], row[:, 1]) if p.trees_per_row > 1 else np.full(len(xs), row[0, 1]))
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
    for i in range(params.n_trees):
        yield _tree_chunk(plan, i)
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
    return ground.z(np.asarray(x, dtype=np.float64) - off[0], np.asarray(y, dtype=np.float64) - off[1]) + off[2]


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
    ``orchard:kinds`` and ``orchard:crs_epsg``.
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
