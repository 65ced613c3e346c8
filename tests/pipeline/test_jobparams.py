"""The job model: tiling beside pipeline parameters, with the rules a tiled job must keep."""

import pickle

import pytest
from pydantic import ValidationError

from pipeline.errors import ParameterError
from pipeline.jobparams import JobParams, TilingParams
from pipeline.params import PipelineParams, SegmentParams
from pipeline.tilelimits import MAX_COPIES, copies_per_point, min_tile_size


def test_a_buffer_below_the_reach_says_which_parameter_its_value_and_limit():
    reach = PipelineParams().reach()  # 5 + 1 + 0.15 m
    with pytest.raises(ParameterError) as err:
        JobParams(tiling=TilingParams(tile_size=20, buffer=2))
    exc = err.value
    assert (exc.param, exc.value, exc.limit) == ("tiling.buffer", 2.0, reach)
    assert "{tiling.buffer} 6.15 or more" in exc.hint and "{segment.max_crown_radius}" in exc.hint
    assert str(exc).endswith("use tiling.buffer 6.15 or more, or a smaller segment.max_crown_radius")


def test_a_smaller_crown_radius_lets_the_same_buffer_through():
    job = JobParams(pipeline=PipelineParams(segment=SegmentParams(max_crown_radius=0.5)),
                    tiling=TilingParams(tile_size=20, buffer=2))
    assert job.buffer() == 2.0


def test_without_a_buffer_the_reach_is_the_buffer_and_bounds_the_tile_size():
    reach = PipelineParams().reach()
    assert JobParams(tiling=TilingParams(tile_size=20)).buffer() == reach
    smallest = min_tile_size(reach)
    assert copies_per_point(smallest, reach) <= MAX_COPIES
    JobParams(tiling=TilingParams(tile_size=smallest))
    with pytest.raises(ParameterError) as err:
        JobParams(tiling=TilingParams(tile_size=smallest - 0.01))
    assert err.value.param == "tiling.tile_size" and err.value.limit == smallest
    assert "{tiling.tile_size}" in err.value.hint


def test_tiles_that_copy_each_point_too_often_are_refused_by_the_tiling_alone():
    with pytest.raises(ParameterError, match="copy each point"):
        TilingParams(tile_size=2, buffer=10)


def test_the_pdal_engine_needs_a_buffer_below_half_the_tile():
    JobParams(tiling=TilingParams(tile_size=20, buffer=7, engine="pdal"))
    JobParams(tiling=TilingParams(tile_size=12, buffer=7))  # the laspy engine takes any buffer
    with pytest.raises(ParameterError, match="PDAL engine") as err:
        TilingParams(tile_size=12, buffer=7, engine="pdal")
    assert (err.value.param, err.value.value, err.value.limit) == ("tiling.tile_size", 12.0, 14.0)
    with pytest.raises(ParameterError, match="PDAL engine"):  # the reach as the buffer: 6.15 m of 12 m
        JobParams(tiling=TilingParams(tile_size=12, engine="pdal"))


@pytest.mark.parametrize("field, value", [("tile_size", 0.5), ("tile_size", float("nan")), ("buffer", -1.0),
                                          ("buffer", 1e308), ("workers", 0), ("worker_memory", 0.0),
                                          ("engine", "gdal")])
def test_field_bounds_are_validation_errors_naming_the_field(field, value):
    with pytest.raises(ValidationError) as err:
        TilingParams(**{field: value})
    assert err.value.errors()[0]["loc"] == (field,)


def test_a_grid_origin_far_from_any_block_is_refused():
    with pytest.raises(ParameterError, match="grid origin must be finite and within") as err:
        TilingParams(tile_size=20, grid_origin=(1e21, 0.0))
    assert err.value.param == "tiling.grid_origin"


def test_the_memory_budget_is_in_bytes_and_none_is_no_budget():
    assert TilingParams(worker_memory=1.5).memory_budget == 1.5e9
    assert TilingParams(worker_memory=None).memory_budget is None


def test_a_structured_error_survives_a_trip_to_a_dask_worker():
    with pytest.raises(ParameterError) as err:
        JobParams(tiling=TilingParams(tile_size=20, buffer=2))
    back = pickle.loads(pickle.dumps(err.value))
    assert type(back) is ParameterError and str(back) == str(err.value)
    assert (back.param, back.value, back.limit, back.hint) == (err.value.param, 2.0, err.value.limit, err.value.hint)


@pytest.mark.parametrize("start, stride, first", [(0, 5, 0), (1, 5, 4), (5, 5, 0), (7, 5, 3), (10, 1, 0), (3, 4, 1)])
def test_first_sampled_is_the_runs_first_point_whose_index_is_a_multiple_of_the_stride(start, stride, first):
    from pipeline.jobparams import first_sampled

    assert first_sampled(start, stride) == first
    assert (start + first) % stride == 0 and 0 <= first < stride
