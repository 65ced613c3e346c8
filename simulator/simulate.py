"""Generating a block chunk by chunk: one chunk per tree, ground strips, then the distractors.

Everything is deterministic for a seed: each tree, ground strip and the distractors draw
from their own random stream. Blocks are generated tree by tree (:func:`iter_simulation`),
so memory stays bounded whatever the block size. The block is built in a straight frame
(rows along x) and mapped to the local frame by :func:`simulator.planting.place`
as each chunk is finished.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from simulator.clutter import objects_chunk
from simulator.forms import grow_tree
from simulator.orchard import GRASS, GROUND, LEAF, OUTLIER, TWIG, WOOD, WOOD_RADIUS, Orchard, concatenate
from simulator.plan import Plan, make_plan, tree_rng
from simulator.scanner import RANGE_REF, Chunk, passes_for, sample_cylinders, sample_discs
from simulator.simparams import SimulationParams

_GROUND_RETURN = 0.3  # ground and grass return less (dark, grazing incidence, vehicle shadow)
_BLIND = 0.7  # ground closer than this to the path (laterally) is hidden by the vehicle [m]


def _tree_chunk(plan: Plan, t: int) -> Orchard:
    """Points of tree ``t`` (0-based; id ``t + 1``)."""
    p = plan.params
    i = int(plan.layout.trees[t])
    tree = grow_tree(tree_rng(p.seed, i), p, plan.tree_xy[i], plan.ground, scale=plan.scale[t])
    rng = p.stream(2, i)
    ch = Chunk()
    for k in passes_for(plan, tree.base[1]):
        pts, rad, _ = sample_cylinders(rng, plan, k, tree.cyl_a, tree.cyl_b, tree.cyl_ra, tree.cyl_rb)
        h = pts[:, 2] - plan.ground.z(pts[:, 0], pts[:, 1])
        above = h >= 0.0  # the trunk starts below the ground
        pts, rad, h = pts[above], rad[above], h[above]
        wood = rad >= WOOD_RADIUS
        ch.add(plan, rng, k, pts, t + 1, wood, np.where(wood, WOOD, TWIG), h=h)
        pts, _ = sample_discs(rng, plan, k, tree.leaf_c, tree.leaf_n, tree.leaf_r)
        ch.add(plan, rng, k, pts, t + 1, False, LEAF)
    return ch.finish(plan, rng, tree.base[:2])


def _ground_chunk(plan: Plan, k: int, xa: float, xb: float, j: int) -> Orchard:
    """Ground and grass seen from pass ``k`` between along-track coordinates xa and xb.

    Strategy: on flat ground the density at lateral offset d from the path is
    rho * h / (d^2 + h^2)^(3/2) (1/r^2 times the cosine of incidence), whose integral
    F(d) = d / (h sqrt(d^2 + h^2)) inverts in closed form, so offsets are drawn exactly.
    """
    p = plan.params
    rng = p.stream(3, k, j)
    x0, x1, y0, y1 = plan.bounds
    yk = plan.pass_y[k]
    h = plan.pass_h[k]
    lo = max(y0 - yk, -p.row_spacing)
    hi = min(y1 - yk, p.row_spacing)
    ch = Chunk()

    def F(d):
        return d / (h * np.sqrt(d * d + h * h))

    def Finv(f):
        q = np.clip(f * h, -0.999999, 0.999999)
        return h * q / np.sqrt(1.0 - q * q)

    for a, b in ((lo, -_BLIND), (_BLIND, hi)):
        if b <= a:
            continue
        mass = _GROUND_RETURN * plan.rho * RANGE_REF**2 * (F(b) - F(a)) * (xb - xa)
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
    plan = make_plan(params)
    for t in range(len(plan.trunks)):
        yield _tree_chunk(plan, t)
    x0, x1, _, _ = plan.bounds
    edges = np.arange(x0, x1, ground_chunk_length).tolist() + [x1]
    for k in range(len(plan.pass_y)):
        for j, (xa, xb) in enumerate(zip(edges[:-1], edges[1:])):
            yield _ground_chunk(plan, k, xa, xb, j)
    yield objects_chunk(plan)


def simulate_orchard(params: SimulationParams | None = None) -> Orchard:
    """Generate a whole block in memory (see :mod:`simulator` for the model).

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
