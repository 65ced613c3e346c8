"""The plan of a block, drawn once before any point: ground, tree positions and sizes,
the scanner's passes and the leaf-area grid that occludes them."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from simulator.branches import unit
from simulator.forms import grow_tree
from simulator.planting import Layout, make_layout, place, young_scale
from simulator.simparams import SimulationParams, local_origin
from simulator.terrain import Terrain

_RHO = 20000.0  # points per m^2 (normal incidence, 1 m range) at density 1
VOXEL = 0.25
"""Cell of the leaf-area grid [m]."""
HEADLAND = 7.0
"""Headland length beyond the first and last tree [m]."""
_MARGIN = 4.0  # block margin beyond the outer passes [m]


@dataclass
class Plan:
    """Everything about a block that is drawn before its points, in the straight local frame.

    A tree's chunk, a ground strip and the distractors are then sampled from the plan
    independently (each from its own random stream), in any order.
    """

    params: SimulationParams
    ground: Terrain
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
    heights: np.ndarray | None = None  # (k,) each tree's top above its trunk base [m]

    def offset(self) -> np.ndarray:
        """Absolute coordinates [m] of the local origin."""
        return local_origin(self.params)

    @cached_property
    def addresses(self) -> dict:
        """The truth of the block's layout, as :class:`simulator.orchard.Orchard` fields."""
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


def tree_rng(seed: int, i: int) -> np.random.Generator:
    """The random stream of the tree in grid slot ``i``: the same tree whatever else the block holds."""
    return np.random.default_rng([seed, 1, i])


def make_plan(p: SimulationParams) -> Plan:
    """Draw the plan of block ``p``: the ground first (:func:`simulator.terrain.ground_height`
    relies on it), then the tree positions and passes, then every tree once for its trunk
    and leaf area."""
    rng = np.random.default_rng([p.seed, 0])
    ground = Terrain.make(p, rng)
    r_idx, t_idx = np.divmod(np.arange(p.n_trees), p.trees_per_row)
    tree_xy = np.c_[t_idx * p.spacing, r_idx * p.row_spacing] + rng.normal(0.0, p.jitter, (p.n_trees, 2))
    x0, x1 = -HEADLAND, (p.trees_per_row - 1) * p.spacing + HEADLAND
    y0, y1 = -0.5 * p.row_spacing - _MARGIN, (p.rows - 0.5) * p.row_spacing + _MARGIN
    pass_y = (np.arange(p.rows + 1) - 0.5) * p.row_spacing
    pass_h = rng.uniform(1.0, 1.8, p.rows + 1)
    shift = unit(rng.normal(size=(p.rows + 1, 3)) * np.array([1.0, 1.0, 0.5]))
    shift *= p.ghosting * rng.uniform(0.5, 1.0, (p.rows + 1, 1))

    h_max = (p.tree_height * 1.05 if p.tree_height else (8.0 if p.form == "conifer" else 4.5)) + 1.5
    h0 = -1.0
    shape = (
        int(np.ceil((x1 - x0) / VOXEL)) + 1,
        int(np.ceil((y1 - y0) / VOXEL)) + 1,
        int(np.ceil((h_max - h0) / VOXEL)) + 1,
    )
    origin = np.array([x0, y0, h0])
    lad = np.zeros(int(np.prod(shape)), dtype=np.float32)
    layout = make_layout(p)
    slots = layout.trees
    scale = np.array([young_scale(p, i) if layout.young[i] else 1.0 for i in slots])
    if p.tree_scale:
        scale = scale * np.asarray(p.tree_scale, np.float64)[slots]
    heights = np.empty(len(slots))
    trunks = np.empty((len(slots), 3))
    trunk_r = np.empty(len(slots))
    z_top = 0.0
    # a tree's random stream is that of its slot: removing a tree leaves the others unchanged
    for k, i in enumerate(slots):
        tree = grow_tree(tree_rng(p.seed, i), p, tree_xy[i], ground, scale=scale[k])
        trunks[k] = place(p, tree.base[None], tree.base[:2])[0]
        trunk_r[k] = tree.trunk_radius
        z_top = max(z_top, tree.top - tree.base[2])
        heights[k] = tree.top - tree.base[2]
        c = tree.leaf_c
        h = c[:, 2] - ground.z(c[:, 0], c[:, 1])
        flat = _grid_index(np.c_[c[:, :2], h], origin, shape)
        lad += np.bincount(flat, weights=np.pi * tree.leaf_r**2, minlength=lad.size).astype(np.float32)
    lad /= VOXEL**3
    profile_x = np.arange(x0 - 2.0, x1 + 2.0, 0.1)
    pass_z = np.stack([ground.z(profile_x, np.full(len(profile_x), yk)) + hk for yk, hk in zip(pass_y, pass_h)])
    return Plan(p, ground, tree_xy, layout, (x0, x1, y0, y1), pass_y, pass_h, shift, lad, shape, origin, trunks,
                trunk_r, scale, z_top, _RHO * p.density, profile_x, pass_z, heights)


def _grid_index(q: np.ndarray, origin: np.ndarray, shape) -> np.ndarray:
    i = np.clip(((q - origin) / VOXEL).astype(np.int64), 0, np.array(shape) - 1)
    return (i[:, 0] * shape[1] + i[:, 1]) * shape[2] + i[:, 2]
