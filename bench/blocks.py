"""Generated benchmark blocks (LAZ + truth), cached in the work folder.

A block is named by its simulation parameters; the same parameters give the same
file, so repeated runs reuse it. Point counts are reached by scaling the simulator's
``density`` (point count grows linearly with it) and the number of trees.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from simulator.simparams import SimulationParams
from simulator.simulate import iter_simulation
from simulator.truth import write_simulation


@dataclass(frozen=True)
class Block:
    name: str
    las: str
    truth: str
    n_points: int
    n_trees: int
    params: dict


def _key(params: SimulationParams) -> str:
    return hashlib.sha256(params.model_dump_json().encode()).hexdigest()[:12]


def make_block(work: Path, name: str, params: SimulationParams) -> Block:
    """Write (or reuse) the block for ``params`` under ``work/blocks``."""
    folder = work / "blocks"
    folder.mkdir(parents=True, exist_ok=True)
    stem = f"{name}-{_key(params)}"
    las, truth, meta = folder / f"{stem}.laz", folder / f"{stem}.truth.parquet", folder / f"{stem}.json"
    if not (las.exists() and truth.exists() and meta.exists()):
        info = write_simulation(params, str(las), str(truth))
        meta.write_text(json.dumps({"n_points": info["n_points"], "n_trees": info["n_trees"]}))
    m = json.loads(meta.read_text())
    return Block(name, str(las), str(truth), int(m["n_points"]), int(m["n_trees"]), params.model_dump())


def count_points(params: SimulationParams) -> int:
    """Points the simulator makes for ``params`` (generated chunk by chunk, not kept)."""
    return sum(chunk.n_points for chunk in iter_simulation(params))


def stand_params(density: float) -> SimulationParams:
    """The paper's stand: 3 trees 5 m apart in one row, sigma = 0.02 m."""
    return SimulationParams(rows=1, trees_per_row=3, spacing=5.0, noise=0.02, seed=7, density=density)


def stand_density(min_points: int) -> float:
    """Smallest round density (0.05 steps) whose 3-tree stand has >= ``min_points``."""
    base = count_points(stand_params(1.0))
    density = max(0.05, round(min_points / base * 1.03 / 0.05 + 0.5) * 0.05)
    while count_points(stand_params(density)) < min_points:
        density += 0.05
    return round(density, 2)


def _layout(n_trees: float, density: float, seed: int) -> SimulationParams:
    rows = max(1, round((n_trees / 5) ** 0.5))
    per_row = max(3, round(n_trees / rows))
    return SimulationParams(rows=rows, trees_per_row=per_row, spacing=5.0, noise=0.02, seed=seed, density=density)


def orchard_params(target_points: int, density: float, points_per_tree: float, seed: int = 11) -> SimulationParams:
    """A block of several rows at the stand's point density with about ``target_points``.

    The tree count is first guessed from ``points_per_tree``, then corrected twice from
    a count at a tenth of the density (point counts are linear in density).
    """
    n_trees = max(3.0, target_points / points_per_tree)
    for _ in range(2):  # the layout rounds rows and trees per row, so correct twice
        guess = _layout(n_trees, density, seed)
        estimate = 10 * count_points(guess.model_copy(update={"density": density / 10}))
        n_trees = max(3.0, guess.n_trees * target_points / max(estimate, 1))
    return _layout(n_trees, density, seed)


def accuracy_params(noise: float, spacing: float, seed: int) -> SimulationParams:
    """An accuracy block: 2 rows of 5 trees with overlapping crowns (crown radius 0.55 x spacing)."""
    return SimulationParams(rows=2, trees_per_row=5, spacing=spacing, row_spacing=max(6.0, spacing + 1.0), noise=noise, seed=seed)
