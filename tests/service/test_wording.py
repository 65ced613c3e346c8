"""Domain errors worded at each edge: options on the command line, fields in the API;
and every tiling default written once, in the model."""

import argparse
import json
import sys

import pytest

from pipeline.errors import NoTreesError, ParameterError
from pipeline.jobparams import TilingParams
from service.commands import process
from service.settings import Settings
from service.wording import api_errors, api_location, api_words, cli_name, cli_words, validation_words
from workers.runoptions import RunOptions


def _hand_made() -> ParameterError:
    return ParameterError(
        "tile buffer 2 m is smaller than the reach (6.15 m); ",
        hint="use {tiling.buffer} 6.15 or more with {tiling.tile_size} 20, or a smaller {segment.max_crown_radius}",
        param="tiling.buffer", value=2.0, limit=6.15,
    )


def test_a_hand_made_error_rendered_both_ways():
    exc = _hand_made()
    assert cli_words(exc) == ("tile buffer 2 m is smaller than the reach (6.15 m); use --buffer 6.15 or more with "
                              "--tile-size 20, or a smaller --segment-max-crown-radius")
    assert api_words(exc) == ("tile buffer 2 m is smaller than the reach (6.15 m); use tiling.buffer 6.15 or more with "
                              "tiling.tile_size 20, or a smaller params.segment.max_crown_radius")
    assert api_errors(exc) == [{"loc": ["body", "tiling", "buffer"], "msg": api_words(exc), "type": "parameter",
                                "input": 2.0, "limit": 6.15}]


def test_the_api_names_the_upload_and_the_command_line_words_a_run_s_settings():
    exc = NoTreesError("ab12cd.laz: no trees found in 50000 points; ",
                       hint="lower {trunks.min_tree_height} / {trunks.min_canopy_voxels}; the work store is {job.work_dir}")
    assert api_words(exc, block_path="/srv/data/blocks/ab12cd.laz", filename="north-block.laz") == (
        "north-block.laz: no trees found in 50000 points; lower params.trunks.min_tree_height / "
        "params.trunks.min_canopy_voxels; the work store is ORCHARD_WORK_DIR")
    assert api_words(exc, hint=False, block_path="/x/ab12cd.laz") == "the block: no trees found in 50000 points; "
    assert cli_words(exc).endswith("lower --trunks-min-tree-height / --trunks-min-canopy-voxels; the work store is --work")
    assert api_errors(exc) is None  # it names no field at fault


def test_braces_that_are_no_parameter_stay_as_they_are():
    exc = ParameterError("inbox '/srv/{farm}/x' and {Not.a} path; {tiling.buffer}")
    assert cli_words(exc) == "inbox '/srv/{farm}/x' and {Not.a} path; --buffer"


@pytest.mark.parametrize("path, flag, loc", [
    ("tiling.tile_size", "--tile-size", ["body", "tiling", "tile_size"]),
    ("tiling.worker_memory", "--worker-memory", None),  # a setting of the service
    ("tiling.engine", "--engine", None),
    ("trunks.cluster_radius", "--trunks-cluster-radius", ["body", "params", "trunks", "cluster_radius"]),
    (("body", "params", "graph", "voxel_size"), "--graph-voxel-size", ["body", "params", "graph", "voxel_size"]),
    (("tiling", "chunk_points"), None, None),
    ("job.out_dir", "--out", None),
])
def test_paths_as_options_and_body_locations(path, flag, loc):
    assert cli_name(path) == flag
    assert api_location(path) == loc


def test_validation_errors_name_the_option():
    errors = [{"loc": ("graph", "voxel_size"), "msg": "Input should be greater than or equal to 0.02"},
              {"loc": ("tile_size",), "msg": "Input should be a finite number"},
              {"loc": ("ground",), "msg": "Value error, too many cells"}]
    assert validation_words(errors) == ["--graph-voxel-size: Input should be greater than or equal to 0.02",
                                        "--tile-size: Input should be a finite number",
                                        "ground: Value error, too many cells"]


def _defaults(add, *argv) -> dict:
    parser = argparse.ArgumentParser()
    add(parser)
    return {a.dest: a for a in parser._actions}


def test_every_tiling_default_is_the_model_s():
    model = {name: f.default for name, f in TilingParams.model_fields.items()}
    run = {name: f.default for name, f in RunOptions.model_fields.items()}
    assert run["worker_memory"] is None  # a model has no budget: a deployment's settings give one
    # the command line's options are unset (None): the command applies the model's, or a setting's, at its edge
    actions = _defaults(process.add_arguments)
    for name in ("tile_size", "buffer", "grid_origin", "engine", "workers", "worker_memory"):
        assert actions[name].default is None, name
        assert f"--{name.replace('_', '-')}" in actions[name].option_strings
    settings = Settings.model_fields
    assert f"default {run['workers']}," in actions["workers"].help
    assert f"or {settings['worker_memory_gb'].default:g})" in actions["worker_memory"].help
    assert f"(default {run['engine']})" in actions["engine"].help
    # the settings that stand for them: the run options' default and bounds
    assert settings["n_workers"].default == run["workers"]
    for setting, name in (("n_workers", "workers"), ("worker_memory_gb", "worker_memory")):
        assert RunOptions.model_fields[name].metadata == settings[setting].metadata[:2], setting
    # built from no options: the model's tiling, and the run options with the setting's budget
    args = argparse.Namespace(tile_size=None, buffer=None, grid_origin=None, engine=None, workers=None, worker_memory=None)
    assert process._tiling(args) == TilingParams() and model["tile_size"] is None
    assert process._run_options(args) == RunOptions(worker_memory=Settings().worker_memory_gb)
    # --tile-size 0: one piece, no budget
    zero = argparse.Namespace(**{**vars(args), "tile_size": 0.0})
    assert process._tiling(zero) == TilingParams() and process._run_options(zero) == RunOptions()


def test_the_api_tiling_body_has_the_model_s_bounds_and_defaults():
    from service.api.schemas import Tiling

    for name, field in Tiling.model_fields.items():
        ours = TilingParams.model_fields[name]
        assert field.metadata == ours.metadata and field.description == ours.description, name
        assert field.is_required() or field.default == ours.default, name
    assert Tiling.model_fields["tile_size"].is_required()


def test_the_cli_does_not_import_the_http_app():
    import subprocess

    code = ("import sys; from service.cli import build_parser; "
            "[build_parser([c]) for c in ('process', 'schedules')]; "
            "import service.runner, service.wording, service.jobrequests, service.db.jobstore, workers.job; "
            "print(sorted(m for m in ('fastapi', 'starlette', 'service.app', 'service.errors') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert json.loads(out.replace("'", '"')) == []
