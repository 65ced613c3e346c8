"""The mobile scanner: what a sensor driving every alley sees of a surface.

Point density falls with range (1/r^2) and with the cosine of incidence, only surfaces
facing the sensor are seen, and leaves occlude what lies behind them (Beer-Lambert
attenuation through the plan's leaf-area grid); every kept point gets Gaussian noise and
its pass's ghosting shift, and every chunk random outliers in the block volume.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simulator.branches import perpendicular, unit
from simulator.orchard import OUTLIER, Orchard
from simulator.plan import VOXEL, Plan
from simulator.planting import place

RANGE_REF = 1.0
"""Reference range [m] at which the plan's point density ``rho`` applies."""
_RANGE_MIN = 0.8  # closer than this the density stops growing [m]
_CLUMPING = 2.0  # a leaf cluster occludes about twice its sampled disc area (several leaves)


def _sensor(plan: Plan, x: np.ndarray, k: int) -> np.ndarray:
    """Sensor positions (n, 3) of pass ``k`` at the along-track coordinates ``x``
    (the scan plane is perpendicular to the driving direction)."""
    x = np.asarray(x, dtype=np.float64)
    z = np.interp(x, plan.profile_x, plan.pass_z[k])
    return np.c_[x, np.full(len(x), plan.pass_y[k]), z]


def _range_factor(r: np.ndarray) -> np.ndarray:
    """Point density at range ``r`` [m] relative to that at ``RANGE_REF`` (1/r^2, capped near the sensor)."""
    return (RANGE_REF / np.maximum(r, _RANGE_MIN)) ** 2


def _transmittance(plan: Plan, pts: np.ndarray, k: int, h_p: np.ndarray | None = None) -> np.ndarray:
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
    gy0 = np.clip((pts[:, 1] - oy) / VOXEL, 0.0, ny - 1e-6)
    gh0 = np.clip((h_p - oh) / VOXEL, 0.0, nh - 1e-6)
    gy1 = min(max((plan.pass_y[k] - oy) / VOXEL, 0.0), ny - 1e-6)
    gh1 = min(max((plan.pass_h[k] - oh) / VOXEL, 0.0), nh - 1e-6)
    length = np.hypot(plan.pass_y[k] - pts[:, 1], plan.pass_h[k] - h_p)
    order = np.argsort(-length, kind="stable")
    L = length[order]
    gy0, gh0 = gy0[order], gh0[order]
    dgy, dgh = gy1 - gy0, gh1 - gh0
    cell0 = np.clip(((pts[order, 0] - ox) / VOXEL).astype(np.int64), 0, nx - 1) * (ny * nh)
    step = 0.6 * VOXEL
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


def passes_for(plan: Plan, y: float) -> np.ndarray:
    """Passes that see an object at lateral position ``y``: those within one row spacing."""
    return np.flatnonzero(np.abs(plan.pass_y - y) <= plan.params.row_spacing * 1.0001)


def sample_cylinders(rng, plan: Plan, k: int, a, b, ra, rb):
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
    e1 = unit(vp)
    e2 = np.cross(ui, e1)
    phi = np.arcsin(2.0 * rng.random(len(idx)) - 1.0)
    pts = axis_pt + rad[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    r_p = np.linalg.norm(vi, axis=1)
    keep = rng.random(len(idx)) < np.minimum(1.0, _range_factor(r_p) / _range_factor(r_c[idx]))
    return pts[keep], rad[keep], idx[keep]


def sample_discs(rng, plan: Plan, k: int, c, n, r, *, two_sided=True):
    """Points on planar discs (leaves, wheel faces) seen from pass ``k``."""
    v = _sensor(plan, c[:, 0], k) - c
    r_c = np.linalg.norm(v, axis=1)
    cos_i = np.sum(v * n, axis=1) / np.maximum(r_c, 1e-9)
    cos_i = np.abs(cos_i) if two_sided else np.maximum(cos_i, 0.0)
    cnt = rng.poisson(plan.rho * _range_factor(r_c) * np.pi * r**2 * cos_i)
    idx = np.repeat(np.arange(len(c)), cnt)
    ni = n[idx]
    e1 = perpendicular(ni, rng)
    e2 = np.cross(ni, e1)
    rho = r[idx] * np.sqrt(rng.random(len(idx)))
    psi = rng.uniform(0, 2 * np.pi, len(idx))
    pts = c[idx] + rho[:, None] * (np.cos(psi)[:, None] * e1 + np.sin(psi)[:, None] * e2)
    return pts, idx


def sample_rects(rng, plan: Plan, k: int, corner, u, v):
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
class Chunk:
    """Points of one chunk of a block (a tree, a ground strip, the distractors) as they are seen."""

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

    def finish(self, plan: Plan, rng, base_xy: np.ndarray | None = None) -> Orchard:
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
