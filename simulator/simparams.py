"""Parameters of a generated orchard block (lengths in metres)."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator


class SimulationParams(BaseModel):
    """Parameters of a generated orchard block (lengths in metres)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    form: Literal["vase", "spindle", "hedge", "young", "conifer"] = Field(
        "vase", description="tree form: vase (open-centre trees), spindle (tall-spindle apple: thin leader, short "
        "laterals along the row) or hedge (super-high-density olive/almond: a continuous wall) or young (newly planted, dormant: a 1-2.5 m whip with a "
        "few feathers, no leaves, tied to a stake) or conifer (a plantation conifer 5-8 m tall; planted 2-2.5 m apart, a "
        "closed stand with fallen branches on its floor)")
    rows: int = Field(2, ge=1, le=500, description="number of tree rows (rows run along x before any rotation)")
    trees_per_row: int = Field(5, ge=1, le=2000, description="planting slots in each row")
    spacing: float = Field(5.0, ge=0.8, le=20.0, description="distance between trees in a row [m]")
    row_spacing: float = Field(6.0, ge=2.0, le=30.0, description="distance between rows [m]")
    position_jitter: float | None = Field(None, ge=0.0, le=1.0, description="standard deviation of tree positions around the grid [m]; default vase 0.15, spindle and hedge 0.04 (planted to a line)")
    noise: float = Field(0.02, ge=0.0, le=0.1, description="standard deviation of the Gaussian range noise [m]")
    seed: int = Field(0, ge=0, le=2**32 - 1, description="random seed; the same seed gives the same block")
    density: float = Field(1.0, gt=0.0, le=1000.0, description="scale of the point density (1 = about 40-80 k points per tree)")
    crown_radius: float | None = Field(None, gt=0.2, le=15.0, description="crown radius along the row [m] (spindle: the longest lateral); default vase 0.55 x spacing, spindle 0.7, hedge 0.8 x spacing up to 1.6")
    tree_height: float | None = Field(None, gt=1.0, le=30.0, description="tree height [m]; default random per tree: vase 3.5-4.5, spindle 2.8-3.5, hedge 2.5-3.0, young 1.0-2.5")
    trunk_radius: float | None = Field(None, gt=0.01, le=1.0, description="trunk radius [m]; default random per tree: vase 0.06-0.15, spindle 0.015-0.025, hedge 0.04-0.06, young 0.008-0.02")
    low_foliage: bool = Field(False, description="drooping outer branches, leaves down to 0.2-0.5 m above the ground (vase and hedge)")
    slope: float = Field(0.04, ge=0.0, le=0.5, description="ground slope [m/m], in a random direction")
    undulation: float = Field(0.15, ge=0.0, le=2.0, description="amplitude of gentle ground undulations [m]")
    grass: float = Field(0.5, ge=0.0, le=1.0, description="fraction of the ground covered by grass patches (0-0.12 m, tufts to 0.25 m)")
    posts: bool = Field(True, description="fence posts with a wire along one long edge of the block")
    vehicle: bool = Field(True, description="a vehicle parked in a headland")
    bin: bool = Field(True, description="a 1.2 m fruit bin in the other headland")
    trellis: int = Field(0, ge=0, le=50, description="a trellis in every row: a post (2.8-3.2 m tall, 0.05-0.065 m radius) at both row ends and in every this many-th gap between trees, with wires at 0.8, 1.6 and 2.4 m along the row; 0 = none")
    risers: float = Field(0.0, ge=0.0, le=1.0, description="irrigation risers on the drip line along every row: this fraction of the trees has one beside it (0.15-0.4 m along the row from the trunk) and this fraction of the gaps between planted slots one in its middle; a pipe 0.02-0.05 m wide and 0.3-1.0 m tall, in no tree (points of kind post); 0 = none")
    leafless: bool = Field(False, description="a dormant (winter) scan: the same trees without their leaves (vase, spindle and hedge; young trees are always leafless)")
    ghosting: float = Field(0.01, ge=0.0, le=0.05, description="registration drift: rigid offset of each alley pass [m]")
    outliers: float = Field(0.002, ge=0.0, le=0.05, description="fraction of random outlier points in the block volume")
    occlusion: float = Field(1.0, ge=0.0, le=10.0, description="scale of the leaf optical depth (0 = no occlusion)")
    easting: float = Field(500000.0, ge=-1e7, le=1e7, description="x of the local origin (first tree) [m]")
    northing: float = Field(6950000.0, ge=-1e7, le=1e7, description="y of the local origin [m]")
    elevation: float = Field(100.0, ge=-1e4, le=1e4, description="ground height at the local origin [m]")
    epsg: int = Field(28356, ge=1024, le=999999, description="EPSG code of the coordinates")
    missing: float = Field(0.0, ge=0.0, le=0.5, description="fraction of the planting slots left empty (inner slots of the rows only)")
    replants: float = Field(0.0, ge=0.0, le=0.5, description="fraction of the planting slots holding a young replant (0.3-0.5 times a grown tree's height and trunk)")
    rotation: float = Field(0.0, ge=-360.0, le=360.0, description="rotation of the whole block about the first slot [degrees, counterclockwise from east]")
    row_curvature: float = Field(0.0, ge=-20.0, le=20.0, description="sideways bow (sagitta) of every row over its length [m]")
    ragged_rows: bool = Field(False, description="rows of different length: each row loses 0-3 slots at either end at random")
    scan: int = Field(0, ge=0, le=2**16, description="scan of the block: another number is another scan of the same "
                      "planting (its own noise, sampling and occlusion draws); 0 is the block's first")
    # a series of captures of one block (simulator.series): per grid slot, row-major
    tree_scale: tuple[float, ...] = Field((), description="size of each slot's tree (growth since planting); empty: 1")
    cut: tuple[int, ...] = Field((), description="grid slots whose tree was cut (empty slots)")
    young_slots: tuple[int, ...] = Field((), description="grid slots holding a replant (a young tree)")

    @model_validator(mode="after")
    def _sizes(self) -> "SimulationParams":
        if self.tree_scale and len(self.tree_scale) != self.rows * self.trees_per_row:
            raise ValueError(f"tree_scale has {len(self.tree_scale)} sizes for {self.rows * self.trees_per_row} slots")
        if any(not 0 <= s < self.rows * self.trees_per_row for s in (*self.cut, *self.young_slots)):
            raise ValueError("cut and young_slots name grid slots 0..rows x trees_per_row - 1")
        if self.leafless and self.form == "conifer":
            raise ValueError("leafless: a conifer keeps its needles (vase, spindle, hedge or young)")
        if self.rows * self.trees_per_row > 200_000:
            raise ValueError(f"{self.rows * self.trees_per_row} trees is too many (at most 200000)")
        if self.crown_radius is not None and self.crown_radius > 2.0 * self.spacing:
            raise ValueError(f"crown_radius ({self.crown_radius} m) above twice the spacing ({self.spacing} m)")
        if self.row_curvature and abs(self.row_curvature) > 0.25 * (self.trees_per_row - 1) * self.spacing:
            raise ValueError(f"row_curvature ({self.row_curvature} m) above a quarter of the row length "
                             f"({(self.trees_per_row - 1) * self.spacing:g} m): rows must stay gently curved")
        return self

    @property
    def jitter(self) -> float:
        """Standard deviation [m] of the tree positions: ``position_jitter`` or the form's default."""
        if self.position_jitter is not None:
            return self.position_jitter
        return 0.15 if self.form == "vase" else 0.04

    def stream(self, *keys: int) -> np.random.Generator:
        """The random stream ``keys`` of this scan (the first scan's are the block's own)."""
        return np.random.default_rng([self.seed, *keys] if self.scan == 0 else [self.seed, *keys, self.scan])

    @property
    def n_trees(self) -> int:
        """Planting slots of the grid (the number of trees without ``missing`` or ``ragged_rows``)."""
        return self.rows * self.trees_per_row


def local_origin(p: SimulationParams) -> np.ndarray:
    """Absolute coordinates [m] of the block's local origin (the first slot of the first row)."""
    return np.array([p.easting, p.northing, p.elevation])
