"""Jobs: tiled equals untiled, deterministic ids, failure policy, replay of a failed tile."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import laspy
import numpy as np
import pyarrow.parquet as pq
import pyproj
import pytest

from pipeline.errors import InputError, NoTreesError, ParameterError
from simulator.scoring.scores import v_measure
from pipeline.ground import raw_ground_model
from pipeline.jobparams import JobParams, TilingParams
from pipeline.params import PipelineParams
from workers.cluster import close_client, make_client
from workers.job import run_job
from workers.jobspec import JobSpec, TileFailed
from workers.replay import finish_job, run_tile
from workers.runoptions import RunOptions
from workers.tasks import ground_sample, process_tile, raw_ground_key, result_key
from workers.tiler import FRAME_KEY, INDEX_KEY, read_tile
from workers.workstore import WorkStore


def _points(out):
    return pq.read_table(out / "points.parquet").to_pydict()


def _trees(out):
    return pq.read_table(out / "trees.parquet")


@pytest.fixture(scope="module")
def tiled_ref(small_block, tmp_path_factory):
    """An undisturbed run of the small block in 10 m tiles and its output folder (read only)."""
    out = tmp_path_factory.mktemp("tiled-ref")
    return run_job(JobSpec(str(small_block), str(out), job=JobParams(tiling=TilingParams(tile_size=10.0)))), out


@pytest.mark.slow  # three whole runs of a block
def test_ids_do_not_depend_on_tiling(small_block, tmp_path):
    runs = [
        run_job(JobSpec(str(small_block), str(tmp_path / "a"))),
        run_job(JobSpec(str(small_block), str(tmp_path / "b"), job=JobParams(tiling=TilingParams(tile_size=9.0, grid_origin=(499_990.5, 6_949_990.25))))),
        run_job(JobSpec(str(small_block), str(tmp_path / "c"), job=JobParams(tiling=TilingParams(tile_size=14.0, buffer=8.0)))),
    ]
    ref = runs[0].trees
    assert ref["tree_id"].tolist() == list(range(1, 9))
    for r in runs[1:]:
        assert r.n_trees == 8
        assert np.hypot(r.trees["trunk_x"] - ref["trunk_x"], r.trees["trunk_y"] - ref["trunk_y"]).max() < 0.05
    pa, pc = _points(tmp_path / "a"), _points(tmp_path / "c")
    assert v_measure(np.asarray(pa["tree_id"]), np.asarray(pc["tree_id"])) >= 0.99
    for r in runs[1:]:  # addresses too, and the row and gap tables
        for col in ("row", "position", "young"):
            assert r.trees[col].tolist() == ref[col].tolist()
    for name in ("rows.parquet", "gaps.parquet"):
        a = pq.read_table(tmp_path / "a" / name).drop(["geometry"]).to_pydict()
        for other in ("b", "c"):
            b = pq.read_table(tmp_path / other / name).drop(["geometry"]).to_pydict()
            assert a.keys() == b.keys()
            for k in a:
                np.testing.assert_allclose(np.asarray(a[k], dtype=float), np.asarray(b[k], dtype=float), atol=0.05)


def test_rows_can_be_switched_off(small_block, tmp_path):
    out = tmp_path / "out"
    outcome = run_job(JobSpec(str(small_block), str(out), job=JobParams(pipeline=PipelineParams(rows={"enabled": False}))))
    assert sorted(p.name for p in out.iterdir()) == ["history.parquet", "points.parquet", "trees.parquet"]
    assert "row" not in outcome.trees


@pytest.fixture(scope="module")
def labelled_run(small_block, tmp_path_factory):
    """The small block's job in one piece with the labelled LAZ, and its output folder (read only)."""
    out = tmp_path_factory.mktemp("labelled") / "out"
    return run_job(JobSpec(str(small_block), str(out), labelled_laz=True)), out


def test_outputs_contract(small_block, labelled_run):
    outcome, out = labelled_run
    assert sorted(p.name for p in out.iterdir()) == ["gaps.parquet", "history.parquet", "labelled.laz", "points.parquet", "rows.parquet", "trees.parquet"]
    trees = _trees(out)
    assert trees.schema.field("tree_id").type == "int64" and trees.schema.field("n_points").type == "int64"
    assert [str(trees.schema.field(n).type) for n in ("row", "position", "young")] == ["int32", "int32", "bool"]
    # 2 rows of 4 trees: numbered from the south, positions from the west
    t = trees.to_pydict()
    order = np.lexsort((t["trunk_x"], np.round(np.asarray(t["trunk_y"]) / 6.0)))  # rows 6 m apart
    assert np.asarray(t["row"])[order].tolist() == [1] * 4 + [2] * 4
    assert np.asarray(t["position"])[order].tolist() == [1, 2, 3, 4] * 2
    rows = pq.read_table(out / "rows.parquet")
    assert rows.column("n_trees").to_pylist() == [4, 4] and rows.column("n_gaps").to_pylist() == [0, 0]
    assert json.loads(rows.schema.metadata[b"geo"])["columns"]["geometry"]["geometry_types"] == ["LineString"]
    assert pq.read_table(out / "gaps.parquet").num_rows == 0
    geo = json.loads(trees.schema.metadata[b"geo"])
    assert pyproj.CRS.from_json_dict(geo["columns"]["geometry"]["crs"]).to_epsg() == 28356
    points = pq.read_table(out / "points.parquet")
    assert [str(points.schema.field(n).type) for n in points.schema.names] == ["uint64", "int64", "bool", "bool", "float"]
    las = laspy.read(out / "labelled.laz")
    assert np.array_equal(las.tree_id, points.column("tree_id").to_numpy())
    assert len(las.points) == outcome.n_points
    # trunk coordinates are in the input CRS
    src = laspy.open(small_block).header
    assert np.all((trees.column("trunk_x").to_numpy() >= src.mins[0] - 1) & (trees.column("trunk_x").to_numpy() <= src.maxs[0] + 1))


@pytest.mark.slow
def test_in_process_dask_with_memory_store(small_block, tiled_ref, tmp_path):
    _, ref_out = tiled_ref
    client = make_client(n_workers=2, dashboard=False, processes=False)
    try:
        seen = []
        out = run_job(
            JobSpec(str(small_block), str(tmp_path / "mem"), job=JobParams(tiling=TilingParams(tile_size=10.0)), work_dir=f"memory://job-{tmp_path.name}"),
            client=client,
            progress=lambda d, t: seen.append((d, t)),
        )
    finally:
        close_client(client)
    assert seen[0] == (0, out.n_tiles) and seen[-1] == (out.n_tiles, out.n_tiles)
    assert _points(ref_out) == _points(tmp_path / "mem")
    assert _trees(ref_out).equals(_trees(tmp_path / "mem"))


def test_buffer_below_reach_is_refused_before_any_output(small_block, tmp_path):
    with pytest.raises(ParameterError, match="reach"):
        run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=10.0, buffer=2.0))))
    assert not (tmp_path / "out").exists()


def test_tiles_too_fine_for_the_block_are_refused_at_planning_before_any_output(small_block, tmp_path):
    from pipeline.blockinfo import read_info
    from workers.jobspec import check_job, plan_tiles

    # 1 m tiles with the reach as the buffer (6.15 m): up to 14 x 14 copies of a point on
    # this block's grid; the job model alone, which knows no block, lets them through
    fine = JobParams(tiling=TilingParams(tile_size=1.0))
    with pytest.raises(ParameterError, match="copy each point") as err:
        plan_tiles(fine, read_info(str(small_block)))
    assert err.value.param == "tiling.tile_size" and err.value.limit == 1.76
    with pytest.raises(ParameterError, match="copy each point"):
        run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=fine))
    assert not (tmp_path / "out").exists()
    spec = JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=12.0, buffer=7.0)),
                   run=RunOptions(engine="pdal"))  # PDAL's buffer must stay below half a tile: a run option's limit
    with pytest.raises(ParameterError, match="PDAL engine needs a buffer"):
        check_job(spec)


def test_bad_input_leaves_nothing(tmp_path):
    bad = tmp_path / "bad.laz"
    bad.write_bytes(b"not a point cloud")
    with pytest.raises(InputError):
        run_job(JobSpec(str(bad), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=10.0))))
    assert not (tmp_path / "out").exists()


def test_no_trees(ground_block, tmp_path):
    with pytest.raises(NoTreesError, match="no trees"):
        run_job(JobSpec(str(ground_block), str(tmp_path / "out")))
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_first_tile_failure_stops_and_names_the_tile(small_block, tmp_path):
    work = tmp_path / "work"
    with pytest.raises(TileFailed) as e:
        run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=10.0)), work_dir=str(work), inject_failure=(0,)))
    assert e.value.tile_id == 0
    msg = str(e.value)
    assert msg.startswith("tile 0 (core x") and "after 3 attempts" in msg
    assert f"{{job.work_dir}} {work} {{job.resume}}" in e.value.hint  # worded by each edge
    assert "\n" not in msg
    assert len(WorkStore(str(work)).list("attempts/000000")) == 3
    assert not (tmp_path / "out" / "trees.parquet").exists()


@pytest.mark.slow
def test_later_tile_failure_gives_partial_result_then_replay(small_block, tiled_ref, tmp_path, monkeypatch):
    ref, ref_out = tiled_ref
    work = tmp_path / "work"
    out = tmp_path / "out"
    # the tile ids with points: take the third one
    victim = 3
    outcome = run_job(JobSpec(str(small_block), str(out), job=JobParams(tiling=TilingParams(tile_size=10.0)), work_dir=str(work), inject_failure=(victim,)))
    assert outcome.partial and outcome.failed_tiles == [victim]
    meta = pq.read_table(out / "points.parquet").schema.metadata
    assert json.loads(meta[b"orchard:failed_tiles"]) == [victim]
    assert len(_points(out)["point_index"]) < ref.n_points
    assert len(WorkStore(str(work)).list(f"attempts/{victim:06d}")) == 3

    # every tile's task used to read the whole index (all tiles' bounds and counts): with
    # thousands of tiles that cost grew with the square of their number
    store = WorkStore(str(work))
    assert store.get_json(FRAME_KEY) == {k: v for k, v in store.get_json(INDEX_KEY).items() if k != "tiles"}
    reads = []
    get_json = WorkStore.get_json
    monkeypatch.setattr(WorkStore, "get_json", lambda self, key: reads.append(key) or get_json(self, key))
    params = PipelineParams().model_dump_json()
    ground_sample(store.url, victim, params, 7)
    process_tile(store.url, victim, params)
    assert FRAME_KEY in reads and INDEX_KEY not in reads
    monkeypatch.undo()

    def labels():
        return {k: store.get_array(f"{result_key(victim)}/{k}.npy") for k in ("index", "tree_id", "is_ground", "wood_score")}

    from_frame = labels()
    # a work store left by an earlier version has no frame: its tiles read the index
    store.remove(result_key(victim))
    store.remove(FRAME_KEY)
    # re-run the failed tile alone, merge again: identical to an undisturbed run
    run_tile(str(work), victim)
    assert all(np.array_equal(from_frame[k], v) for k, v in labels().items())
    again = finish_job(str(work))
    assert not again.partial and again.n_trees == ref.n_trees
    assert _points(out) == _points(ref_out)
    assert _trees(out).equals(_trees(ref_out))
    assert not work.exists()


def test_a_tile_takes_the_raw_ground_model_its_ground_pass_fitted(small_block, tmp_path):
    work = tmp_path / "work"
    victim = 2
    run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=10.0)), work_dir=str(work),
                    inject_failure=(victim,)))  # a failed tile keeps the work store
    store = WorkStore(str(work))
    params = PipelineParams()
    rec = read_tile(store, victim)
    stored = store.get_object(raw_ground_key(victim))
    frame = store.get_json(FRAME_KEY)
    xyz = (np.column_stack([rec["X"], rec["Y"], rec["Z"]]) * frame["scales"] + frame["offsets"]) - frame["origin"]
    refit = raw_ground_model(xyz, params=params.ground)
    assert np.allclose(stored.dtms[0], refit.dtms[0], atol=1e-6)  # this tile's, not another's

    def labels():
        return {k: store.get_array(f"{result_key(victim)}/{k}.npy") for k in ("index", "tree_id", "is_ground", "wood_score")}

    process_tile(store.url, victim, params.model_dump_json())
    given = labels()
    store.remove(raw_ground_key(victim))  # as a store written before the models were kept
    process_tile(store.url, victim, params.model_dump_json())
    assert all(np.array_equal(given[k], v) for k, v in labels().items())
    # and the stored model is the one used: one a metre lower leaves no point on the ground
    store.put_object(raw_ground_key(victim), type(stored)(tuple(d - 1.0 for d in stored.dtms), stored.origins,
                                                          stored.cell_size, 0.0))
    process_tile(store.url, victim, params.model_dump_json())
    assert given["is_ground"].any() and not labels()["is_ground"].any()


def test_run_tile_needs_a_job(tmp_path):
    with pytest.raises(ParameterError, match="holds no job"):
        run_tile(str(tmp_path), 0)


def test_params_reach_the_tiles(small_block, tmp_path):
    # a huge minimum canopy removes every tree, tiled or not
    params = PipelineParams.model_validate({"trunks": {"min_canopy_voxels": 10_000_000}})
    with pytest.raises(NoTreesError):
        run_job(JobSpec(str(small_block), str(tmp_path / "o"), job=JobParams(pipeline=params, tiling=TilingParams(tile_size=20.0))))


def test_work_folder_holding_other_files_is_refused_and_left_alone(small_block, tmp_path):
    # `--work` pointed at a folder of the user's: the store deletes what it writes, so it
    # must not take a folder that holds anything else (it used to delete the folder whole)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(ParameterError, match="new or empty folder"):
        run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=10.0)), work_dir=str(mine)))
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    assert small_block.exists() and not (tmp_path / "out").exists()


def test_work_store_removes_only_what_it_wrote(small_block, tmp_path):
    # the work folder is the output folder: after the job the outputs stay, the tiles go
    out = tmp_path / "out"
    run_job(JobSpec(str(small_block), str(out), job=JobParams(tiling=TilingParams(tile_size=20.0)), work_dir=str(out)))
    assert sorted(p.name for p in out.iterdir()) == ["gaps.parquet", "history.parquet", "points.parquet", "rows.parquet", "trees.parquet"]
    store = WorkStore(str(tmp_path / "w"))
    store.claim()
    store.put_json("job.json", {})
    store.put_array("tiles/000001/part.npy", np.zeros(3))
    (tmp_path / "w" / "later.txt").write_text("someone else's")
    store.remove()
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["later.txt"]
    (tmp_path / "w" / "later.txt").unlink()
    store.claim()
    store.put_json("job.json", {})
    store.remove()
    assert not (tmp_path / "w").exists()  # nothing else there: the folder goes too


def test_a_lock_file_left_by_a_killed_run_goes_with_its_store(tmp_path):
    # kill -9 during a job: the next start cancels it and deletes its store, which left
    # the lock file (and so the folder) behind for good
    work = tmp_path / "w"
    store = WorkStore(str(work))
    store.claim()
    store.put_json("job.json", {})
    (work / ".orchard-lock").write_text("")  # no process holds it any more
    store.remove()
    assert not work.exists()
    # a lock still held stays, with its folder, until its holder lets go
    store.claim()
    with WorkStore(str(work)).lock():
        store.remove()
        assert sorted(p.name for p in work.iterdir()) == [".orchard-lock"]
    assert not work.exists()


def test_a_new_job_does_not_reuse_an_earlier_jobs_tile_results(small_block, tmp_path):
    work = tmp_path / "work"
    first = run_job(JobSpec(str(small_block), str(tmp_path / "a"), job=JobParams(tiling=TilingParams(tile_size=20.0)), work_dir=str(work), inject_failure=(3,)))
    assert first.partial and WorkStore(str(work)).list("results")  # kept for a re-run
    with pytest.raises(TileFailed):
        run_job(JobSpec(str(small_block), str(tmp_path / "b"), job=JobParams(tiling=TilingParams(tile_size=12.0)), work_dir=str(work), inject_failure=(0,)))
    # the second job's store holds its own tiles and no result of the first job's tiles,
    # which a --resume would have merged as if they were its own
    assert WorkStore(str(work)).list("results") == []
    assert WorkStore(str(work)).get_json("job.json")["grid"]["tile_size"] == 12.0


def test_a_failed_write_leaves_the_previous_outputs_whole(small_block, labelled_run, tmp_path, monkeypatch):
    # outputs are published as one set: an output failing after another was written
    # must not leave the folder mixing two runs (or one run's trees without its points)
    out = tmp_path / "out"
    shutil.copytree(labelled_run[1], out)  # an earlier run's outputs
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(before) == ["gaps.parquet", "history.parquet", "labelled.laz", "points.parquet", "rows.parquet", "trees.parquet"]

    def disk_full(*a, **k):
        raise OSError(28, "No space left on device")

    from workers import outputs

    monkeypatch.setattr(outputs, "write_trees_parquet", disk_full)
    with pytest.raises(ParameterError, match="cannot write the outputs .* No space left"):
        run_job(JobSpec(str(small_block), str(out), job=JobParams(pipeline=PipelineParams.model_validate({"matter": {"threshold": 0.9}}))))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # no staging folder left either
    monkeypatch.undo()
    # a run without --labelled-laz removes the earlier run's labelled.laz with the rest
    run_job(JobSpec(str(small_block), str(out)))
    assert sorted(p.name for p in out.iterdir()) == ["gaps.parquet", "history.parquet", "points.parquet", "rows.parquet", "trees.parquet"]


@pytest.mark.slow
def test_a_partial_result_gives_no_tree_the_points_of_a_failed_tiles_tree(small_block, tiled_ref, tmp_path):
    from pipeline.blockinfo import read_info
    from pipeline.tiling import core_tile
    from workers.jobspec import plan_tiles

    _, full = tiled_ref
    index_grid = plan_tiles(JobParams(tiling=TilingParams(tile_size=10.0)), read_info(str(small_block)))
    trees = _trees(full).to_pydict()
    owner = core_tile(np.c_[trees["trunk_x"], trees["trunk_y"]], index_grid)
    first = int(core_tile(np.c_[trees["trunk_x"], trees["trunk_y"]][:1], index_grid)[0])
    victim = int(next(t for t in sorted(set(owner.tolist())) if t != first and t > min(owner)))
    part = tmp_path / "part"
    outcome = run_job(JobSpec(str(small_block), str(part), job=JobParams(tiling=TilingParams(tile_size=10.0)), work_dir=str(tmp_path / "w1"), inject_failure=(victim,)))
    assert outcome.partial and outcome.failed_tiles == [victim]
    assert json.loads(pq.read_table(part / "trees.parquet").schema.metadata[b"orchard:failed_tiles"]) == [victim]
    got = _trees(part).to_pydict()
    assert len(got["tree_id"]) == len(trees["tree_id"]) - int((owner == victim).sum())
    # every surviving tree holds a subset of its points in the undisturbed run: none
    # took the failed tile's trees' points (they stay unlabelled)
    p_full, p_part = _points(full), _points(part)
    lab_full = dict(zip(p_full["point_index"], p_full["tree_id"]))
    for gid, x, y in zip(got["tree_id"], got["trunk_x"], got["trunk_y"]):
        fid = int(np.argmin(np.hypot(np.asarray(trees["trunk_x"]) - x, np.asarray(trees["trunk_y"]) - y))) + 1
        mine = [i for i, t in zip(p_part["point_index"], p_part["tree_id"]) if t == gid]
        wrong = sum(lab_full[i] != fid for i in mine)
        assert wrong <= 0.002 * len(mine), (gid, wrong, len(mine))
    # points in no tree carry no wood score, as in a complete run
    for p in (p_full, p_part):
        assert not np.asarray(p["wood_score"])[np.asarray(p["tree_id"]) == 0].any()


def test_a_tile_that_finishes_after_its_job_was_cancelled_leaves_nothing(small_block, tmp_path):
    # a tile already running on a worker when the job is cancelled carries on; it must not
    # write its results into the work store the job's end deleted
    work = tmp_path / "work"
    outcome = run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=20.0)), work_dir=str(work), inject_failure=(3,)))
    assert outcome.partial and (work / "job.json").exists()
    (work / "job.json").unlink()  # the job's end took the store away (job record first)
    shutil.rmtree(work / "results", ignore_errors=True)
    assert process_tile(str(work), 3, PipelineParams().model_dump_json()) == {"abandoned": True}
    assert not (work / "results").exists()  # its results are gone (the rest is the job's end to delete)


def test_a_users_folders_named_like_the_stores_are_not_its_own(small_block, tmp_path):
    # a folder of the user's that happens to hold "tiles" and "results" folders: only a
    # folder the store marked is the store's (they were deleted with it)
    mine = tmp_path / "survey"
    (mine / "tiles").mkdir(parents=True)
    (mine / "tiles" / "my-tile.laz").write_bytes(b"x")
    (mine / "results").mkdir()
    (mine / ".draft.tmp").write_text("y")
    with pytest.raises(ParameterError, match="new or empty folder"):
        run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=10.0)), work_dir=str(mine)))
    assert sorted(p.relative_to(mine).as_posix() for p in mine.rglob("*")) == [".draft.tmp", "results", "tiles", "tiles/my-tile.laz"]
    WorkStore(str(mine)).remove()  # not marked: nothing is the store's
    assert (mine / "tiles" / "my-tile.laz").exists()


def test_two_runs_cannot_share_a_work_store(small_block, tmp_path):
    # a second run on the same --work (or --out) used to delete the first one's tiles
    work = tmp_path / "work"
    with WorkStore(str(work)).lock():  # a run holding it
        with pytest.raises(ParameterError, match="in use by another run"):
            run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=20.0)), work_dir=str(work)))
    run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=20.0)), work_dir=str(work)))  # free again
    assert not work.exists()


def test_a_tile_whose_worker_does_not_see_the_work_store_fails_the_job_clearly(tmp_path):
    # the task finds no job in the store: deleted under it (a cancel), or, if this process
    # still sees the job there, a worker with another view of the store; the second was
    # recorded as "cancelled on request"
    from workers.dispatch import kept
    from workers.jobspec import JobCancelled
    from workers.workstore import JOB_KEY

    store = WorkStore(str(tmp_path / "work"))
    store.claim()
    tile = {"id": 3, "core": (0.0, 0.0, 6.0, 6.0), "n_buffered": 10}
    store.put_json(JOB_KEY, {"tiles": []})
    with pytest.raises(TileFailed, match="tile 3 .*does not see the job's work store") as err:
        kept({"abandoned": True}, store, tile)
    assert "same address" in err.value.hint
    store.remove(JOB_KEY)
    with pytest.raises(JobCancelled):
        kept({"abandoned": True}, store, tile)
    assert kept({"tile_id": 3}, store, tile) == {"tile_id": 3}


@pytest.mark.slow
def test_many_tiles_under_a_low_open_file_limit(small_block, tmp_path):
    # the merge memory-maps five arrays per tile and each map holds a file descriptor:
    # with some hundred tiles the common limit of 1024 ran out after every tile was done.
    # The hard limit is the soft one: nothing in the job may lift it (a hard limit above
    # it once let the merge raise its own, a path the job no longer has)
    soft = hard = 48
    script = (
        "import resource, sys; resource.setrlimit(resource.RLIMIT_NOFILE, (int(sys.argv[3]), int(sys.argv[4])));"
        "from workers.job import run_job; from workers.jobspec import JobSpec; from pipeline.jobparams import JobParams, TilingParams;"
        "o = run_job(JobSpec(sys.argv[1], sys.argv[2], job=JobParams(tiling=TilingParams(tile_size=5.0)))); print(o.n_tiles, o.n_trees)"  # 34 tiles
    )
    run = subprocess.run([sys.executable, "-c", script, str(small_block), str(tmp_path / "out"), str(soft), str(hard)],
                         capture_output=True, text=True, timeout=600, check=False)
    assert run.returncode == 0, run.stderr[-2000:]
    n_tiles, n_trees = map(int, run.stdout.split())
    assert 5 * n_tiles > 3 * soft and n_trees >= 6


def test_a_cancel_while_the_file_is_tiled_on_a_cluster_without_workers_stops_the_job(small_block, tmp_path):
    # the range tasks of a block of more than chunk_points were waited for with
    # client.gather: with no worker left, the job waited for ever and heard no cancel
    import threading

    from distributed import Client, LocalCluster

    from workers.jobspec import JobCancelled

    cancel = threading.Event()
    with LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster, Client(cluster) as client:
        threading.Timer(1.0, cancel.set).start()
        with pytest.raises(JobCancelled):
            run_job(JobSpec(str(small_block), str(tmp_path / "out"), job=JobParams(tiling=TilingParams(tile_size=10.0)), run=RunOptions(chunk_points=50_000), work_dir=str(tmp_path / "work")), client=client, cancel=cancel)
    assert not (tmp_path / "out" / "trees.parquet").exists()
