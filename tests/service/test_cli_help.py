"""Every command documents itself; every pipeline parameter is an option with its unit."""

import subprocess
import sys

import pytest

from pipeline.params import GROUPS
from service.commands import COMMANDS


@pytest.mark.parametrize("command", COMMANDS)
def test_help_of_every_command(command):
    p = subprocess.run([sys.executable, "-m", "service.cli", command, "--help"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr
    assert "usage:" in p.stdout


def test_process_help_lists_every_parameter_with_a_unit():
    p = subprocess.run([sys.executable, "-m", "service.cli", "process", "--help"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    text = " ".join(p.stdout.split())
    for group, model in GROUPS.items():
        for name in model.model_fields:
            assert f"--{group}-{name}".replace("_", "-") in text, name
    assert "[m]" in text


@pytest.mark.parametrize(
    "option, message",
    [
        (["--graph-voxel-size", "-1"], "--graph-voxel-size: Input should be greater than or equal to 0.02"),
        # allowed one by one, together hours of filtering and gigabytes on a worker
        (["--ground-cell-size", "0.0101"], "search_radius (1.0 m) spans more than 20 cells of cell_size (0.0101 m)"),
        (["--matter-threshold", "high"], "argument --matter-threshold: invalid float value: 'high' (see orchard process --help)"),
    ],
)
def test_nonsense_parameter_is_one_line_exit_2(tmp_path, option, message):
    p = subprocess.run(
        [sys.executable, "-m", "service.cli", "process", "x.laz", "--out", str(tmp_path / "o"), *option],
        capture_output=True,
        text=True,
    )
    assert p.returncode == 2
    assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert message in p.stderr, p.stderr


def test_process_help_shows_what_kind_of_value_each_option_takes():
    # metres as M, counts as N, other numbers as X (not argparse's P__GROUP__FIELD)
    p = subprocess.run([sys.executable, "-m", "service.cli", "process", "--help"], capture_output=True, text=True)
    text = " ".join(p.stdout.split())
    assert "P__" not in text
    assert "--trunks-cluster-radius M" in text
    assert "--trunks-min-canopy-voxels N" in text
    assert "--trunks-satellite-ratio X" in text
    assert "--matter-threshold X" in text  # float | None is a float option too


def test_a_missing_argument_is_one_line_exit_2():
    p = subprocess.run([sys.executable, "-m", "service.cli", "process"], capture_output=True, text=True)
    assert p.returncode == 2
    assert len(p.stderr.strip().splitlines()) == 1 and "INPUT" in p.stderr, p.stderr
