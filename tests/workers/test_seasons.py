"""Captures of one block over the seasons: keys, removed and replanted trees, coverage,
non-overlapping captures and failures, through jobs and ``orchard process --previous``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.errors import NoOverlapError
from pipeline.jobparams import JobParams, TilingParams
from pipeline.registration import RigidTransform
from simulator.plan import make_plan
from simulator.series import capture_series
from simulator.simparams import SimulationParams, local_origin
from simulator.truth import write_simulation
from service.cli import main
from workers.job import run_job
from workers.jobspec import JobSpec
from workers.seasons import capture_record

BASE = SimulationParams(form="spindle", rows=3, trees_per_row=8, spacing=1.2, row_spacing=3.5, density=0.3, seed=21,
                        posts=False, vehicle=False, bin=False)


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    """Three captures of one spindle block (1.2 m apart: every drift of the series is
    more than half the spacing in some direction), the first processed."""
    folder = tmp_path_factory.mktemp("series")
    caps = capture_series(BASE, 3, seed=2)
    paths = []
    for k, c in enumerate(caps):
        path = folder / f"cap{k}.laz"
        write_simulation(c.params, str(path), str(folder / f"cap{k}.truth.parquet"), creation_date=c.captured_at)
        paths.append(path)
    run_job(JobSpec(str(paths[0]), str(folder / "out0")))
    return caps, paths, folder


def _trees(out: Path) -> dict:
    return pq.read_table(out / "trees.parquet").to_pydict()


def _truth(capture) -> dict:
    """Grid slot → the true trunk position of its tree (input CRS)."""
    plan = make_plan(capture.params)
    return {int(s): p for s, p in zip(plan.layout.trees, plan.trunks[:, :2] + local_origin(capture.params)[:2])}


def _slot_keys(capture, out: Path) -> dict:
    """Grid slot → (key, row, position) of the output tree standing on it (truth trunks matched within 0.35 m)."""
    plan = make_plan(capture.params)
    truth = plan.trunks[:, :2] + local_origin(capture.params)[:2]
    t = _trees(out)
    xy = np.c_[t["trunk_x"], t["trunk_y"]]
    out_keys = {}
    for slot, p in zip(plan.layout.trees, truth):
        d = np.linalg.norm(xy - p, axis=1)
        if d.min() < 0.35:
            out_keys[int(slot)] = (t["tree_key"][int(d.argmin())], t["row"][int(d.argmin())], t["position"][int(d.argmin())])
    return out_keys


def test_a_first_capture_numbers_its_trees_and_starts_the_history(series):
    caps, paths, folder = series
    t = _trees(folder / "out0")
    assert t["tree_key"] == sorted(t["tree_key"]) == list(range(1, len(t["tree_id"]) + 1))
    assert set(t["status"]) == {"new"} and set(t["height_change_m"]) == {None}
    record = capture_record(folder / "out0")
    assert record["capture_id"] == "cap0" and record["captured_at"] == "2025-03-01"
    assert record["captured_at_source"] == "file" and record["previous_capture_id"] is None
    assert record["next_tree_key"] == len(t["tree_id"]) + 1
    history = pq.read_table(folder / "out0" / "history.parquet")
    assert history.num_rows == len(t["tree_id"]) and set(history.column("capture").to_pylist()) == {"cap0"}
    assert {"tree_key", "since"} <= set(pq.read_table(folder / "out0" / "gaps.parquet").column_names)


def test_the_same_capture_twice_keeps_every_key(series, tmp_path):
    caps, paths, folder = series
    run_job(JobSpec(str(paths[0]), str(tmp_path / "again"), previous=str(folder / "out0")))
    a, b = _trees(folder / "out0"), _trees(tmp_path / "again")
    assert b["tree_key"] == a["tree_key"] and set(b["status"]) == {"same"}
    assert (b["row"], b["position"]) == (a["row"], a["position"])
    assert capture_record(tmp_path / "again")["registration"]["residual_m"] < 1e-6
    # the capture's rows replace its earlier ones in the history, not added twice
    assert pq.read_table(tmp_path / "again" / "history.parquet").num_rows == len(a["tree_key"])


def test_a_drifted_capture_keeps_keys_and_reports_removed_and_replanted_trees(series, tmp_path):
    caps, paths, folder = series
    run_job(JobSpec(str(paths[1]), str(tmp_path / "b"), previous=str(folder / "out0")))
    before, after = _slot_keys(caps[0], folder / "out0"), _slot_keys(caps[1], tmp_path / "b")
    both = [s for s in before if s in after and s not in caps[1].cut]
    assert len(both) >= 20
    assert all(after[s] == before[s] for s in both)  # key and address
    record = capture_record(tmp_path / "b")
    reg = record["registration"]
    assert reg["residual_m"] < 0.1  # the trunks' own placement noise, both captures'
    true_b, true_a = _truth(caps[1]), _truth(caps[0])
    slots = [s for s in true_b if s in true_a]
    moved = RigidTransform(reg["dx"], reg["dy"], reg["rotation_deg"], reg["cx"], reg["cy"]).apply(
        np.array([true_b[s] for s in slots]))
    assert np.sqrt(np.mean(np.sum((moved - np.array([true_a[s] for s in slots])) ** 2, axis=1))) < 0.05
    gaps = pq.read_table(tmp_path / "b" / "gaps.parquet").to_pydict()
    removed = {k: (r, p) for k, r, p in zip(gaps["tree_key"], gaps["row"], gaps["position"]) if k is not None}
    for s in caps[1].cut:  # every cut tree at its address, with the capture that last saw it
        key, row, pos = before[s]
        assert removed[key] == (row, pos)
    assert set(s for k, s in zip(gaps["tree_key"], gaps["since"]) if k is not None) == {"cap0"}
    t = _trees(tmp_path / "b")
    same = np.array(t["status"]) == "same"
    assert np.mean(np.array(t["height_change_m"])[same] > 0) >= 0.9
    assert set(np.array(t["days_since_previous"])[same]) == {45.0}
    history = pq.read_table(tmp_path / "b" / "history.parquet").to_pydict()
    assert history["status"].count("removed") == len(caps[1].cut) == record["counts"]["removed"]


def test_a_capture_of_half_the_block_removes_nothing_outside_it(series, tmp_path):
    caps, paths, folder = series
    las = laspy.read(paths[1])
    mid = float(np.median(las.x))
    half = tmp_path / "half.laz"
    las.points = las.points[np.asarray(las.x) < mid]
    las.write(half)
    run_job(JobSpec(str(half), str(tmp_path / "half"), previous=str(folder / "out0")))
    before = _slot_keys(caps[0], folder / "out0")
    record = capture_record(tmp_path / "half")
    cut_keys = {before[s][0] for s in caps[1].cut if s in before}
    gaps = pq.read_table(tmp_path / "half" / "gaps.parquet").to_pydict()
    removed = {k for k in gaps["tree_key"] if k is not None}
    assert removed <= cut_keys  # nothing outside the half is called removed
    unseen = json.loads(pq.read_schema(tmp_path / "half" / "trees.parquet").metadata[b"orchard:unseen"])
    assert len(unseen) >= 8
    # the next full capture finds the unseen trees again under their keys
    run_job(JobSpec(str(paths[2]), str(tmp_path / "c"), previous=str(tmp_path / "half")))
    after = _slot_keys(caps[2], tmp_path / "c")
    kept = [s for s in before if s in after and s not in caps[1].cut and s not in caps[2].cut]
    assert len(kept) >= 18 and all(after[s][0] == before[s][0] for s in kept)


def test_captures_that_do_not_overlap_fail_naming_both_and_write_nothing(series, tmp_path, capsys):
    caps, paths, folder = series
    far = tmp_path / "elsewhere.laz"
    write_simulation(BASE.model_copy(update={"easting": BASE.easting + 300.0}), str(far), str(tmp_path / "t.parquet"))
    before = {p.name: p.read_bytes() for p in (folder / "out0").iterdir()}
    code = main(["process", str(far), "--out", str(tmp_path / "out"), "--previous", str(folder / "out0")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "elsewhere" in err and "cap0" in err
    assert not (tmp_path / "out").exists()
    assert {p.name: p.read_bytes() for p in (folder / "out0").iterdir()} == before
    with pytest.raises(NoOverlapError):
        run_job(JobSpec(str(far), str(tmp_path / "out"), previous=str(folder / "out0")))


@pytest.mark.parametrize("into_previous", [False, True])
def test_a_job_failing_during_registration_leaves_the_block_as_it_was(series, tmp_path, monkeypatch, into_previous):
    caps, paths, folder = series
    prev = tmp_path / "a"
    shutil.copytree(folder / "out0", prev)
    before = {p.name: p.read_bytes() for p in prev.iterdir()}

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # as a Ctrl-C or a stop lands mid-registration

    monkeypatch.setattr("workers.seasons.register", killed)
    out = prev if into_previous else tmp_path / "b"
    with pytest.raises(KeyboardInterrupt):
        run_job(JobSpec(str(paths[1]), str(out), previous=str(prev)))
    assert {p.name: p.read_bytes() for p in prev.iterdir()} == before
    assert into_previous or not out.exists()


@pytest.mark.slow
def test_tiled_and_whole_runs_agree_on_the_seasons_columns(series, tmp_path):
    caps, paths, folder = series
    whole, tiled = tmp_path / "whole", tmp_path / "tiled"
    run_job(JobSpec(str(paths[1]), str(whole), previous=str(folder / "out0")))
    run_job(JobSpec(str(paths[1]), str(tiled), previous=str(folder / "out0"), job=JobParams(tiling=TilingParams(tile_size=6.0))))
    assert capture_record(tiled)["counts"] == capture_record(whole)["counts"]
    cols = ["tree_key", "status", "row", "position", "height_change_m", "crown_volume_change_m3",
            "trunk_diameter_change_m", "days_since_previous"]
    a, b = (pq.read_table(d / "trees.parquet", columns=cols).to_pydict() for d in (whole, tiled))
    assert a == b
    for name in ("history.parquet", "gaps.parquet"):
        assert pq.read_table(whole / name).drop_columns(["geometry"] if name == "gaps.parquet" else []).equals(
            pq.read_table(tiled / name).drop_columns(["geometry"] if name == "gaps.parquet" else []))


def test_orchard_process_with_previous_end_to_end(series, tmp_path, capsys):
    caps, paths, folder = series
    code = main(["process", str(paths[1]), "--out", str(tmp_path / "b"), "--previous", str(folder / "out0"),
                 "--capture-id", "bloom", "--captured-on", "2025-04-20"])
    assert code == 0, capsys.readouterr().err
    header = (tmp_path / "b" / "trees.csv").read_text().splitlines()[0].replace('"', "").split(",")
    assert {"tree_key", "status", "height_change_m", "crown_volume_change_m3", "trunk_diameter_change_m",
            "days_since_previous"} <= set(header)
    record = capture_record(tmp_path / "b")
    # the file's header has a date: it wins over --captured-on
    assert (record["capture_id"], record["captured_at"], record["captured_at_source"]) == ("bloom", "2025-04-15", "file")
    assert record["previous_capture_id"] == "cap0"
    history = pq.read_table(tmp_path / "b" / "history.parquet").to_pydict()
    assert set(history["capture"]) == {"cap0", "bloom"}
