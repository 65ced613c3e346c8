"""A series of captures of one generated block: the same planting scanned again and again.

Between two captures every tree grows (height, trunk and crown by 5-10 %), a few trees
are cut, some empty slots are replanted with young trees, and the capture's frame
drifts against the previous one (GNSS/SLAM drift: a shift of 0.5-2 m in a random
direction and a heading change of 0.5-2 degrees); each capture is a new scan (its own
noise, sampling and occlusion). Capture ``k`` is a :class:`SimulationParams` of the
block (``tree_scale``, ``cut``, ``young_slots``, ``scan``, ``rotation`` and the origin
carry the changes), so it is generated and written like any block.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import date, timedelta

import numpy as np

from simulator.planting import make_layout
from simulator.simparams import SimulationParams


@dataclass(frozen=True)
class SeriesCapture:
    """One capture of a series.

    Attributes
    ----------
    params : SimulationParams — the block as this capture scans it
    captured_at : date
    cut : tuple of int — slots whose tree was cut since the previous capture
    replanted : tuple of int — slots replanted since the previous capture
    """

    params: SimulationParams
    captured_at: date
    cut: tuple[int, ...]
    replanted: tuple[int, ...]


def capture_series(base: SimulationParams, n: int, *, seed: int, start: date = date(2025, 3, 1), every_days: int = 45,
                   growth: tuple[float, float] = (1.05, 1.10), cut_fraction: float = 0.05,
                   replant_fraction: float = 0.5, shift: tuple[float, float] = (0.5, 2.0),
                   heading_deg: tuple[float, float] = (0.5, 2.0)) -> list[SeriesCapture]:
    """``n`` captures of the block ``base``, the first undrifted.

    Parameters
    ----------
    base : SimulationParams — the planting (its seed fixes it)
    n : int — captures
    seed : int — the series' own draws (growth, cuts, replants, drift)
    growth : (lo, hi) — per-tree size ratio between two captures
    cut_fraction : float — share of the living grown trees cut between two captures (at least one)
    replant_fraction : float — share of the slots cut before that are replanted
    shift, heading_deg : (lo, hi) — drift of each capture's frame against the previous one [m], [degrees]
    """
    rng = np.random.default_rng([seed, 55])
    slots = base.n_trees
    layout = make_layout(base)
    present = layout.present.copy()
    young = layout.young.copy()
    scale = np.ones(slots)
    cut_all: set[int] = set()
    easting, northing, rotation = base.easting, base.northing, base.rotation
    out = []
    for k in range(n):
        cut, replanted = (), ()
        if k:
            scale *= rng.uniform(*growth, slots)
            grown = np.flatnonzero(present & ~young)
            n_cut = max(1, int(round(cut_fraction * len(grown))))
            cut = tuple(int(s) for s in rng.choice(grown, min(n_cut, len(grown)), replace=False))
            earlier = np.array(sorted(cut_all), np.int64)
            n_re = int(round(replant_fraction * len(earlier)))
            replanted = tuple(int(s) for s in rng.choice(earlier, n_re, replace=False)) if n_re else ()
            present[list(cut)] = False
            present[list(replanted)] = True
            young[list(replanted)] = True
            scale[list(replanted)] = 1.0
            cut_all = (cut_all | set(cut)) - set(replanted)
            angle = rng.uniform(0, 2 * np.pi)
            dist = rng.uniform(*shift)
            easting += dist * np.cos(angle)
            northing += dist * np.sin(angle)
            rotation += rng.choice([-1.0, 1.0]) * rng.uniform(*heading_deg)
        params = base.model_copy(update={
            "scan": k, "tree_scale": tuple(float(s) for s in scale),
            "cut": tuple(int(s) for s in np.flatnonzero(~present & layout.present)),
            "young_slots": tuple(int(s) for s in np.flatnonzero(present & young & ~layout.young)),
            "easting": float(easting), "northing": float(northing), "rotation": float(rotation),
        })
        out.append(SeriesCapture(SimulationParams.model_validate(params.model_dump()),
                                 start + timedelta(days=every_days * k), cut, replanted))
    return out
