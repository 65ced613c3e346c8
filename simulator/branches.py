"""The simulator's branches: trees as tapered cylinder segments along bent polylines,
the vector helpers they grow with, and the `Tree` every form returns (the vase, spindle
and hedge of `simulator.forms`, the conifer and the young whip build on these)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def perpendicular(u: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random unit vectors perpendicular to the unit vectors ``u`` (m, 3)."""
    r = rng.normal(size=u.shape)
    r -= np.sum(r * u, axis=1, keepdims=True) * u
    bad = np.linalg.norm(r, axis=1) < 1e-6
    if bad.any():
        r[bad] = np.cross(u[bad], [1.0, 0.0, 0.0])
    return unit(r)


@dataclass
class Tree:
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
        cur = unit(cur + bend * rng.normal(size=(m, 3)) + np.array([0.0, 0.0, lift]))
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
    return pos, unit(b - a), rad
