"""The job model: tiling beside pipeline parameters, with the rules a tiled job must keep
whatever its block (the block's own limits are planning's: tests/workers/test_job.py)."""

import pickle

import pytest
from pydantic import ValidationError

from pipeline.errors import ParameterError
from pipeline.jobparams import JobParams, TilingParams
from pipeline.params import PipelineParams, SegmentParams
from pipeline.tilelimits import MAX_BUFFER, MAX_TILE_SIZE, MIN_TILE_SIZE
from workers.runoptions import RunOptions


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


def test_without_a_buffer_the_reach_is_the_buffer():
    reach = PipelineParams().reach()
    assert JobParams(tiling=TilingParams(tile_size=20)).buffer() == reach


def test_limits_that_depend_on_the_block_are_left_to_planning():
    # a point of 2 m tiles with a 10 m buffer falls in up to 121 tiles of a large block,
    # in 1 of a block that is one tile: the model alone cannot tell, the block's grid can
    JobParams(tiling=TilingParams(tile_size=2, buffer=10))
    JobParams(tiling=TilingParams(tile_size=12, buffer=7))  # the PDAL engine's narrower buffer: a run option's


def test_one_set_of_bounds_the_model_states_those_of_tilelimits():
    fields = TilingParams.model_fields
    bounds = {name: {type(m).__name__: getattr(m, type(m).__name__.lower()) for m in fields[name].metadata}
              for name in ("tile_size", "buffer")}
    assert bounds["tile_size"] == {"Ge": MIN_TILE_SIZE, "Le": MAX_TILE_SIZE}
    assert bounds["buffer"] == {"Ge": 0.0, "Le": MAX_BUFFER}


@pytest.mark.parametrize("field, value", [("tile_size", 0.5), ("tile_size", float("nan")), ("tile_size", 2e5),
                                          ("buffer", -1.0), ("buffer", 1e308), ("buffer", 1.5e5)])
def test_field_bounds_are_validation_errors_naming_the_field(field, value):
    with pytest.raises(ValidationError) as err:
        TilingParams(**{field: value})
    assert err.value.errors()[0]["loc"] == (field,)


@pytest.mark.parametrize("field, value", [("workers", 0), ("worker_memory", 0.0), ("engine", "gdal"), ("chunk_points", 0)])
def test_run_options_are_no_part_of_the_job(field, value):
    assert field not in TilingParams.model_fields and field not in JobParams.model_fields
    with pytest.raises(ValidationError) as err:
        RunOptions(**{field: value})
    assert err.value.errors()[0]["loc"] == (field,)


def test_a_job_travels_whole_through_json():
    job = JobParams(pipeline=PipelineParams(segment=SegmentParams(max_crown_radius=2.0)),
                    tiling=TilingParams(tile_size=12.5, buffer=4.0, grid_origin=(1.0, 2.0)))
    assert JobParams.model_validate_json(job.model_dump_json()) == job
    assert JobParams.model_validate(job.model_dump(mode="json")) == job
    assert job.with_tile_size(30).tiling.tile_size == 30.0 and job.with_tile_size(30).pipeline == job.pipeline


def test_a_grid_origin_far_from_any_block_is_refused():
    with pytest.raises(ParameterError, match="grid origin must be finite and within") as err:
        TilingParams(tile_size=20, grid_origin=(1e21, 0.0))
    assert err.value.param == "tiling.grid_origin"


def test_the_memory_budget_is_in_bytes_and_none_is_no_budget():
    assert RunOptions(worker_memory=1.5).memory_budget == 1.5e9
    assert RunOptions(worker_memory=None).memory_budget is None


def test_a_structured_error_survives_a_trip_to_a_dask_worker():
    with pytest.raises(ParameterError) as err:
        JobParams(tiling=TilingParams(tile_size=20, buffer=2))
    back = pickle.loads(pickle.dumps(err.value))
    assert type(back) is ParameterError and str(back) == str(err.value)
    assert (back.param, back.value, back.limit, back.hint) == (err.value.param, 2.0, err.value.limit, err.value.hint)


@pytest.mark.parametrize("start, stride, first", [(0, 5, 0), (1, 5, 4), (5, 5, 0), (7, 5, 3), (10, 1, 0), (3, 4, 1)])
def test_first_sampled_is_the_runs_first_point_whose_index_is_a_multiple_of_the_stride(start, stride, first):
    from pipeline.mapsample import first_sampled

    assert first_sampled(start, stride) == first
    assert (start + first) % stride == 0 and 0 <= first < stride
