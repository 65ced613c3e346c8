"""Things in the block that are not trees: fence posts and wire, trellises, stakes, irrigation
risers, a vehicle and a bin."""

from __future__ import annotations

import numpy as np

from simulator.conifer import debris
from simulator.orchard import GRASS, POST, VEHICLE, Orchard
from simulator.plan import HEADLAND, Plan
from simulator.scanner import Chunk, passes_for, sample_cylinders, sample_discs, sample_rects
from simulator.young import stakes


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


def _add_trellis(ch: Chunk, plan: Plan) -> None:
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


def _add_posts(ch: Chunk, plan: Plan, rng, xs, ys, height, radius, *, wires, y: float) -> None:
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
    for k in passes_for(plan, y):
        pts, _, _ = sample_cylinders(rng, plan, k, ca, cb, cr, cr)
        pts = pts[pts[:, 2] >= g.z(pts[:, 0], pts[:, 1])]
        ch.add(plan, rng, k, pts, 0, False, POST)


def _add_stakes(ch: Chunk, plan: Plan) -> None:
    """The stake beside every young tree (:func:`simulator.young.stakes`), as points of kind post."""
    _add_pipes(ch, plan, *stakes(plan), stream=7)


def _add_pipes(ch: Chunk, plan: Plan, a: np.ndarray, b: np.ndarray, r: np.ndarray, stream: int) -> None:
    """Upright cylinders from bottom ends ``a`` (k, 3) to top ends ``b`` (k, 3) of radii
    ``r`` (k,) [m], scanned from the passes within a row spacing, as points of kind post
    above the ground; drawn from their own random stream ([seed, ``stream``])."""
    rng = np.random.default_rng([plan.params.seed, stream])
    for k in range(len(plan.pass_y)):
        near = np.abs(a[:, 1] - plan.pass_y[k]) <= plan.params.row_spacing
        if near.any():
            pts, _, _ = sample_cylinders(rng, plan, k, a[near], b[near], r[near], r[near])
            pts = pts[pts[:, 2] >= plan.ground.z(pts[:, 0], pts[:, 1])]
            ch.add(plan, rng, k, pts, 0, False, POST)


def risers(plan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Irrigation risers on the drip line of every row (``params.risers``), in the straight local frame.

    The drip line runs along the trunks; ``round(risers x trees)`` trees have a riser
    beside them, 0.15-0.4 m along the row from the trunk, and ``round(risers x gaps)``
    gaps between consecutive planted slots of a row one in their middle (on a curved row,
    between the two slots). Each is a pipe 1-2.5 cm in radius, 0.3-1.0 m tall. Drawn from
    their own random stream ([seed, 10]), so the rest of the block is the same with or
    without them. Returns bottom ends (k, 3), top ends (k, 3) and radii (k,) [m].
    """
    p = plan.params
    rng = np.random.default_rng([p.seed, 10])
    lay = plan.layout
    xy = plan.tree_xy[lay.trees]
    by = rng.choice(len(xy), int(round(p.risers * len(xy))), replace=False)
    side = rng.choice([-1.0, 1.0], len(by))
    near = xy[by] + np.c_[side * rng.uniform(0.15, 0.4, len(by)), rng.normal(0, 0.03, len(by))]
    # consecutive planted slots of a row (slots are row-major)
    s = np.flatnonzero(lay.planted)
    pair = lay.row[s[:-1]] == lay.row[s[1:]]
    left, right = s[:-1][pair], s[1:][pair]
    mid = rng.choice(len(left), int(round(p.risers * len(left))), replace=False)
    gap = 0.5 * (plan.tree_xy[left[mid]] + plan.tree_xy[right[mid]]) + np.c_[np.zeros(len(mid)), rng.normal(0, 0.03, len(mid))]
    at = np.vstack([near, gap])
    k = len(at)
    zb = plan.ground.z(at[:, 0], at[:, 1])
    ht = rng.uniform(0.3, 1.0, k)
    r = rng.uniform(0.01, 0.025, k)
    a = np.c_[at, zb - 0.05]
    b = np.c_[at[:, 0] + rng.normal(0, 0.01, k), at[:, 1] + rng.normal(0, 0.01, k), zb + ht]
    return a, b, r


def _add_risers(ch: Chunk, plan: Plan) -> None:
    """The irrigation risers of :func:`risers`, as points of kind post."""
    _add_pipes(ch, plan, *risers(plan), stream=11)


def _add_debris(ch: Chunk, plan: Plan) -> None:
    """Fallen branches on a conifer block's floor (:func:`simulator.conifer.debris`),
    as points of kind grass (low material in no tree)."""
    a, b, r = debris(plan)
    rng = np.random.default_rng([plan.params.seed, 9])
    for k in range(len(plan.pass_y)):
        near = np.abs(0.5 * (a[:, 1] + b[:, 1]) - plan.pass_y[k]) <= plan.params.row_spacing
        if near.any():
            pts, _, _ = sample_cylinders(rng, plan, k, a[near], b[near], r[near], r[near])
            pts = pts[pts[:, 2] >= plan.ground.z(pts[:, 0], pts[:, 1])]
            ch.add(plan, rng, k, pts, 0, False, GRASS)


def objects_chunk(plan: Plan) -> Orchard:
    """Fence posts and wire, trellis posts and wires and irrigation risers (when asked
    for), a young block's stakes, the vehicle and the bin."""
    p = plan.params
    rng = p.stream(4)
    g = plan.ground
    x0, x1, y0, y1 = plan.bounds
    ch = Chunk()
    if p.posts:
        y_f = plan.pass_y[0] - 2.5
        xs = np.arange(x0 + 1.0, x1 - 0.5, 3.0) + rng.normal(0, 0.08, len(np.arange(x0 + 1.0, x1 - 0.5, 3.0)))
        ys = y_f + rng.normal(0, 0.03, len(xs))
        ht = rng.uniform(1.2, 1.8, len(xs))
        rp = rng.uniform(0.04, 0.06, len(xs))
        _add_posts(ch, plan, rng, xs, ys, ht, rp, wires=(1.0,), y=y_f)  # one wire ~1.0 m high
    if p.trellis:
        _add_trellis(ch, plan)
    if p.form == "young":
        _add_stakes(ch, plan)
    if p.risers:
        _add_risers(ch, plan)
    if p.form == "conifer":
        _add_debris(ch, plan)
    boxes = []
    if p.vehicle:  # parked in the far headland beside the first inner alley's path
        k_al = min(1, len(plan.pass_y) - 1)
        vx = x1 - HEADLAND / 2
        vy = plan.pass_y[k_al] + 2.2
        boxes.append((np.array([vx, vy]), (3.5, 1.7, 1.35), 0.45, True))
    if p.bin:
        bx = x0 + HEADLAND / 2
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
        for k in passes_for(plan, xy[1]):
            pts = sample_rects(rng, plan, k, corner, u, v)
            ch.add(plan, rng, k, pts, 0, False, VEHICLE)
            if wheels:
                pts, _, _ = sample_cylinders(rng, plan, k, wa, wb, np.full(4, wr), np.full(4, wr))
                ch.add(plan, rng, k, pts, 0, False, VEHICLE)
                pts, _ = sample_discs(rng, plan, k, wb, axis_dir, np.full(4, wr), two_sided=False)
                ch.add(plan, rng, k, pts, 0, False, VEHICLE)
    return ch.finish(plan, rng)
