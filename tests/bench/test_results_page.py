"""The benchmark report renders a run's raw data and splices it into docs/benchmarks.md."""

from bench.__main__ import write_outputs
from bench.results_page import END, START, render, splice_section

MACHINE = {"date": "2026-01-01 00:00 UTC", "cpu": "test CPU", "logical_cores": 2, "usable_cores": 2, "ram_gib": 1.0,
           "os": "Linux", "python": "CPython 3.11", "versions": {"numpy": "2"}}


def test_tile_size_table_by_hand():
    row = {"tile_size": 20.0, "buffer_factor": ((20 + 2 * 6.15) / 20) ** 2, "n_tiles": 10, "n_found": 51, "wall_s": 24.8,
           "cpu_s": 45.9, "points_per_s": 10_158_991 / 24.8, "worker_maxrss": [0.9 * 2**30, 0.91 * 2**30],
           "timings": {"tile": 5.6, "process": 18.5, "merge_write": 0.7}}
    data = {"machine": MACHINE, "command": "python -m bench", "elapsed_s": 60.0,
            "tiles": {"rows": [row], "workers": 2, "buffer": 6.15,
                      "block": {"n_points": 10_158_991, "n_trees": 51}}}
    text = render(data)
    assert "## Tile size" in text and "a 6.15 m buffer on every side" in text
    assert "| 20 m | 2.61 | 10 | 51 | 24.8 s | 45.9 s | 0.41 M/s | 5.6 s / 18.5 s / 0.7 s | 0.91 GiB |" in text
    assert "## Tile size" not in render({k: v for k, v in data.items() if k != "tiles"})


PAGE = f"""# Benchmarks

Intro kept.

{START}
old figures
{END}

## Against raycloudtools

kept too
"""


def test_splice_replaces_only_the_marked_section(tmp_path):
    page = tmp_path / "benchmarks.md"
    page.write_text(PAGE)
    results = "# Benchmark results\n\nGenerated.\n\n## Accuracy\n\n![accuracy](accuracy.png)\n\n### Trunk diameters\n"
    assert splice_section(page, results, image_prefix="../bench/")
    text = page.read_text()
    assert "old figures" not in text and "Benchmark results" not in text
    assert text.startswith("# Benchmarks\n\nIntro kept.\n\n" + START + "\nGenerated.")
    # nested under the page's level-1 title: levels unchanged; plots linked from docs/
    assert "\n## Accuracy\n" in text and "\n### Trunk diameters\n" in text
    assert "![accuracy](../bench/accuracy.png)" in text
    assert text.endswith(END + "\n\n## Against raycloudtools\n\nkept too\n")


def test_splice_leaves_a_page_without_markers_alone(tmp_path):
    page = tmp_path / "benchmarks.md"
    page.write_text("# Benchmarks\n\nno markers\n")
    assert not splice_section(page, "# Benchmark results\n")
    assert page.read_text() == "# Benchmarks\n\nno markers\n"
    assert not splice_section(tmp_path / "missing.md", "# Benchmark results\n")


def test_write_outputs_fills_the_docs_page_not_the_readme(tmp_path):
    page = tmp_path / "docs" / "benchmarks.md"
    page.parent.mkdir()
    page.write_text(PAGE)
    readme = tmp_path / "README.md"
    readme.write_text(f"# x\n{START}\nkeep\n{END}\n")
    data = {"machine": MACHINE, "command": "python -m bench", "elapsed_s": 60.0}
    write_outputs(data, tmp_path / "bench", page=page, log=lambda msg: None)
    results = (tmp_path / "bench" / "results.md").read_text()
    body = results.split("\n", 1)[1].strip()  # the page keeps its own title
    assert body and body in page.read_text() and "old figures" not in page.read_text()
    assert "keep" in readme.read_text()


def test_scaling_table_gives_every_process_by_hand():
    gib = 2**30
    row = {"target": 100_000_000, "n_points": 100_000_000, "n_trees": 576, "n_found": 575, "n_tiles": 60, "wall_s": 400.0,
           "cpu_s": 760.0, "points_per_s": 250_000.0, "main_maxrss": 0.8 * gib, "worker_maxrss": [1.18 * gib, 1.2 * gib],
           "tree_peak_total": 3.1 * gib, "sampled_peaks": {"main": [int(0.79 * gib)], "dask-worker": [int(1.2 * gib)] * 2,
                                                           "resource-tracker": [int(0.01 * gib)]},
           "decode": {"laspy_xyz_only": {"points_per_s": 5_000_000.0}}, "ratio_vs_decode": 0.05}
    data = {"machine": MACHINE, "command": "python -m bench --large", "elapsed_s": 60.0,
            "scaling": {"rows": [row], "exponent": float("nan"), "tile_size": 20.0, "workers": 2},
            "scaling_notes": ["a note"]}
    text = render(data)
    assert ("| 100,000,000 | 576 (575) | 60 | 400.0 s | 760.0 s | 1.90 | 0.25 M/s | 0.80 GiB | 1.20 / 1.18 GiB | "
            "resource-tracker 0.01 GiB | 3.10 GiB | 5.00 M/s | 0.050 |") in text
    assert "no scheduler process of its own" in text and "_a note_" in text
    # a run recorded before the per-process samples: the column says so, the rest renders
    old = dict(row, worker_maxrss=[1.2 * gib])
    del old["sampled_peaks"]
    assert "| 0.80 GiB | 1.20 GiB | – | 3.10 GiB |" in render(dict(data, scaling=dict(data["scaling"], rows=[old])))
