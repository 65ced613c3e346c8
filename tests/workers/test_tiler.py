"""The tiler: exact tiles in the work store, bounded memory, both engines agree."""

from __future__ import annotations

import tracemalloc

import laspy
import numpy as np
import pytest

from pipeline.blockinfo import read_info
from pipeline.errors import ParameterError
from pipeline.laswriting import LasBlockWriter
from pipeline.reading import read_points, read_raw_range, to_local
from pipeline.tiling import plan_grid
from workers.workstore import WorkStore
from workers.tiler import INDEX_KEY, TILE_DTYPE, pdal_available, read_tile, tile_block


def _tile(path, store, tile_size=10.0, buffer=3.0, origin=None, chunk_points=50_000, engine="laspy"):
    info = read_info(path)
    grid = plan_grid(info.mins, info.maxs, tile_size=tile_size, buffer=buffer, grid_origin=origin or info.origin[:2])
    return info, grid, tile_block(info, grid, store, chunk_points=chunk_points, engine=engine)


@pytest.mark.parametrize("url", ["memory://tiler-test", "folder"])
def test_tiles_are_exact(small_block, tmp_path, url):
    store = WorkStore(str(tmp_path / "work") if url == "folder" else f"{url}-{tmp_path.name}")
    info, grid, index = _tile(small_block, store, chunk_points=30_000)
    assert store.get_json(INDEX_KEY) == index
    xyz, _ = read_points(small_block)
    n = info.n_points
    seen_core = np.zeros(n, dtype=np.int64)
    # absolute x, y as the tiler computes them, from the stored integers
    las = laspy.read(small_block)
    ax = las.X * info.scales[0] + info.offsets[0]
    ay = las.Y * info.scales[1] + info.offsets[1]
    for t in index["tiles"]:
        rec = read_tile(store, t["id"])
        assert len(rec) == t["n_buffered"] and int(rec["core"].sum()) == t["n_core"]
        idx = rec["index"].astype(np.int64)
        assert np.all(np.diff(idx) > 0)
        # the stored integers give exactly the coordinates of an untiled read
        local = to_local(np.column_stack([rec["X"], rec["Y"], rec["Z"]]), info)
        assert np.array_equal(local, xyz[idx])
        # core flags: half-open core bounds
        x0, y0, x1, y1 = t["core"]
        in_core = (x0 <= ax) & (ax < x1) & (y0 <= ay) & (ay < y1)
        assert np.array_equal(np.sort(idx[rec["core"].astype(bool)]), np.flatnonzero(in_core))
        seen_core[idx[rec["core"].astype(bool)]] += 1
        # buffered set: exactly the points in the open buffered box, plus the core
        bx0, by0, bx1, by1 = t["buffered"]
        in_buf = ((bx0 < ax) & (ax < bx1) & (by0 < ay) & (ay < by1)) | in_core
        assert np.array_equal(idx, np.flatnonzero(in_buf))
    assert np.all(seen_core == 1)  # every point in exactly one core
    assert sum(t["n_core"] for t in index["tiles"]) == n


def _flat_block(path, n, seed=0):
    rng = np.random.default_rng(seed)
    with LasBlockWriter(path, offsets=(500_000.0, 6_950_000.0, 0.0)) as w:
        for _ in range(n // 100_000):
            xy = rng.uniform(0, 60, (100_000, 2))
            w.write(np.column_stack([xy + [500_000.0, 6_950_000.0], rng.uniform(100, 105, 100_000)]))
    return path


def test_peak_memory_does_not_grow_with_block_size(tmp_path):
    """Python-side peak allocation while tiling 0.3 M and 1.2 M points with 50 k-point chunks."""
    peaks = []
    for n in (300_000, 1_200_000):
        path = _flat_block(tmp_path / f"b{n}.laz", n)
        store = WorkStore(str(tmp_path / f"work{n}"))
        tracemalloc.start()
        _tile(path, store, tile_size=20.0, buffer=2.0, chunk_points=50_000)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    assert peaks[1] < 1.3 * peaks[0] + 2_000_000
    assert peaks[1] < 1_200_000 * 12  # less than half of the block's xyz as float64


def test_pdal_engine_gives_the_same_tiles(small_block, tmp_path):
    if not pdal_available():
        pytest.skip("PDAL's Python bindings are not installed")
    a = WorkStore(str(tmp_path / "laspy"))
    b = WorkStore(str(tmp_path / "pdal"))
    _, _, ia = _tile(small_block, a, tile_size=10.0, buffer=3.0)
    _, _, ib = _tile(small_block, b, tile_size=10.0, buffer=3.0, engine="pdal")
    assert ia["tiles"] == ib["tiles"]
    for t in ia["tiles"]:
        ra, rb = read_tile(a, t["id"]), read_tile(b, t["id"])
        assert np.array_equal(ra, rb)


def test_pdal_engine_refuses_wide_buffers(small_block, tmp_path):
    with pytest.raises(ParameterError, match="half the tile size"):
        _tile(small_block, WorkStore(str(tmp_path / "w")), tile_size=10.0, buffer=6.0, engine="pdal")


def test_pdal_engine_missing_is_a_clear_error(small_block, tmp_path):
    if pdal_available():
        pytest.skip("PDAL is installed")
    with pytest.raises(ParameterError, match="import pdal failed"):
        _tile(small_block, WorkStore(str(tmp_path / "w")), tile_size=10.0, buffer=3.0, engine="pdal")


def test_unknown_engine(small_block, tmp_path):
    with pytest.raises(ParameterError, match="unknown tiling engine"):
        _tile(small_block, WorkStore(str(tmp_path / "w")), engine="gdal")


def test_parallel_tiling_on_dask_gives_the_same_tiles(tmp_path, dask_client):
    """Chunks split by dask tasks (each seeking its own range) equal the sequential tiler,
    also for a LAZ of variable-size chunks (lazrs cannot seek in those: its points after a
    seek were garbage within the bounds, and tiled runs gave wrong trees, exit 0)."""
    from laz_fixtures import write_variable_chunk_laz

    rng = np.random.default_rng(4)
    xyz = np.column_stack([rng.uniform(0, 30, 50_000), rng.uniform(0, 20, 50_000), rng.uniform(0, 3, 50_000)]) + [500000, 6950000, 100]
    fixed = tmp_path / "b.laz"
    with LasBlockWriter(fixed, crs_epsg=28356) as w:
        w.write(xyz)
    variable = write_variable_chunk_laz(fixed, tmp_path / "v.laz", [9_000, 1, 17_000, 4_999, 19_000])
    assert read_info(fixed).seekable and not read_info(variable).seekable
    client = dask_client
    for path in (fixed, variable):
        info = read_info(path)
        grid = plan_grid(info.mins, info.maxs, tile_size=10.0, buffer=2.0, grid_origin=(500000.0, 6950000.0), reach=1.0)
        seq = WorkStore(str(tmp_path / f"seq-{path.stem}"))
        par = WorkStore(str(tmp_path / f"par-{path.stem}"))
        a = tile_block(info, grid, seq, chunk_points=7_000)
        keys, submit = [], client.submit
        client.submit = lambda fn, *args, **kw: keys.append(kw["key"]) or submit(fn, *args, **kw)
        try:
            b = tile_block(info, grid, par, chunk_points=7_000, client=client)
        finally:
            del client.submit
        assert a["tiles"] == b["tiles"]
        # never in the submitting process: one task reads a file that cannot be entered in the middle
        assert len(keys) == (1 if path == variable else 8) and keys[0].startswith("tile-all-" if path == variable else "tile-range-")
        for t in a["tiles"]:
            ra, rb = read_tile(seq, t["id"]), read_tile(par, t["id"])
            assert np.array_equal(np.sort(ra, order="index"), np.sort(rb, order="index"))


def test_a_range_of_a_laz_with_variable_size_chunks_is_the_same_points(small_block, tmp_path):
    from laz_fixtures import write_variable_chunk_laz

    n = read_info(small_block).n_points
    sizes = [40_000, 3, 25_000] + [50_000] * ((n - 65_003) // 50_000)
    sizes.append(n - sum(sizes))
    path = write_variable_chunk_laz(small_block, tmp_path / "v.laz", sizes)
    info = read_info(path)
    assert not info.seekable
    stored = laspy.read(path).points.array
    for start in (0, 39_999, 40_001, 65_003, n - 10):
        got = read_raw_range(path, start, 20_000, info=info)
        assert np.array_equal(got[:, 0], stored["X"][start : start + 20_000]), start
        assert np.array_equal(got[:, 2], stored["Z"][start : start + 20_000]), start

@pytest.mark.parametrize("starts", [(0, 5, 9), (5, 0, 9), (0, 9, 5)])
def test_a_tiles_parts_are_read_in_point_order_whatever_order_they_are_listed_in(tmp_path, starts):
    # parts are named by the first point of their chunk; one listed out of order (or a
    # part whose own records are out of order) is put back in order
    store = WorkStore(str(tmp_path / "w"))
    sizes = {0: 5, 5: 4, 9: 3}
    for k, start in enumerate(starts):
        rec = np.zeros(sizes[start], dtype=TILE_DTYPE)
        rec["index"] = np.arange(start, start + sizes[start])
        rec["X"] = rec["index"] * 10
        store.put_array(f"tiles/000001/part-{k:012d}.npy", rec)
    got = read_tile(store, 1)
    assert got["index"].tolist() == list(range(12)) and got["X"].tolist() == [10 * i for i in range(12)]
    shuffled = np.zeros(3, dtype=TILE_DTYPE)
    shuffled["index"] = [20, 14, 17]
    store.put_array("tiles/000001/part-000000000099.npy", shuffled)
    assert read_tile(store, 1)["index"].tolist() == [*range(12), 14, 17, 20]
