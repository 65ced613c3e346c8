"""The ``young`` tree form: a newly planted, dormant tree tied to a stake.

A young block is where growers count trees (survival after planting), and a winter scan
is leafless. Each tree is a whip 1.0-2.5 m tall, 1.6-4 cm thick at the ground, with a
few feathers (side shoots 0.15-0.55 m long, from 0.4-0.8 m up, in any direction: not
trained yet) and short twigs on them; no leaves. Beside every trunk, 6-12 cm away,
stands its stake (a bamboo or wooden pole 1-2.5 cm in radius, 1.2-2.2 m tall, often as
tall as the tree): not tree material, points of kind ``post``. All lengths are metres.
"""

from __future__ import annotations

import numpy as np

from simulator.branches import Tree, _add_polylines, _Branches, _points_on, _polylines, perpendicular, unit


def grow_young(rng: np.random.Generator, p, base_xy: np.ndarray, ground, scale: float = 1.0) -> Tree:
    """Branches of one young, dormant tree (no leaves); see the module docstring.

    Parameters are those of :func:`simulator.forms.grow_tree`.
    """
    gz = float(ground.z(base_xy[0], base_xy[1]))
    base = np.array([base_xy[0], base_xy[1], gz])
    height = ((p.tree_height * rng.uniform(0.95, 1.05)) if p.tree_height else rng.uniform(1.0, 2.5)) * scale
    r0 = ((p.trunk_radius * rng.uniform(0.9, 1.1)) if p.trunk_radius else rng.uniform(0.008, 0.02)) * scale
    r0 = max(r0, 0.005)
    br = _Branches()
    # the whip: nearly straight (tied to its stake), tapering to a 3 mm tip
    n_sub = 10
    lean = np.deg2rad(rng.uniform(0.0, 3.0))
    az = rng.uniform(0, 2 * np.pi)
    d0 = np.array([np.sin(lean) * np.cos(az), np.sin(lean) * np.sin(az), np.cos(lean)])
    s = np.linspace(-0.1, height, n_sub + 1)
    wobble = np.cumsum(rng.normal(0.0, 0.01, (n_sub + 1, 2)), axis=0)
    wobble[:3] = 0.0
    nodes = base[None] + s[:, None] * d0[None]
    nodes[:, :2] += wobble
    radii = r0 + (0.003 - r0) * np.clip(s / height, 0.0, 1.0)
    leader, leader_r = nodes[None], radii[None]
    _add_polylines(br, leader, leader_r)
    trunk_radius_03 = r0 + (0.003 - r0) * 0.3 / height
    # feathers: a few side shoots in any direction, from the lower third up
    h_first = min(rng.uniform(0.4, 0.8), 0.6 * height)
    m = int(rng.integers(2, 9)) if height > h_first + 0.3 else 0
    if m:
        h_lat = np.sort(rng.uniform(h_first, height - 0.15, m))
        pos, _, prad = _points_on(leader, leader_r, np.zeros(m, np.int64), (h_lat + 0.1) / (height + 0.1))
        azs = rng.uniform(0, 2 * np.pi, m)
        pol = np.deg2rad(rng.uniform(35, 75, m))
        d = np.c_[np.sin(pol) * np.cos(azs), np.sin(pol) * np.sin(azs), np.cos(pol)]
        length = rng.uniform(0.15, 0.55, m) * max(scale, 0.5)
        r_a = np.maximum(np.minimum(0.6 * prad, rng.uniform(0.004, 0.009, m)), 0.003)
        lat, lat_r = _polylines(rng, pos, d, length, r_a, np.full(m, 0.0025), bend=0.1, lift=0.05)
        _add_polylines(br, lat, lat_r)
        # a few short twigs on the feathers
        n_tw = rng.poisson(length / 0.12)
        owner = np.repeat(np.arange(m), n_tw)
        if len(owner):
            tp, tdir, _ = _points_on(lat, lat_r, owner, rng.uniform(0.2, 1.0, len(owner)))
            td = unit(perpendicular(tdir, rng) + np.array([0.0, 0.0, 0.5]))
            tw, tw_r = _polylines(rng, tp, td, rng.uniform(0.04, 0.12, len(owner)), np.full(len(owner), 0.003),
                                  np.full(len(owner), 0.002), n_sub=1, bend=0.2)
            _add_polylines(br, tw, tw_r)
    a, b, ra, rb = br.arrays()
    none = np.zeros((0, 3))
    return Tree(a, b, ra, rb, none, none, np.zeros(0), base, float(trunk_radius_03), float(np.max(b[:, 2])))


def stakes(plan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stake beside every tree of a young block, in the straight local frame.

    Drawn from their own random stream ([seed, 6]), so the trees are the same with or
    without them. Returns bottom ends (k, 3), top ends (k, 3) and radii (k,) [m].
    """
    p = plan.params
    rng = np.random.default_rng([p.seed, 6])
    xy = plan.tree_xy[plan.layout.trees]
    k = len(xy)
    ang = rng.uniform(0, 2 * np.pi, k)
    off = rng.uniform(0.06, 0.12, k)
    sx, sy = xy[:, 0] + off * np.cos(ang), xy[:, 1] + off * np.sin(ang)
    zb = plan.ground.z(sx, sy)
    ht = rng.uniform(1.2, 2.2, k)
    r = rng.uniform(0.01, 0.025, k)
    a = np.c_[sx, sy, zb - 0.05]
    b = np.c_[sx + rng.normal(0, 0.01, k), sy + rng.normal(0, 0.01, k), zb + ht]
    return a, b, r
