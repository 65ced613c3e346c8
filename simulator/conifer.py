"""The ``conifer`` tree form: a plantation conifer in a closed stand, and its forest floor.

Each tree is a straight bole 5-8 m tall, 10-24 cm thick at the ground, bare (self-pruned)
to 1.2-2.2 m; above that, whorls every 0.3-0.5 m of 4-6 branches sloping out and down,
shorter towards the top (a cone 1.1-1.4 times the spacing across at its base, so that
neighbouring crowns interlock), with needle clusters along their outer parts. Planted
2-2.5 m apart, a block of them is a closed canopy. The floor is rough: fallen branches
lie across it (:func:`debris`, points of kind ``grass``: low material in no tree). All
lengths are metres.
"""

from __future__ import annotations

import numpy as np

from simulator.branches import Tree, _add_polylines, _Branches, _points_on, _polylines, unit


def grow_conifer(rng: np.random.Generator, p, base_xy: np.ndarray, ground, scale: float = 1.0) -> Tree:
    """Bole, whorls and needles of one conifer; parameters of :func:`simulator.forms.grow_tree`."""
    gz = float(ground.z(base_xy[0], base_xy[1]))
    base = np.array([base_xy[0], base_xy[1], gz])
    height = ((p.tree_height * rng.uniform(0.95, 1.05)) if p.tree_height else rng.uniform(5.0, 8.0)) * scale
    r0 = ((p.trunk_radius * rng.uniform(0.9, 1.1)) if p.trunk_radius else rng.uniform(0.05, 0.12)) * scale
    reach = (p.crown_radius if p.crown_radius else rng.uniform(0.55, 0.7) * p.spacing) * scale
    br = _Branches()
    n_sub = 16
    lean = np.deg2rad(rng.uniform(0.0, 3.0))
    az = rng.uniform(0, 2 * np.pi)
    d0 = np.array([np.sin(lean) * np.cos(az), np.sin(lean) * np.sin(az), np.cos(lean)])
    s = np.linspace(-0.1, height, n_sub + 1)
    nodes = base[None] + s[:, None] * d0[None]
    nodes[3:, :2] += np.cumsum(rng.normal(0.0, 0.01, (n_sub - 2, 2)), axis=0)
    radii = r0 + (0.01 - r0) * np.clip(s / height, 0.0, 1.0)
    bole, bole_r = nodes[None], radii[None]
    _add_polylines(br, bole, bole_r)
    trunk_radius_03 = r0 + (0.01 - r0) * 0.3 / height
    # whorls from the crown base to near the top
    h0 = rng.uniform(1.2, 2.2) * scale
    hw = np.arange(h0, height - 0.3, rng.uniform(0.3, 0.5))
    per = rng.integers(4, 7, len(hw))
    h_br = np.repeat(hw, per)
    m = len(h_br)
    if m:
        pos, _, prad = _points_on(bole, bole_r, np.zeros(m, np.int64), (h_br + 0.1) / (height + 0.1))
        azs = rng.uniform(0, 2 * np.pi, m)
        pol = np.deg2rad(rng.uniform(70, 100, m))
        d = np.c_[np.sin(pol) * np.cos(azs), np.sin(pol) * np.sin(azs), np.cos(pol)]
        rel = (h_br - h0) / max(height - h0, 1e-6)
        length = reach * (1.0 - rel) ** 0.8 * rng.uniform(0.8, 1.1, m) + 0.15
        r_a = np.maximum(np.minimum(0.4 * prad, rng.uniform(0.008, 0.02, m)), 0.004)
        lat, lat_r = _polylines(rng, pos, d, length, r_a, np.full(m, 0.003), bend=0.1, lift=-0.03)
        _add_polylines(br, lat, lat_r)
        seg_len = np.linalg.norm(np.diff(lat, axis=1), axis=2).sum(axis=1)
        cnt = rng.poisson(25.0 * seg_len * 0.7)
        owner = np.repeat(np.arange(m), cnt)
        lp, _, _ = _points_on(lat, lat_r, owner, rng.uniform(0.3, 1.0, len(owner)))
        leaf_c = lp + rng.normal(0.0, 0.05, lp.shape)
        leaf_n = unit(rng.normal(size=lp.shape) + np.array([0.0, 0.0, 0.4]))
        leaf_r = rng.uniform(0.03, 0.05, len(owner))
    else:
        leaf_c, leaf_n, leaf_r = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    a, b, ra, rb = br.arrays()
    top = float(max(np.max(b[:, 2]), np.max(leaf_c[:, 2]) if len(leaf_c) else -np.inf))
    return Tree(a, b, ra, rb, leaf_c, leaf_n, leaf_r, base, float(trunk_radius_03), top)


def debris(plan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fallen branches lying on a conifer block's floor, in the straight local frame:
    about one per 2 m², 0.4-2 m long and 1.5-5 cm in radius, from their own random
    stream ([seed, 8]). Returns start points (q, 3), end points (q, 3) and radii (q,) [m]."""
    p = plan.params
    rng = np.random.default_rng([p.seed, 8])
    x0, x1, y0, y1 = plan.bounds
    q = int(rng.poisson(0.5 * (x1 - x0) * (y1 - y0)))
    c = np.c_[rng.uniform(x0, x1, q), rng.uniform(y0, y1, q)]
    ang = rng.uniform(0, np.pi, q)
    half = 0.5 * rng.uniform(0.4, 2.0, q)
    r = rng.uniform(0.015, 0.05, q)
    a2 = c - half[:, None] * np.c_[np.cos(ang), np.sin(ang)]
    b2 = c + half[:, None] * np.c_[np.cos(ang), np.sin(ang)]
    za = plan.ground.z(a2[:, 0], a2[:, 1]) + r
    zb = plan.ground.z(b2[:, 0], b2[:, 1]) + r
    return np.c_[a2, za], np.c_[b2, zb], r
