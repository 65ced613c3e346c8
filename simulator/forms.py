"""Tree forms of the orchard simulator: the branching structure and leaves of one tree.

Three forms, all in the block's straight local frame (rows along x):

- ``vase``: an open-centre tree, a slightly leaning trunk branching low (0.4-0.9 m) into
  3-5 scaffolds with 3 recursive sub-levels tapering to ~1 cm twigs that reach a crown
  envelope; leaf clusters fill mostly the outer shell of the crown;
- ``spindle``: a tall-spindle apple, a thin central leader (3-5 cm at the base, 2.8-3.5 m
  tall) carrying short laterals (0.3-0.7 m, from 0.6-0.8 m up) trained mostly along the row, with fruiting
  spurs and leaves along them;
- ``hedge``: a super-high-density olive or almond, a short trunk (8-12 cm) branching at
  0.5-0.8 m into upright scaffolds that fill a narrow crown elongated along the row, so
  that neighbouring crowns merge into a continuous wall.

A replant (``scale`` < 1) is the same form grown smaller: height, trunk, crown and
branching height are scaled together. All lengths are metres.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from simulator.branches import Tree, _add_polylines, _Branches, _points_on, _polylines, perpendicular, unit
from simulator.conifer import grow_conifer
from simulator.young import grow_young


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
    w = perpendicular(pdir, rng)
    d = np.cos(alpha)[:, None] * pdir + np.sin(alpha)[:, None] * w
    out = np.zeros((n, 3))
    out[:, :2] = pos[:, :2] - axis_xy
    out = unit(out)
    d = unit(d + out_bias * out + np.array([0.0, 0.0, up_bias]))
    dist = env.distance(pos, d)
    length = np.maximum(rng.uniform(*reach, n) * dist, min_len)
    r0 = np.maximum(prad * rng.uniform(*radius_factor, n), 0.004)
    return pos, d, length, r0


def grow_tree(rng: np.random.Generator, p, base_xy: np.ndarray, ground, *, scale: float = 1.0) -> Tree:
    """Branching structure and leaves of one tree of form ``p.form`` (local frame).

    Parameters
    ----------
    rng : numpy.random.Generator
        The tree's own stream (the same tree for the same stream).
    p : SimulationParams
    base_xy : (2,) float
        Trunk position [m] in the straight local frame.
    ground : object with ``z(x, y)``
        The block's ground surface [m].
    scale : float
        Size of the tree relative to a grown one (< 1 for a replant).
    """
    if p.form == "conifer":

        return grow_conifer(rng, p, base_xy, ground, scale)
    if p.form == "young":

        return grow_young(rng, p, base_xy, ground, scale)
    grow = {"vase": _grow_vase, "spindle": _grow_spindle, "hedge": _grow_hedge}[p.form]
    tree = grow(rng, p, base_xy, ground, scale)
    if p.leafless:  # the tree grown as in leaf (the same draws), its leaves dropped
        return replace(tree, leaf_c=tree.leaf_c[:0], leaf_n=tree.leaf_n[:0], leaf_r=tree.leaf_r[:0],
                       top=float(np.max(tree.cyl_b[:, 2])))
    return tree


def _grow_vase(rng, p, base_xy, ground, scale):
    gz = float(ground.z(base_xy[0], base_xy[1]))
    base = np.array([base_xy[0], base_xy[1], gz])
    height = ((p.tree_height * rng.uniform(0.95, 1.05)) if p.tree_height else rng.uniform(3.5, 4.5)) * scale
    r_t = ((p.trunk_radius * rng.uniform(0.9, 1.1)) if p.trunk_radius else rng.uniform(0.06, 0.15)) * scale
    r_crown = (p.crown_radius if p.crown_radius else 0.55 * p.spacing) * rng.uniform(0.95, 1.05) * scale
    # the envelope is slightly wider than the crown radius: twigs and leaves fill it only sparsely at the rim
    rx = 1.12 * r_crown
    ry = 1.08 * min(r_crown, 0.36 * p.row_spacing) * rng.uniform(0.95, 1.05)
    h_branch = rng.uniform(0.4, 0.9) * scale
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
        d1 = np.vstack([d1, unit(np.array([[0, 0, 1.0]]) + rng.normal(0, 0.05, (1, 3)))])
        p1 = np.vstack([p1, top0[None]])
        r1 = np.append(r1, rb_t * rng.uniform(0.6, 0.75))
    len1 = np.maximum(env.distance(p1, d1) * rng.uniform(0.5, 0.7, len(p1)), 0.2)
    nodes1, rad1 = _polylines(rng, p1, d1, len1, r1, r1 * 0.6, bend=0.1, lift=0.05)
    _add_polylines(br, nodes1, rad1)
    return _fill_crown(rng, p, ground, env, axis_xy, br, nodes1, rad1, base, trunk_radius_03)


def _fill_crown(rng, p, ground, env, axis_xy, br, nodes1, rad1, base, trunk_radius):
    """Levels 2-4 (sub-branches and twigs reaching the envelope ``env``), drooping shoots
    when ``p.low_foliage``, and leaves, grown from the scaffold polylines ``nodes1``."""
    rx, ry, zc = env.rx, env.ry, env.centre[2]
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
            out = unit(out)
            dd = unit(out * rng.uniform(0.25, 0.6, (n_p, 1)) + np.array([0.0, 0.0, -1.0]) + rng.normal(0, 0.12, (n_p, 3)))
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
        ln.append(unit(rng.normal(size=pos.shape) + np.array([0.0, 0.0, 0.4])))
        lr.append(rng.uniform(0.03, 0.06, len(owner)))
    a, b, ra, rb = br.arrays()
    leaf_c = np.concatenate(lc)
    top = float(max(np.max(b[:, 2]), np.max(leaf_c[:, 2]) if len(leaf_c) else -np.inf))
    return Tree(a, b, ra, rb, leaf_c, np.concatenate(ln), np.concatenate(lr), base, float(trunk_radius), top)



def _grow_hedge(rng, p, base_xy, ground, scale):
    """A super-high-density olive/almond: short trunk, upright scaffolds, a narrow crown
    elongated along the row that overlaps its neighbours' into one wall."""
    gz = float(ground.z(base_xy[0], base_xy[1]))
    base = np.array([base_xy[0], base_xy[1], gz])
    height = ((p.tree_height * rng.uniform(0.95, 1.05)) if p.tree_height else rng.uniform(2.5, 3.0)) * scale
    r_t = ((p.trunk_radius * rng.uniform(0.9, 1.1)) if p.trunk_radius else rng.uniform(0.04, 0.06)) * scale
    # along the row the crown reaches well into the neighbours' (a continuous wall); across
    # it is pruned to a 1-1.5 m wide wall
    half_len = (p.crown_radius if p.crown_radius else min(0.8 * p.spacing, 1.6)) * rng.uniform(0.95, 1.05) * scale
    # twigs overshoot the envelope a little and leaves sit around them: the visible wall is
    # ~0.2 m wider and ~0.1 m taller than the envelope
    half_wid = min(rng.uniform(0.4, 0.62), 0.3 * p.row_spacing) * scale
    h_branch = rng.uniform(0.5, 0.8) * scale
    lean = np.deg2rad(rng.uniform(0.0, 3.0))
    az = rng.uniform(0, 2 * np.pi)
    d0 = np.array([np.sin(lean) * np.cos(az), np.sin(lean) * np.sin(az), np.cos(lean)])
    trunk_len = (h_branch + 0.1) / d0[2]
    a0 = base - 0.1 / d0[2] * d0
    top0 = a0 + trunk_len * d0
    crown_base = h_branch - 0.1
    zc = gz + crown_base + 0.4 * (height - crown_base)
    env = _Envelope(centre=np.array([top0[0], top0[1], zc]), rx=half_len, ry=half_wid, c_up=gz + height - 0.1 * scale - zc,
                    c_lo=zc - gz - crown_base)

    br = _Branches()
    ra_t, rb_t = r_t * 1.08, r_t * 0.85
    br.add(a0[None], top0[None], np.array([ra_t]), np.array([rb_t]))
    trunk_radius_03 = ra_t + (rb_t - ra_t) * (0.1 + 0.3) / (trunk_len * d0[2])

    # scaffolds: upright, most of them leaning along the row (the wall's direction)
    n_s = int(rng.integers(3, 7))
    along = rng.random(n_s) < 0.75
    azs = np.where(along, np.pi * rng.integers(0, 2, n_s), rng.choice([-0.5, 0.5], n_s) * np.pi)
    azs = azs + rng.normal(0, 0.3, n_s)
    pol = np.deg2rad(rng.uniform(15, 40, n_s))
    d1 = np.c_[np.sin(pol) * np.cos(azs), np.sin(pol) * np.sin(azs), np.cos(pol)]
    p1 = top0[None] + d0[None] * rng.uniform(-0.1, 0.1, n_s)[:, None]
    r1 = rb_t * rng.uniform(0.5, 0.7, n_s)
    len1 = np.maximum(env.distance(p1, d1) * rng.uniform(0.6, 0.8, n_s), 0.2)
    nodes1, rad1 = _polylines(rng, p1, d1, len1, r1, r1 * 0.5, bend=0.1, lift=0.1)
    _add_polylines(br, nodes1, rad1)
    return _fill_crown(rng, p, ground, env, top0[:2], br, nodes1, rad1, base, trunk_radius_03)


def _grow_spindle(rng, p, base_xy, ground, scale):
    """A tall-spindle apple: a thin central leader with short laterals trained along the
    row, fruiting spurs on the laterals and leaves along both."""
    gz = float(ground.z(base_xy[0], base_xy[1]))
    base = np.array([base_xy[0], base_xy[1], gz])
    height = ((p.tree_height * rng.uniform(0.95, 1.05)) if p.tree_height else rng.uniform(2.8, 3.5)) * scale
    r0 = ((p.trunk_radius * rng.uniform(0.9, 1.1)) if p.trunk_radius else rng.uniform(0.015, 0.025)) * scale
    reach = (p.crown_radius if p.crown_radius else 0.7) * scale  # longest lateral
    br = _Branches()

    # the leader: a staked, nearly straight pole tapering to a whip at the top
    n_sub = 14
    lean = np.deg2rad(rng.uniform(0.0, 2.0))
    az = rng.uniform(0, 2 * np.pi)
    d0 = np.array([np.sin(lean) * np.cos(az), np.sin(lean) * np.sin(az), np.cos(lean)])
    s = np.linspace(-0.1, height, n_sub + 1)
    wobble = np.cumsum(rng.normal(0.0, 0.008, (n_sub + 1, 2)), axis=0)
    wobble[:3] = 0.0  # straight near the ground, where the stem is measured
    nodes = base[None] + s[:, None] * d0[None]
    nodes[:, :2] += wobble
    h_rel = np.clip(s / height, 0.0, 1.0)
    radii = r0 + (0.004 - r0) * h_rel  # linear taper from r0 at the ground to a 4 mm tip
    leader, leader_r = nodes[None], radii[None]
    _add_polylines(br, leader, leader_r)
    trunk_radius_03 = r0 + (0.004 - r0) * 0.3 / height

    # laterals every 8-15 cm from 0.6-0.8 m up to 0.2 m below the top
    h_first = rng.uniform(0.6, 0.8) * scale
    h_lat = np.arange(h_first, height - 0.2 * scale, 0.115 * max(scale, 0.5))
    h_lat = np.clip(h_lat + rng.uniform(-0.035, 0.035, len(h_lat)), h_first, height)
    m = len(h_lat)
    if m:
        t = (h_lat + 0.1) / (height + 0.1)
        pos, _, prad = _points_on(leader, leader_r, np.zeros(m, np.int64), t)
        # trained along the row (a few left growing across it)
        along = rng.random(m) < 0.8
        azs = np.where(along, np.pi * rng.integers(0, 2, m), rng.choice([-0.5, 0.5], m) * np.pi)
        azs = azs + rng.normal(0, 0.25, m)
        pol = np.deg2rad(rng.uniform(65, 95, m))  # near horizontal, some bent down by fruit
        d = np.c_[np.sin(pol) * np.cos(azs), np.sin(pol) * np.sin(azs), np.cos(pol)]
        rel = (h_lat - h_first) / max(height - h_first, 1e-6)
        # shorter towards the top (the spindle's cone), and across the row (pruned to the wall)
        length = rng.uniform(0.3, 0.7, m) * (1.0 - 0.35 * rel) * np.where(along, 1.0, 0.6) * reach / 0.7
        r_a = np.maximum(np.minimum(0.5 * prad, rng.uniform(0.006, 0.012, m)), 0.004)
        lat, lat_r = _polylines(rng, pos, d, length, r_a, np.full(m, 0.003), bend=0.12, lift=-0.04)
        _add_polylines(br, lat, lat_r)
        # fruiting spurs: short twigs every ~8 cm along the laterals
        n_sp = rng.poisson(length / 0.08)
        owner = np.repeat(np.arange(m), n_sp)
        sp_pos, sp_dir, _ = _points_on(lat, lat_r, owner, rng.uniform(0.1, 1.0, len(owner)))
        sp_d = unit(perpendicular(sp_dir, rng) + np.array([0.0, 0.0, 0.3]))
        sp_len = rng.uniform(0.04, 0.12, len(owner)) * max(scale, 0.5)
        spur, spur_r = _polylines(rng, sp_pos, sp_d, sp_len, np.full(len(owner), 0.004), np.full(len(owner), 0.003),
                                  n_sub=1, bend=0.2)
        if len(owner):
            _add_polylines(br, spur, spur_r)
        leaf_sets = [(lat, lat_r, 0.15, 32.0), (spur, spur_r, 0.0, 40.0), (leader, leader_r, 0.6, 35.0)]
    else:
        leaf_sets = [(leader, leader_r, 0.3, 25.0)]
    lc, ln, lr = [], [], []
    for nd, rd, t0, rate in leaf_sets:
        seg_len = np.linalg.norm(np.diff(nd, axis=1), axis=2).sum(axis=1)
        cnt = rng.poisson(rate * seg_len * (1.0 - t0))
        owner = np.repeat(np.arange(len(nd)), cnt)
        pos, _, _ = _points_on(nd, rd, owner, rng.uniform(t0, 1.0, len(owner)))
        lc.append(pos + rng.normal(0.0, 0.04, pos.shape))
        ln.append(unit(rng.normal(size=pos.shape) + np.array([0.0, 0.0, 0.4])))
        lr.append(rng.uniform(0.025, 0.045, len(owner)))
    a, b, ra, rb = br.arrays()
    leaf_c = np.concatenate(lc)
    top = float(max(np.max(b[:, 2]), np.max(leaf_c[:, 2]) if len(leaf_c) else -np.inf))
    return Tree(a, b, ra, rb, leaf_c, np.concatenate(ln), np.concatenate(lr), base, float(trunk_radius_03), top)
