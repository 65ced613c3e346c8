"""The per-block pipeline: ground → voxel graph → trunks → segmentation → wood/leaf.

`process_points` is what a dask task runs on a buffered tile and what a single-block
run runs on the whole block. It composes the kernels; it reads no files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.params import PipelineParams


@dataclass(frozen=True)
class BlockResult:
    """Per-point labels and per-trunk data for one block or buffered tile.

    Attributes
    ----------
    tree_id : (n,) int64
        0 = not a tree (ground, clutter); k >= 1 is the tree whose trunk is ``trunks[k-1]``.
    is_ground : (n,) bool
    is_wood : (n,) bool
        Always False where ``tree_id == 0``.
    wood_score : (n,) float32
        In [0, 1]; the score that was thresholded to give ``is_wood``.
    height : (n,) float32
        Height above the ground surface [m].
    trunks : (k, 3) float64
        Trunk base (centre of the trunk where it meets the ground), in the frame of the input xyz.
    trunk_support : (k,) float64
        Number of graph nodes whose shortest path to the ground ends in this trunk
        (a confidence, used to break ties when tiles disagree).
    trunk_diameter : (k,) float64
        Trunk diameter at ``params.metrics.trunk_height`` [m]; NaN when not measurable.
    """

    tree_id: np.ndarray
    is_ground: np.ndarray
    is_wood: np.ndarray
    wood_score: np.ndarray
    height: np.ndarray
    trunks: np.ndarray
    trunk_support: np.ndarray
    trunk_diameter: np.ndarray

    @property
    def n_trees(self) -> int:
        return int(self.trunks.shape[0])


def process_points(
    xyz: np.ndarray,
    *,
    params: PipelineParams,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> BlockResult:
    """Run the whole per-block pipeline on one point cloud.

    Parameters
    ----------
    xyz : (n, 3) float64
        Point coordinates [m] in a local frame (input coordinates minus a block origin).
    params : PipelineParams
    grid_origin : (3,) float
        Origin of the voxel and ground grids in the same frame. Tiles of one block pass
        the same value so that their grids line up and results agree across tiles.

    Returns
    -------
    BlockResult
    """
    raise NotImplementedError
