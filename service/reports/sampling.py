"""The subsample of a block's points that the report's map and the job page's
footprints draw: every ``stride``-th point, with its tree id, read in chunks so memory
stays bounded."""

from __future__ import annotations

import os

import numpy as np

from pipeline.blockinfo import read_info
from pipeline.mapsample import REPORT_POINTS, sample_stride
from pipeline.parquet import sampled_tree_ids
from pipeline.reading import sample_xy


def sample_points(
    block_path: str, points_parquet: str | os.PathLike, *, max_points: int = REPORT_POINTS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every ``stride``-th point of the block with its tree id.

    Returns
    -------
    xy : (m, 2) float64
        Local coordinates [m] (block coordinates minus ``origin``).
    tree_id : (m,) int64
    origin : (3,) float64
    """
    info = read_info(block_path)
    stride = sample_stride(info.n_points, max_points)
    xy, idx = sample_xy(block_path, stride, info=info)
    tree_id = sampled_tree_ids(points_parquet, idx, stride)
    return xy, tree_id, np.asarray(info.origin, dtype=np.float64)
