"""Tiles that read their own points from the input (a COPC block): no pass over the block
before the first tile, no tile written, the same outputs as the same points in plain LAZ."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest
from laz_fixtures import lying_copy

from pipeline.blockinfo import read_info
from pipeline.errors import InputError
from pipeline.formats.copc import read_box, read_nodes
from pipeline.jobparams import JobParams, TilingParams
from workers.job import run_job
from workers.jobspec import JobSpec
from workers.workstore import WorkStore

COPC = Path(__file__).parent / "data" / "rows6.copc.laz"


@pytest.fixture(scope="module")
def plain_twin(tmp_path_factory) -> Path:
    """The COPC fixture's points, in its order, as a plain LAZ of fixed-size chunks."""
    las = laspy.read(COPC)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = las.header.scales, las.header.offsets
    header.add_crs(las.header.parse_crs())
    out = laspy.LasData(header)
    out.X, out.Y, out.Z = las.X, las.Y, las.Z
    path = tmp_path_factory.mktemp("twin") / "rows6.laz"
    out.write(path)
    return path


@pytest.fixture(scope="module")
def copc_tiled(tmp_path_factory):
    """The COPC fixture's job in 10 m tiles (read only): its outcome, its output folder and
    the keys it wrote to its work store."""
    out = tmp_path_factory.mktemp("copc-tiled")
    written = []
    put = WorkStore.put_array

    def spy(self, key, arr):
        written.append(key)
        return put(self, key, arr)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(WorkStore, "put_array", spy)
        outcome = run_job(JobSpec(str(COPC), str(out), job=JobParams(tiling=TilingParams(tile_size=10.0))))
    return outcome, out, written


def _outputs(folder: Path) -> dict:
    return {name: pq.read_table(folder / name) for name in ("points.parquet", "trees.parquet")}


def test_a_box_reads_its_nodes_points_with_their_positions_in_the_file():
    info = read_info(COPC)
    assert info.copc and not read_info(COPC).seekable
    las = laspy.read(COPC)
    stored = np.column_stack([las.X, las.Y, las.Z])
    ints, index = read_box(info, (-np.inf, -np.inf, np.inf, np.inf))
    assert np.array_equal(np.sort(index), np.arange(info.n_points))  # every point once
    assert np.array_equal(ints, stored[index.astype(np.int64)])
    x0, y0 = info.mins[0] + 2, info.mins[1] + 2
    ints, index = read_box(info, (x0, y0, x0 + 3, y0 + 3))
    assert np.array_equal(ints, stored[index.astype(np.int64)])
    x = las.X * info.scales[0] + info.offsets[0]
    y = las.Y * info.scales[1] + info.offsets[1]
    inside = np.flatnonzero((x0 <= x) & (x <= x0 + 3) & (y0 <= y) & (y <= y0 + 3))
    assert set(inside) <= set(index.tolist())  # a superset of the box's points
    assert len(index) < info.n_points


def test_copc_tiles_give_the_trees_of_the_same_points_in_plain_laz_and_are_never_written(plain_twin, copc_tiled,
                                                                                         tmp_path, monkeypatch):
    copc, copc_out, copc_written = copc_tiled
    tile_parts = [k for k in copc_written if k.startswith("tiles/") and "/part-" in k]
    assert copc.n_tiles > 1 and copc_written and not tile_parts
    written = []
    put = WorkStore.put_array

    def spy(self, key, arr):
        written.append(key)
        return put(self, key, arr)

    monkeypatch.setattr(WorkStore, "put_array", spy)
    plain = run_job(JobSpec(str(plain_twin), str(tmp_path / "plain"), job=JobParams(tiling=TilingParams(tile_size=10.0))))
    assert any("/part-" in k for k in written)  # the plain LAZ's tiles are written, as before
    assert (copc.n_trees, copc.n_tiles) == (plain.n_trees, plain.n_tiles) and copc.n_trees >= 5
    a, b = _outputs(copc_out), _outputs(tmp_path / "plain")
    for name in a:
        assert a[name].equals(b[name]), name
    # the report's sample: the same points with the same trees
    assert np.array_equal(copc.sample["xy"], plain.sample["xy"])
    assert np.array_equal(copc.sample["tree_id"], plain.sample["tree_id"])


def test_a_copc_block_in_one_piece_is_the_plain_one(plain_twin, tmp_path):
    run_job(JobSpec(str(COPC), str(tmp_path / "copc")))
    run_job(JobSpec(str(plain_twin), str(tmp_path / "plain")))
    a, b = _outputs(tmp_path / "copc"), _outputs(tmp_path / "plain")
    for name in a:
        assert a[name].equals(b[name]), name


def _lying(tmp_path: Path, *, count: int | None = None, max_x: float | None = None) -> Path:
    return lying_copy(COPC, tmp_path / "lying.copc.laz", count=count, max_x=max_x)


def _nothing_written(out: Path) -> bool:
    return not out.exists() or not any(out.iterdir())


def test_a_header_lying_about_its_count_is_refused_before_any_tile(tmp_path):
    info = read_info(COPC)
    path = _lying(tmp_path, count=info.n_points - 1000)
    out = tmp_path / "out"
    with pytest.raises(InputError, match=f"{info.n_points - 1000} points but its COPC hierarchy holds {info.n_points}"):
        run_job(JobSpec(str(path), str(out), job=JobParams(tiling=TilingParams(tile_size=10.0))))
    assert _nothing_written(out)


def test_a_header_lying_about_its_extent_is_a_clear_error_and_nothing_is_written(tmp_path):
    info = read_info(COPC)
    # the true extent ends 24 m on; the header says 12 m: the points beyond lie outside it
    path = _lying(tmp_path, max_x=info.mins[0] + 12.0)
    out = tmp_path / "out"
    with pytest.raises(InputError, match="outside the header's bounds"):
        run_job(JobSpec(str(path), str(out), job=JobParams(tiling=TilingParams(tile_size=10.0))))
    assert _nothing_written(out)


def test_the_hierarchy_counts_every_point_once():
    nodes = read_nodes(COPC)
    assert nodes.n_points == read_info(COPC).n_points
    assert np.array_equal(nodes.first[1:], np.cumsum(nodes.count)[:-1])
    assert (np.diff(nodes.offset) > 0).all()  # in file order


def test_the_hierarchys_density_sample_never_misses_a_cell_holding_points():
    from pipeline.reading import sample_density

    info = read_info(COPC)
    copc = sample_density(COPC, info=info, voxel_size=0.1)
    counted = sample_density(COPC, info=dataclasses.replace(info, copc=False), voxel_size=0.1)  # every point read
    assert copc.counts.shape == counted.counts.shape
    assert copc.counts.sum() >= info.n_points
    assert ((copc.counts > 0) | (counted.counts == 0)).all()  # every cell holding points is counted
    assert (copc.nodes <= copc.counts).all()


def test_a_lying_copc_header_on_the_command_line_is_one_line_and_exit_2(tmp_path, capsys, dask_cluster):
    # on the tests' cluster: its workers log here, so a worker's traceback would be seen
    from service.cli import main

    info = read_info(COPC)
    for n, kw in enumerate(({"count": info.n_points - 1000}, {"max_x": info.mins[0] + 12.0})):
        (tmp_path / str(n)).mkdir()
        path = _lying(tmp_path / str(n), **kw)
        out = tmp_path / f"out{n}"
        code = main(["process", str(path), "--out", str(out), "--tile-size", "10",
                     "--scheduler", dask_cluster.scheduler_address])
        err = capsys.readouterr().err
        assert code == 2, err
        lines = [line for line in err.strip().splitlines() if not line.startswith("dask dashboard:")]
        assert len(lines) == 1 and lines[0].startswith("orchard process: ") and "Traceback" not in err
        assert "lying.copc.laz" in err and _nothing_written(out)


def test_a_box_read_in_batches_of_nodes_is_the_box_read_at_once():
    from pipeline.formats.copc import iter_box

    info = read_info(COPC)
    box = (info.mins[0] + 2, info.mins[1] + 2, info.mins[0] + 9, info.mins[1] + 9)
    ints, index = read_box(info, box)
    parts = list(iter_box(info, box, batch_points=10_000))
    assert len(parts) > 1
    assert np.array_equal(np.concatenate([p[0] for p in parts]), ints)
    assert np.array_equal(np.concatenate([p[1] for p in parts]), index)


def test_settling_a_streamed_index_takes_the_tiles_counts_and_drops_the_empty_ones(tmp_path):
    from workers.settling import settle_index
    from workers.tiler import INDEX_KEY

    store = WorkStore(str(tmp_path / "work"))
    idx = {"engine": "copc", "input": "b.copc.laz", "mins": [0, 0, 0], "maxs": [9, 9, 9], "estimated": True,
           "tiles": [{"id": i, "n_core": 50, "n_buffered": 90} for i in range(3)]}
    summaries = [{"tile_id": 0, "n_core": 30, "n_buffered": 40}, {"tile_id": 1, "n_core": 0, "n_buffered": 7},
                 {"tile_id": 2, "n_core": 70, "n_buffered": 80}]
    settled, kept = settle_index(store, idx, summaries, {}, 100)
    assert [(t["id"], t["n_core"], t["n_buffered"]) for t in settled["tiles"]] == [(0, 30, 40), (2, 70, 80)]
    assert [s["tile_id"] for s in kept] == [0, 2] and not settled["estimated"]
    assert store.get_json(INDEX_KEY) == settled
    with pytest.raises(InputError, match="announces 101 points .* hold 100"):
        settle_index(store, idx, summaries, {}, 101)
    # a tile that failed: no count to check, the estimate stays
    settled, _ = settle_index(store, idx, summaries[:2], {2: "boom"}, 101)
    assert [t["n_core"] for t in settled["tiles"]] == [30, 50] and settled["estimated"]
    plain = dict(idx, engine="laspy")
    assert settle_index(store, plain, summaries, {}, 5) == (plain, summaries)


@pytest.mark.slow
def test_a_streamed_job_stopped_at_its_first_tile_resumes_to_the_same_outputs(copc_tiled, tmp_path):
    # a COPC job has no written tiles to resume from: its work store keeps the tiles'
    # index and the resumed tiles read their points from the input again
    from workers.replay import resume_job
    from workers.jobspec import TileFailed

    tiling = TilingParams(tile_size=10.0)
    whole, whole_out, _ = copc_tiled
    work = tmp_path / "work"
    with pytest.raises(TileFailed):
        run_job(JobSpec(str(COPC), str(tmp_path / "stopped"), work_dir=str(work), job=JobParams(tiling=tiling),
                        inject_failure=(0,)))
    store = WorkStore(str(work))
    assert not store.exists("results/000000/summary.pkl")
    assert not any("/part-" in k for k in store.list("tiles"))  # nothing of the block was written to resume from
    resumed = resume_job(str(work), out_dir=str(tmp_path / "stopped"))
    assert resumed.n_trees == whole.n_trees >= 5
    a, b = _outputs(whole_out), _outputs(tmp_path / "stopped")
    for name in a:
        assert a[name].equals(b[name]), name
