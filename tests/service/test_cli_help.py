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


def test_nonsense_parameter_is_one_line_exit_2(tmp_path):
    p = subprocess.run(
        [sys.executable, "-m", "service.cli", "process", "x.laz", "--out", str(tmp_path / "o"), "--graph-voxel-size", "-1"],
        capture_output=True,
        text=True,
    )
    assert p.returncode == 2
    assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
