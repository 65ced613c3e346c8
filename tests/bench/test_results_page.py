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
