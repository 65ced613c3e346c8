"""``orchard process`` writes trees.csv and a self-contained report.html beside the Parquet files."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pyarrow.parquet as pq
import pytest
from service_fixtures import simulated_block

from service.cli import main


@pytest.mark.slow
def test_process_writes_trees_csv_and_a_report_that_opens_from_disk(tmp_path, capsys):
    block = simulated_block(tmp_path / "b.laz", rows=1, trees_per_row=3, density=0.3, seed=2)
    out = tmp_path / "o"
    assert main(["process", str(block), "--out", str(out)]) == 0, capsys.readouterr().err
    trees = pq.read_table(out / "trees.parquet")
    assert trees.num_rows >= 2

    with open(out / "trees.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == [n for n in trees.column_names if n != "geometry"] and len(rows) == trees.num_rows + 1

    text = (out / "report.html").read_text(encoding="utf-8")
    # everything inside: no script, style or image fetched from anywhere
    assert not re.search(r"<script[^>]*\bsrc=|<link[^>]*stylesheet", text)
    assert "Leaflet" in text and "Orchard report — b.laz" in text
    data = json.loads(re.search(r'<script type="application/json" id="orchard-data">(.*?)</script>', text, re.S).group(1))
    assert data["n_trees"] == trees.num_rows
    tx = trees.column("trunk_x").to_numpy()
    assert np.allclose(np.array(data["x"]) + data["origin"][0], tx, atol=0.01)
    assert all(o is not None and len(o) >= 6 for o in data["outlines"])  # every tree's footprint
    cfg = json.loads(re.search(r'<script type="application/json" id="orchard-report">(.*?)</script>', text, re.S).group(1))
    assert set(cfg["downloads"]) >= {"trees.csv", "trees.parquet", "points.parquet", "map.png"}
    assert all((out / name).is_file() for name in cfg["downloads"].values())  # links to the files beside it
