"""Parameter models for every algorithm of the per-block pipeline.

One pydantic model per algorithm, with units and bounds. The same `PipelineParams`
object is stored with a job, shipped to a dask worker and used by the command line
(each field becomes an option ``--<group>-<field>``, with its description as help).
All lengths are metres.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Model(BaseModel):
    # non-finite numbers are refused as such (NaN would fail a bound with a misleading message)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class GroundParams(_Model):
    """Ground removal by local z-minimum (paper: lateral radius R_g = 1 m)."""

    cell_size: float = Field(0.25, gt=0.01, le=5.0, description="grid cell for ground minima [m]")
    search_radius: float = Field(1.0, gt=0.05, le=20.0, description="lateral radius of the local z-minimum (R_g) [m]")
    tolerance: float = Field(0.12, ge=0.0, le=2.0, description="points this close above the ground surface are ground [m]")
    outlier_depth: float = Field(0.3, gt=0.0, le=10.0, description="cell minima this far below their neighbours' median are noise, not ground [m]")
    max_slope: float = Field(1.0, ge=0.0, le=10.0, description="ground rises at most this much per metre from lower ground (0 = no limit) [m/m]")

    @model_validator(mode="after")
    def _radius_in_cells(self) -> "GroundParams":
        # the filters' footprint is a disk of search_radius / cell_size cells: their time
        # and a worker's memory grow with its square
        if self.search_radius > MAX_RADIUS_CELLS * self.cell_size:
            raise ValueError(
                f"search_radius ({self.search_radius} m) spans more than {MAX_RADIUS_CELLS} cells of cell_size "
                f"({self.cell_size} m); the ground filters would take too long: use a cell_size of at least "
                f"{self.search_radius / MAX_RADIUS_CELLS:g} m"
            )
        return self


#: most cells of ``GroundParams.cell_size`` that ``search_radius`` may span (the ground
#: filters take seconds per million points there)
MAX_RADIUS_CELLS = 20


class GraphParams(_Model):
    """Voxel graph: nodes are voxel centroids, edges join nodes within a radius."""

    voxel_size: float = Field(0.1, ge=0.02, le=1.0, description="voxel edge length (v_s) [m]")
    edge_radius: float = Field(0.15, gt=0.0, le=2.0, description="nodes closer than this are joined by an edge (R_e) [m]")
    weighting: Literal["distance", "enriched"] = Field(
        "distance",
        description="segmentation edge weight: 'distance' (paper, plain) or 'enriched' (paper: distance x cosine distance of enrichment features)",
    )

    max_gap: float = Field(1.0, ge=0.0, le=10.0, description="a graph component floating above the ground is joined to its nearest neighbour component across a gap up to this long (sparse scans) [m]")

    @model_validator(mode="after")
    def _radius_covers_voxel(self) -> "GraphParams":
        if self.edge_radius < self.voxel_size:
            raise ValueError(
                f"edge_radius ({self.edge_radius} m) must be at least voxel_size ({self.voxel_size} m), "
                "or neighbouring voxels are never joined"
            )
        if self.edge_radius > MAX_EDGE_VOXELS * self.voxel_size:
            raise ValueError(
                f"edge_radius ({self.edge_radius} m) above {MAX_EDGE_VOXELS} x voxel_size ({self.voxel_size} m) makes "
                "the graph too dense"
            )
        return self


#: widest edge radius in voxel sizes: a node's edges grow with the cube of the ratio
MAX_EDGE_VOXELS = 6


class TrunkParams(_Model):
    """Trunk detection without priors: where the canopy's shortest paths reach the ground."""

    contact_height: float = Field(0.08, gt=0.0, le=3.0, description="graph nodes this far above the top of the ground layer (the ground tolerance) can be a tree's ground contact [m]")
    cluster_radius: float | None = Field(None, gt=0.0, le=5.0, description="ground contacts closer than this are one trunk (and a group that is no trunk counts towards one within 1.25 times this); default: from the block's measured in-row tree spacing s, 0.8 x min(1, s / 2.2 m) [m]")
    min_tree_height: float | None = Field(None, gt=0.0, le=50.0, description="a tree's material reaches at least this height (its 95th height percentile; fence posts, bins and vehicles stay lower); default: from the block, half the median height of its contact groups that branch, at most 2 m and at least 0.7 m, a group below 2 m passing only if it branches (docs/method.md) [m]")
    min_canopy_voxels: int | None = Field(None, ge=1, le=10_000_000, description="least number of voxels whose shortest path ends in a trunk; default: from the block, a quarter of the median catchment of its contact groups that branch, at most 150 and at least 20, a group below 150 passing only if it branches [voxels]")
    leaf_cost: float = Field(4.0, ge=0.0, le=100.0, description="drainage paths through fully scattered (leafy) nodes cost this much more, so canopies drain down their branches [x]")
    satellite_radius: float | None = Field(None, ge=0.0, le=10.0, description="a contact this close to a stronger trunk (up to twice as far to a much stronger one, see satellite_ratio) is that tree's foliage touching the ground; also the reach of the stem test; default: from the block's measured in-row tree spacing s, 2.0 x min(1, s / 2.2 m)^2 [m]")
    satellite_ratio: float = Field(1.5, ge=1.0, le=100.0, description="a contact near a trunk is its satellite when the trunk drains this many times more material, times (distance / satellite_radius)^2 beyond satellite_radius [x]")
    max_trunk_width: float = Field(1.0, gt=0.0, le=5.0, description="widest trunk cross-section accepted near the ground [m]")
    max_planar_fraction: float = Field(0.15, ge=0.0, le=1.0, description="objects whose material below min_tree_height is more planar (box-like) than this are not trees [fraction]")
    stem_ratio: float = Field(3.0, ge=0.0, le=1000.0, description="a contact group is shoots touching down, not a trunk, when a trunk within satellite_radius drains at least half as much and its stem stands out this many times more clearly in the 0.3 m above the ground layer; 0 = off [x]")
    max_post_radius: float | None = Field(None, ge=0.0, le=1.0, description="for trellised rows: a contact group standing on a straight vertical pole of one thickness up to this radius, from 0.3 to 2.2 m above the ground and ending below max_post_height, is a trellis post and no tree material (looked for on scans with under 0.05 m of ground noise). Default: 0.08 m, its posts kept where without them the trees stand 1.8 m or more apart in the row (a straight central leader, as tall spindles at closer spacing have, can pass for a post; docs/limits.md); 0 = off [m]")
    max_post_height: float = Field(4.5, gt=2.5, le=20.0, description="a trellis post ends below this height; a pole still going on at it is a tree's bole (see max_post_radius) [m]")
    min_foot_ratio: float = Field(0.0, ge=0.0, le=100.0, description="a trunk continues into the ground layer: the density of points in the upper half of the ground layer within 0.2 m of its centre must be at least this many times that 0.2-0.8 m around it (a shoot hanging into the grass has no foot); off by default, as it also drops trunks on clean scans (docs/limits.md); try 1.0; 0 = off [x]")

    def needs_floors(self) -> bool:
        """Whether a size floor is left to follow the block's trees."""
        return self.min_tree_height is None or self.min_canopy_voxels is None

    def at_floors(self, height: float | None = None, size: float | None = None) -> "TrunkParams":
        """These parameters with every size floor left unset set: ``height`` [m] and
        ``size`` [voxels] measured on the block, or the mature trees' floors (None)."""
        update = {}
        if self.min_tree_height is None:
            update["min_tree_height"] = MATURE_FLOORS["min_tree_height"] if height is None else float(height)
        if self.min_canopy_voxels is None:
            update["min_canopy_voxels"] = MATURE_FLOORS["min_canopy_voxels"] if size is None else int(size)
        return self.model_copy(update=update)

    def needs_spacing(self) -> bool:
        """Whether a radius is left to follow the block's tree spacing."""
        return any(getattr(self, f) is None for f in SPACING_RADII["trunks"])

    def at_spacing(self, spacing: float | None) -> "TrunkParams":
        """These parameters with every radius left unset set from the in-row tree
        ``spacing`` [m] (None: not measured, the free-standing trees' values)."""
        return self.model_copy(update=_from_spacing(self, "trunks", spacing))


class SegmentParams(_Model):
    """Segmentation by shortest path from all trunks at once."""

    max_crown_radius: float = Field(5.0, gt=0.1, le=30.0, description="farthest any tree's material reaches from its trunk, horizontally; it sets the tile buffer (raise it for wide trees taller than crown_radius / crown_per_height) [m]")
    crown_radius: float = Field(5.0, gt=0.1, le=30.0, description="farthest a tree's material reaches from its trunk, horizontally, unless crown_per_height makes it more; never more than max_crown_radius [m]")
    crown_per_height: float = Field(1.0, ge=0.0, le=5.0, description="a tall tree's material reaches this many times its height from its trunk, horizontally, where that is more than crown_radius (wide old trees) [x]")
    leaf_cost: float = Field(0.0, ge=0.0, le=100.0, description="segmentation paths through fully scattered (leafy) nodes cost this much more (0 = plain distance) [x]")
    floating_height: float = Field(0.5, ge=0.0, le=20.0, description="unreached fragments whose lowest point is above this height are canopy and join the nearest tree; lower ones are separate objects [m]")
    min_fragment: int = Field(3, ge=1, le=10_000, description="unreached fragments of fewer graph nodes than this are noise (outliers) and stay unlabelled, unless they float within fragment_reach of a tree [nodes]")
    fragment_reach: float = Field(0.3, ge=0.0, le=5.0, description="a floating unreached fragment smaller than min_fragment (a lone leaf at the crown's rim) joins the nearest tree if a tree node, or a fragment that joined, lies this close; farther it is an outlier [m]")
    foot_margin: float = Field(0.03, ge=0.0, le=0.5, description="ground points within the trunk's fitted circle plus this margin are the trunk's foot and belong to the tree [m]")
    unreached_radius: float | None = Field(None, ge=0.0, le=10.0, description="points the graph does not reach go to the nearest trunk if a tree node lies this close; default: from the block's measured in-row tree spacing s, 0.6 x min(1, s / 2.2 m) [m]")
    surface_area: float = Field(0.4, ge=0.0, le=1000.0, description="a connected planar surface this large standing above floating_height (a vehicle's or a bin's side, a wall) is never tree material, nor is anything within surface_margin of it; 0 = off [m^2]")
    surface_margin: float = Field(0.3, ge=0.0, le=5.0, description="material this close to such a surface belongs to the object (its edges, wheels) [m]")
    grass_height: float = Field(0.3, ge=0.0, le=2.0, description="graph nodes lower than this above the ground and farther than grass_clearance from every trunk are grass or the feet of clutter: never tree material, and no path runs through them (a crown at a row's end does not spread over the headland's grass); 0 = off [m]")
    grass_clearance: float = Field(0.5, ge=0.0, le=5.0, description="low nodes this close to a trunk are its foot, not grass (see grass_height) [m]")
    method: Literal["paths", "refined"] = Field("refined", description="'paths': every node goes to the trunk of its shortest path (the paper's rule); 'refined': then the contested nodes (another trunk's path at most contest_margin longer) go where a random walk from them most likely ends, among the trees' settled nodes")
    contest_margin: float = Field(0.2, ge=0.0, le=5.0, description="with method 'refined', a node is contested when another trunk's shortest path to it is at most this much longer than its own [m]")

    def at_spacing(self, spacing: float | None) -> "SegmentParams":
        """These parameters with every radius left unset set from the in-row tree
        ``spacing`` [m] (None: not measured, the free-standing trees' values)."""
        return self.model_copy(update=_from_spacing(self, "segment", spacing))


#: Size floors left unset (None) follow the block's trees (:func:`pipeline.floors.block_floors`);
#: these are their caps, the mature trees' floors, which hold on blocks of grown trees
MATURE_FLOORS: dict[str, float] = {"min_tree_height": 2.0, "min_canopy_voxels": 150}


#: Radii left unset (None) follow the block's in-row tree spacing s [m]
#: (:mod:`pipeline.spacing`): each is ``cap * min(1, s / FULL_SPACING) ** power``, by
#: field: (cap [m], power). The caps suit free-standing trees and hold from FULL_SPACING
#: up; the satellite radius shrinks faster, as a dense row's trees are trained narrow.
FULL_SPACING = 2.2
SPACING_RADII: dict[str, dict[str, tuple[float, float]]] = {
    "trunks": {"cluster_radius": (0.8, 1.0), "satellite_radius": (2.0, 2.0)},
    "segment": {"unreached_radius": (0.6, 1.0)},
}


def _from_spacing(model: _Model, group: str, spacing: float | None) -> dict[str, float]:
    """The radii of ``model`` left unset, from ``spacing`` [m] by SPACING_RADII."""
    out = {}
    for field, (cap, power) in SPACING_RADII[group].items():
        if getattr(model, field) is None:
            out[field] = cap if spacing is None else cap * min(1.0, spacing / FULL_SPACING) ** power
    return out


#: the wood threshold the paper selected on its real data
PAPER_THRESHOLD = 0.216
#: the combined score's threshold that maximises wood F1 on the training orchards
#: (printed by ``python -m bench.fit_matter`` with the weights in pipeline.woodleaf)
COMBINED_THRESHOLD = 0.34


class MatterParams(_Model):
    """Wood/leaf classification from shortest-path counts."""

    method: Literal["combined", "paper"] = Field(
        "combined", description="'paper': S = log(p)/log(p_max) with a fixed threshold; 'combined': per-tree score, smoothing and shape features"
    )
    threshold: float | None = Field(
        None, ge=0.0, le=1.0,
        description="score at or above which a voxel is wood; default per method: 0.34 for 'combined' (best wood F1 on the "
        "training orchards), 0.216 for 'paper' (the paper's value) [0-1]",
    )
    smoothing_radius: float = Field(0.25, ge=0.05, le=2.0, description="neighbourhood over which scores and shape features are averaged [m]")

    def effective_threshold(self) -> float:
        if self.threshold is not None:
            return self.threshold
        return PAPER_THRESHOLD if self.method == "paper" else COMBINED_THRESHOLD


class MetricsParams(_Model):
    """Per-tree measurements."""

    trunk_height: float = Field(0.3, gt=0.0, le=5.0, description="height above the trunk base where the trunk diameter is measured [m]")
    trunk_slice: float = Field(0.1, gt=0.0, le=1.0, description="thickness of the slice used for the trunk diameter [m]")
    crown_base: float = Field(0.5, ge=0.0, le=20.0, description="tree material above this height counts as crown [m]")
    max_trunk_radius: float = Field(0.5, gt=0.0, le=5.0, description="thickest trunk: a stem circle (for the diameter, or the trunk's foot in the ground layer) of a larger radius, or centred farther from the trunk, fits something else and is ignored [m]")


class RowParams(_Model):
    """Rows, tree addresses and empty slots (:func:`pipeline.rows.find_rows`)."""

    enabled: bool = Field(True, description="find the rows and give every tree a row and position")
    max_gap_slots: float = Field(6.0, ge=1.5, le=100.0, description="two trees this many planting slots apart (a run of empty slots between them) still belong to one row [slots]")
    lateral_tolerance: float = Field(0.3, gt=0.0, lt=0.5, description="two trees are neighbours in a row when one lies at most this fraction of the distance between rows to the side of the other's row line [fraction]")
    max_offset: float = Field(0.2, gt=0.0, lt=0.5, description="a tree farther than this fraction of the distance between rows from its row's line is off the row (a false trunk between rows, a lone tree) [fraction]")
    max_section_angle: float = Field(15.0, gt=0.0, le=45.0, description="neighbouring trees whose row directions differ by more than this belong to different sections (blocks of another row direction) [degrees]")
    young_ratio: float = Field(0.6, gt=0.0, lt=1.0, description="a tree lower than this fraction of the median height of its two neighbours on either side in its row is a replant (young) [fraction]")
    drop_between_rows: bool = Field(True, description="a trunk standing between two rows (off both row lines, within the rows' extent; or less than half a row spacing beyond an outer row) is no tree but foliage or a weed touching down: its material goes to the nearest tree; a trunk with a stem of its own (a bole in a closed stand) is never dropped")


class PipelineParams(_Model):
    """Everything the per-block pipeline needs; stored with each job."""

    ground: GroundParams = GroundParams()
    graph: GraphParams = GraphParams()
    trunks: TrunkParams = TrunkParams()
    segment: SegmentParams = SegmentParams()
    matter: MatterParams = MatterParams()
    metrics: MetricsParams = MetricsParams()
    rows: RowParams = RowParams()

    def reach(self) -> float:
        """Horizontal distance [m] beyond which a point does not change a label.

        A tile's buffer must be at least this wide for tiled results to equal untiled
        ones: a tree with material in the core has its trunk within
        ``max_crown_radius`` of it, and the paths from that trunk to the core run
        close to the line between them, within PATH_MARGIN of the crown radius.
        """
        return self.segment.max_crown_radius + PATH_MARGIN + self.graph.edge_radius


#: how far beyond the crown radius [m] the paths from a trunk to its crown run (the
#: tiled-equals-untiled tests of tests/workers hold with it)
PATH_MARGIN = 1.0


GROUPS: dict[str, type[_Model]] = {
    "ground": GroundParams,
    "graph": GraphParams,
    "trunks": TrunkParams,
    "segment": SegmentParams,
    "matter": MatterParams,
    "metrics": MetricsParams,
    "rows": RowParams,
}
