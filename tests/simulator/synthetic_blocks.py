"""The generated blocks the simulator's tests share (their fixtures are in conftest.py)."""

from __future__ import annotations

from simulator.simparams import SimulationParams

#: a small vase block: 2 rows of 3 trees, sparse
SMALL = SimulationParams(rows=2, trees_per_row=3, density=0.15, seed=11)

#: a tall-spindle block with empty slots and replants, no clutter
LAYOUT = SimulationParams(form="spindle", rows=3, trees_per_row=10, spacing=1.0, row_spacing=3.5, density=0.05,
                          seed=7, missing=0.1, replants=0.1, posts=False, vehicle=False, bin=False)
