"""A block decoded once before its tiles (workers.cellranges): counted and split into
ranges sorted by cell in one pass, its buffered tiles never written, each tile gathered
from the ranges: the same tiles, the same sample and the same outputs as counting and
then tiling."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from laz_fixtures import lying_copy

import workers.cellranges as cellranges
import workers.job as job
from pipeline.blockinfo import BlockInfo, read_info
from pipeline.budget import FIXED_BYTES, block_bytes
from pipeline.errors import InputError
from pipeline.jobparams import JobParams
from pipeline.params import PipelineParams
from pipeline.reading import sample_density
from pipeline.tiling import plan_grid
from workers.cellranges import gather_tile, index_from_cells, split_block
from workers.job import run_job
from workers.jobspec import JobSpec
from workers.runoptions import RunOptions
from workers.tiler import _write_parts, absolute_xy, read_sample, read_tile, tile_index
from workers.workstore import WorkStore

RUN = 7_000  # points per range: several ranges on a small block


@pytest.fixture(scope="module")
def block(sparse_block):
    return read_info(str(sparse_block))


@pytest.fixture
def client(dask_client):
    return dask_client


def _spec(block: BlockInfo, out: Path) -> JobSpec:
    need = block_bytes(sample_density(block.path, info=block, voxel_size=0.1))
    budget = (FIXED_BYTES + 0.6 * (need - FIXED_BYTES)) / 1e9  # the whole block does not fit
    params = PipelineParams.model_validate({"segment": {"max_crown_radius": 3.0}})
    return JobSpec(block.path, str(out), job=JobParams(pipeline=params), run=RunOptions(worker_memory=budget))


def _files(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.fixture(scope="module")
def split_run(block, dask_client, tmp_path_factory):
    """The block's job split while counting, in ranges of RUN points (read only): its
    outcome, its output folder, the keys it wrote to its work store and the tiles' index."""
    import workers.counting as counting

    out = tmp_path_factory.mktemp("split") / "out"
    written, indexes = [], []
    put, made = WorkStore.put_array, job.index_from_cells
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(counting, "CHUNK_POINTS", RUN)
        mp.setattr(cellranges, "CHUNK_POINTS", RUN)
        mp.setattr(WorkStore, "put_array", lambda self, key, arr: written.append(key) or put(self, key, arr))
        mp.setattr(job, "index_from_cells", lambda *a: indexes.append(made(*a)) or indexes[-1])
        outcome = run_job(_spec(block, out), client=dask_client)
    return outcome, out, written, indexes


@pytest.mark.slow  # two tiled jobs, one of them split_run
def test_a_job_split_while_counting_writes_no_tile_and_gives_the_outputs_of_counting_then_tiling(
        block, client, split_run, monkeypatch, tmp_path):
    import workers.counting as counting

    new, new_out, written, _ = split_run
    monkeypatch.setattr(counting, "CHUNK_POINTS", RUN)
    monkeypatch.setattr(cellranges, "CHUNK_POINTS", RUN)
    # no buffered tile written by the split; each tile's records once, by its ground pass, for its own task
    tiles = [k for k in written if k.startswith("tiles/0")]
    assert written and tiles and all(k.endswith("/records.npy") for k in tiles) and len(set(tiles)) == len(tiles)
    assert len({k for k in written if k.endswith("/points.npy")}) == math.ceil(block.n_points / RUN)
    assert new.n_tiles > 1 and new.n_points == block.n_points and new.n_trees > 0

    monkeypatch.setattr(job, "splits_while_counting", lambda spec, info: False)  # the old path: count, then tile
    old = run_job(_spec(block, tmp_path / "old"), client=client)
    assert (new.n_tiles, new.n_trees) == (old.n_tiles, old.n_trees)
    a, b = _files(new_out), _files(tmp_path / "old")
    assert a.keys() == b.keys() and "points.parquet" in a
    for name in a:
        assert a[name] == b[name], name  # byte for byte
    assert np.array_equal(new.sample["xy"], old.sample["xy"])
    assert np.array_equal(new.sample["tree_id"], old.sample["tree_id"])


def test_the_split_counts_what_the_count_counts_and_an_unseekable_file_is_split_in_one_task(block, client,
                                                                                             monkeypatch, tmp_path):
    import dataclasses

    monkeypatch.setattr(cellranges, "CHUNK_POINTS", RUN)
    here = sample_density(block.path, info=block, voxel_size=0.1, chunk_points=RUN)
    for info in (block, dataclasses.replace(block, seekable=False)):
        store = WorkStore(str(tmp_path / f"w{info.seekable}"))
        sample, cells, parts = split_block(info, info.origin[:2], store, voxel_size=0.1, client=client)
        assert sample.exact and np.array_equal(sample.counts, here.counts) and np.array_equal(sample.nodes, here.nodes)
        assert [p["start"] for p in parts] == list(range(0, block.n_points, RUN))
        assert sum(p["count"] for p in parts) == block.n_points
        # the report's sample is the tiler's
        xy, index = read_sample(store, block.n_points)
        assert np.array_equal(index, np.arange(0, block.n_points, index[1] - index[0]))


def _lying(block: BlockInfo, tmp_path: Path, *, count=None, max_x=None) -> Path:
    return lying_copy(Path(block.path), tmp_path / "lying.laz", count=count, max_x=max_x)


@pytest.mark.parametrize("lie", ["count", "extent"])
def test_a_header_lying_about_its_count_or_extent_is_a_clear_error_and_nothing_is_written(block, client, monkeypatch,
                                                                                          tmp_path, lie):
    monkeypatch.setattr(cellranges, "CHUNK_POINTS", RUN)
    if lie == "count":
        # more points than its LAZ chunks can hold (a lie within the last chunk decodes
        # zeros there, on either path: laspy does not see the chunk end)
        path, match = _lying(block, tmp_path, count=2 * block.n_points), "the header announces"
    else:
        path, match = _lying(block, tmp_path, max_x=block.mins[0] + 10.0), "outside the header's bounds"
    spec = _spec(block, tmp_path / "out")
    spec.input_path = str(path)
    if lie == "extent":
        assert job.splits_while_counting(spec, read_info(path))
    with pytest.raises(InputError, match=match):
        run_job(spec, client=client)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@st.composite
def _blocks(draw):
    n = draw(st.integers(1, 400))
    seed = draw(st.integers(0, 2**31))
    rng = np.random.default_rng(seed)
    scale = draw(st.sampled_from([0.001, 0.01, 0.25]))
    span = draw(st.floats(2.0, 60.0))
    # stored integers, some on whole metres (cell and tile edges) from the origin
    ints = np.empty((n, 3), dtype=np.int32)
    ints[:, :2] = rng.integers(0, int(span / scale) + 1, size=(n, 2))
    for d in (0, 1):  # on whole and half metres: cell, tile and buffer edges
        edges = rng.random(n) < 0.3
        step = rng.choice([0.5, 1.0])
        ints[edges, d] = (np.round(ints[edges, d] * scale / step) * step / scale).astype(np.int32)
    ints[:, 2] = rng.integers(0, 1000, size=n)
    offsets = (500_000.0 + draw(st.sampled_from([0.0, 0.3, 0.75])), 6_000_000.0, 0.0)
    xyz = ints * scale + np.asarray(offsets)
    mins, maxs = tuple(xyz.min(axis=0)), tuple(xyz.max(axis=0))
    origin = tuple(float(math.floor(v)) for v in mins)
    info = BlockInfo(path="unused.laz", n_points=n, version="1.4", point_format=6, compressed=True,
                     scales=(scale,) * 3, offsets=offsets, mins=mins, maxs=maxs, crs_wkt=None, origin=origin,
                     seekable=True, copc=False)
    size = float(max(draw(st.integers(1, 20)), math.ceil(span / 6)))  # at most 7 x 7 tiles
    buffer = draw(st.sampled_from([0.0, 0.25, 0.5, 1.0, 1.5, 2.5, size]))
    shift = (float(draw(st.integers(-3, 0))), float(draw(st.integers(-3, 0))))
    grid = plan_grid(mins, maxs, tile_size=size, buffer=buffer, grid_origin=(origin[0] + shift[0], origin[1] + shift[1]),
                     max_tiles=10_000)
    ranges = sorted(set(draw(st.lists(st.integers(1, max(1, n - 1)), max_size=4)) + [0]))
    return info, ints, grid, ranges


@settings(max_examples=30, deadline=None)
@given(_blocks())
def test_a_gathered_tile_is_the_tiles_written_tile_and_the_index_its_index(drawn):
    info, ints, grid, starts = drawn
    with tempfile.TemporaryDirectory() as folder:
        old, new = WorkStore(f"{folder}/old"), WorkStore(f"{folder}/new")
        counts = {}
        for a, z in zip(starts, [*starts[1:], info.n_points]):
            index = np.arange(a, z, dtype=np.uint64)
            _write_parts(old, f"part-{a:012d}", ints[a:z], index, absolute_xy(ints[a:z], info), grid, counts)
        want = tile_index(info, grid, counts, "laspy")
        cells = cellranges.cell_grid(info, grid.origin)
        parts = [cellranges._split(info, cells, new, a, ints[a:z], None)
                 for a, z in zip(starts, [*starts[1:], info.n_points])]
        for p in parts:
            p.pop("density")
        got = index_from_cells(info, grid, cells, parts, new)
        cored = [t for t in want["tiles"] if t["n_core"] > 0]
        assert [(t["id"], t["n_core"]) for t in got["tiles"]] == [(t["id"], t["n_core"]) for t in cored]
        assert all(g["n_buffered"] >= w["n_buffered"] for g, w in zip(got["tiles"], cored))
        for t in want["tiles"]:  # every tile holding points, buffer-only ones too
            a, b = read_tile(old, t["id"]), gather_tile(new, got, t["id"])
            assert np.array_equal(a, b), t["id"]


@pytest.mark.slow  # three tiled jobs, one of them split_run
def test_a_failed_tile_of_a_split_block_runs_again_alone_from_the_ranges(block, client, split_run, monkeypatch,
                                                                         tmp_path):
    import dataclasses

    import workers.counting as counting
    from workers.replay import finish_job, run_tile

    ref, ref_out, _, indexes = split_run
    monkeypatch.setattr(counting, "CHUNK_POINTS", RUN)  # as the reference run
    monkeypatch.setattr(cellranges, "CHUNK_POINTS", RUN)
    victim = indexes[-1]["tiles"][-1]["id"]  # not the canary: a later tile's failure leaves a partial job
    work, out = tmp_path / "work", tmp_path / "out"
    spec = dataclasses.replace(_spec(block, out), work_dir=str(work), inject_failure=(victim,))
    outcome = run_job(spec, client=client)
    assert outcome.partial and outcome.failed_tiles == [victim] and ref.n_tiles > 1
    run_tile(str(work), victim)  # in this process, from the ranges the job left
    again = finish_job(str(work))
    assert not again.partial and not work.exists()
    assert _files(out) == _files(ref_out)


def test_a_tile_is_gathered_once_its_task_takes_the_records_its_ground_pass_kept(block, monkeypatch, tmp_path):
    import workers.tasks as tasks
    from pipeline.ground import stats_stride
    from workers.job import _job_record
    from workers.jobspec import grid_origin
    from workers.workstore import JOB_KEY

    monkeypatch.setattr(cellranges, "CHUNK_POINTS", RUN)
    spec = _spec(block, tmp_path / "out")
    store = WorkStore(str(tmp_path / "work"))
    store.claim()
    _, cells, parts = split_block(block, grid_origin(spec.tiling, block), store, voxel_size=0.1)
    grid = plan_grid(block.mins, block.maxs, tile_size=10.0, buffer=3.0, grid_origin=cells.origin, max_tiles=100)
    index = index_from_cells(block, grid, cells, parts, store)
    store.put_json(JOB_KEY, _job_record(spec, block, grid, store.url))
    gathered = []
    monkeypatch.setattr(tasks, "gather_tile", lambda *a: gathered.append(a[2]) or gather_tile(*a))
    tid = max(index["tiles"], key=lambda t: t["n_core"])["id"]
    params = spec.params.model_dump_json()
    tasks.ground_sample(store.url, tid, params, stats_stride(block.n_points))
    assert gathered == [tid] and np.array_equal(store.get_array(tasks.records_key(tid)), gather_tile(store, index, tid))

    def labels():
        summary = tasks.process_tile(store.url, tid, params)
        return summary, {k: store.get_array(f"{tasks.result_key(tid)}/{k}.npy")
                         for k in ("index", "tree_id", "is_ground", "is_wood", "wood_score")}

    kept_summary, kept = labels()
    assert gathered == [tid]  # the tile's task gathered nothing: it took the kept records
    store.remove(tasks.records_key(tid))  # as a store written before the records were kept
    summary, again = labels()
    assert gathered == [tid, tid] and summary["n_buffered"] == kept_summary["n_buffered"] > kept_summary["n_core"] > 0
    assert all(np.array_equal(kept[k], again[k]) for k in kept)
