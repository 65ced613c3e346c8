"""workers.job.report_sample: the report's points from memory equal those read back from the files."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.reading import read_points
from service.reports.sampling import sample_points
from workers.job import REPORT_POINTS, report_sample, run_job
from workers.jobspec import JobSpec


def _same(sample: dict, read: tuple) -> None:
    xy, tree_id, origin = read
    assert sample["xy"].dtype == xy.dtype and sample["tree_id"].dtype == tree_id.dtype
    np.testing.assert_array_equal(sample["xy"], xy)  # bit for bit: the map's PNG must not change
    np.testing.assert_array_equal(sample["tree_id"], tree_id)
    np.testing.assert_array_equal(sample["origin"], origin)


@pytest.fixture(scope="module")
def whole(small_block, tmp_path_factory):
    """The small block's job, in one piece."""
    return run_job(JobSpec(str(small_block), str(tmp_path_factory.mktemp("whole"))))


def test_a_whole_block_job_carries_the_points_the_report_would_read(small_block, whole):
    outcome = whole
    assert outcome.sample["max_points"] == REPORT_POINTS
    read = sample_points(str(small_block), outcome.outputs["points"], max_points=REPORT_POINTS)
    assert (read[1] > 0).any() and (read[1] == 0).any()  # trees and other points alike
    _same(outcome.sample, read)


@pytest.mark.parametrize("max_points", [1, 999, 10**9])
def test_report_sample_takes_every_stride_th_point(small_block, whole, max_points):
    outcome = whole
    xyz, info = read_points(str(small_block))
    table = pq.read_table(outcome.outputs["points"], columns=["point_index", "tree_id"])
    tree_id = np.zeros(len(xyz), np.int64)
    tree_id[table.column(0).to_numpy().astype(np.int64)] = table.column(1).to_numpy()
    _same(report_sample(xyz, tree_id, info.origin, max_points),
          sample_points(str(small_block), outcome.outputs["points"], max_points=max_points))


@pytest.mark.parametrize("chunk_points", [30_001, 2_000_000])
def test_a_tiled_job_carries_the_points_the_tiler_kept_as_the_report_would_read_them(small_block, tmp_path,
                                                                                    chunk_points):
    from pipeline.jobparams import JobParams, TilingParams
    from workers.runoptions import RunOptions

    outcome = run_job(JobSpec(str(small_block), str(tmp_path / "out"),
                              job=JobParams(tiling=TilingParams(tile_size=10.0)), run=RunOptions(chunk_points=chunk_points)))
    assert outcome.n_tiles > 1 and outcome.sample["max_points"] == REPORT_POINTS
    read = sample_points(str(small_block), outcome.outputs["points"], max_points=REPORT_POINTS)
    assert (read[1] > 0).any() and (read[1] == 0).any()
    _same(outcome.sample, read)


def test_a_partial_tiled_job_gives_the_failed_tiles_points_no_tree(small_block, tmp_path):
    from pipeline.jobparams import JobParams, TilingParams

    outcome = run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=10.0)),
                              work_dir=str(tmp_path / "work"), inject_failure=(3,)))
    assert outcome.partial
    _same(outcome.sample, sample_points(str(small_block), outcome.outputs["points"], max_points=REPORT_POINTS))
