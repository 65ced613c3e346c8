"""`orchard --help` and `orchard process --help` start without the heavy libraries.

Start-up time is measured in docs/performance.md; here only what gets imported is
checked (no timed assertions), in a fresh interpreter so earlier tests' imports do
not hide a regression.
"""

import subprocess
import sys

import pytest

#: never needed to print help
HEAVY = ("dask", "distributed", "fastapi", "matplotlib", "pyproj", "pyarrow", "scipy", "laspy")

_PROBE = """
import sys
from service.cli import main
try:
    main({argv!r})
except SystemExit:
    pass
print("imported:", *sorted(name for name in {names!r} if name in sys.modules))
"""


def _imported_after(argv: list[str], names: tuple[str, ...]) -> set[str]:
    p = subprocess.run(
        [sys.executable, "-c", _PROBE.format(argv=argv, names=names)], capture_output=True, text=True, timeout=60
    )
    assert p.returncode == 0, p.stderr
    assert "usage:" in p.stdout
    last = p.stdout.rstrip("\n").splitlines()[-1]
    assert last.startswith("imported:")
    return set(last.split()[1:])


def test_top_level_help_imports_no_numpy_pydantic_or_service_libraries():
    assert _imported_after(["--help"], HEAVY + ("numpy", "pydantic")) == set()


@pytest.mark.parametrize("command", ["process", "simulate", "evaluate", "schedules"])
def test_command_help_imports_no_cluster_web_or_plotting_libraries(command):
    assert _imported_after([command, "--help"], HEAVY if command != "simulate" else HEAVY[:4]) == set()


_BAD_INPUT_PROBE = """
import sys
from service.cli import main
code = main({argv!r})
print("exit:", code)
print("imported:", *sorted(name for name in {names!r} if name in sys.modules))
"""


@pytest.mark.parametrize("kind", ["missing", "not LAS", "hostile header"])
def test_process_refuses_a_bad_input_before_importing_the_pipeline(tmp_path, kind):
    """A missing or unreadable input is refused from its header, before laspy, scipy,
    pyarrow and the cluster and plotting libraries load (they take most of a run's start-up)."""
    block = tmp_path / "block.laz"
    if kind == "not LAS":
        block.write_bytes(b"not a point cloud\n" * 10)
    if kind == "hostile header":  # a LAS 1.4 header announcing 4 billion VLRs in a 375-byte file
        head = bytearray(375)
        head[0:4], head[24], head[25] = b"LASF", 1, 4
        head[94:96] = (375).to_bytes(2, "little")
        head[96:100] = (375).to_bytes(4, "little")
        head[100:104] = (2**32 - 1).to_bytes(4, "little")
        block.write_bytes(bytes(head))
    argv = ["process", str(block), "--out", str(tmp_path / "out")]
    p = subprocess.run(
        [sys.executable, "-c", _BAD_INPUT_PROBE.format(argv=argv, names=HEAVY)], capture_output=True, text=True, timeout=60
    )
    assert p.returncode == 0, p.stderr
    lines = p.stdout.rstrip("\n").splitlines()
    assert lines[-2] == "exit: 2", p.stdout + p.stderr
    assert "block.laz" in p.stderr
    assert set(lines[-1].split()[1:]) == set()  # the header is checked by struct alone


_FIRST_READ_PROBE = """
import sys
import pipeline.reading

def first_read(*args, **kwargs):
    print("imported:", *sorted(name for name in {names!r} if name in sys.modules))
    raise SystemExit(0)

pipeline.reading.read_points = pipeline.reading.read_counted = first_read  # before anything imports them
from service.cli import main
main({argv!r})
"""


@pytest.mark.parametrize("n_points, budget", [(2_000, []), (200_000, ["--worker-memory", "0.4"])])
def test_process_reads_a_valid_block_before_importing_the_job(tmp_path, n_points, budget):
    """A block that surely fits the budget, and one counted for it (200,000 points may
    not fit 0.4 GB), are both read before scipy, pyarrow, the work store's fsspec and
    the cluster and plotting libraries load: the pipeline's imports come after."""
    import laspy
    import numpy as np

    block = tmp_path / "block.las"
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = [0.01] * 3
    las = laspy.LasData(header)
    rng = np.random.default_rng(0)
    las.x, las.y, las.z = rng.uniform(0, 10, n_points), rng.uniform(0, 10, n_points), rng.uniform(0, 3, n_points)
    las.write(block)
    names = ("scipy", "pyarrow", "fsspec", "dask", "distributed", "fastapi", "matplotlib", "laspy", "numpy")
    argv = ["process", str(block), "--out", str(tmp_path / "out"), *budget]
    p = subprocess.run([sys.executable, "-c", _FIRST_READ_PROBE.format(argv=argv, names=names)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert set(p.stdout.rstrip("\n").splitlines()[-1].split()[1:]) == {"laspy", "numpy"}


_RUN_PROBE = """
import sys
from service.cli import main
print("exit:", main({argv!r}))
print("imported:", *sorted(name for name in {names!r} if name in sys.modules))
"""


@pytest.mark.slow  # a whole run
def test_process_draws_the_reports_map_in_another_process(tmp_path):
    """matplotlib (its import about 0.4 s) loads in a process forked as the run starts
    (`service.reports.mapprocess`), not in the one that reads and processes the block."""
    from service_fixtures import simulated_block

    block = simulated_block(tmp_path / "b.laz", rows=1, trees_per_row=2, density=0.2, seed=3)
    out = tmp_path / "out"
    argv = ["process", str(block), "--out", str(out)]
    p = subprocess.run([sys.executable, "-c", _RUN_PROBE.format(argv=argv, names=("matplotlib", "pyarrow"))],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    lines = p.stdout.rstrip("\n").splitlines()
    assert lines[-2] == "exit: 0", p.stdout + p.stderr
    assert lines[-1].split()[1:] == ["pyarrow"]  # the probe works: the run's outputs loaded pyarrow
    assert (out / "map.png").read_bytes()[:4] == b"\x89PNG" and "data:image/png;base64," in (out / "report.html").read_text()


_FREEZE_PROBE = """
import gc, sys
from service.cli import main
main([])  # as a test or another program calls it
print("frozen:", gc.get_freeze_count())
sys.argv = ["orchard"]
main()  # as the console script does
print("frozen:", gc.get_freeze_count() > 0)
"""


def test_the_command_lines_process_leaves_its_objects_to_its_end():
    """`main()` for the command line freezes the garbage collector's objects as it returns:
    the interpreter's shutdown would search them for cycles again and again. Called with
    arguments it leaves them alone."""
    p = subprocess.run([sys.executable, "-c", _FREEZE_PROBE], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert [line for line in p.stdout.splitlines() if line.startswith("frozen:")] == ["frozen: 0", "frozen: True"]
