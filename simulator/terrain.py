"""The simulated ground: a sloping, gently undulating surface with patches of grass."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from simulator.planting import unplace_xy
from simulator.simparams import SimulationParams, local_origin


@dataclass
class Terrain:
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
    def make(cls, p: SimulationParams, rng: np.random.Generator) -> "Terrain":
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


def ground_height(params: SimulationParams, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The simulated ground's true height [m] at (x, y), in the block's absolute
    coordinates (those of :func:`simulator.simulate.simulate_orchard`'s points).

    For benchmarks that hand a peer the true terrain, e.g. a ground mesh for
    raycloudtools' ``rayextract trees``. The ground is the first thing the block's plan
    draws, so it is rebuilt here from the seed without growing the trees.
    """
    ground = Terrain.make(params, np.random.default_rng([params.seed, 0]))
    off = local_origin(params)
    # the ground is bent and turned with the rows: look it up in the straight frame
    xs, ys = unplace_xy(params, np.asarray(x, dtype=np.float64) - off[0], np.asarray(y, dtype=np.float64) - off[1])
    return ground.z(xs, ys) + off[2]
