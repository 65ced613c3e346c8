"""The PDAL engine's view-to-tile logic, without PDAL: views shaped as PDAL 2.8.4's
``filters.splitter`` makes them (a model of ``SplitterFilter::processPoint``), with the
buffer-only views of cells off the grid, edge tiles of few core points and empty cells,
give exactly the laspy engine's tiles; views that do not add up fail loudly."""

from __future__ import annotations

import json
import sys
import tempfile
import types
from pathlib import Path

import laspy
import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

from pipeline.blockinfo import read_info
from pipeline.laswriting import LasBlockWriter
from pipeline.tiling import plan_grid
from workers.tiler import (
    INDEX_KEY,
    TilesDoNotAddUp,
    check_tiles_add_up,
    read_sample,
    read_tile,
    tile_block,
    tiles_from_views,
)
from workers.workstore import WorkStore

OFFSET = np.array([500_000.0, 6_950_000.0, 0.0])


def splitter_views(x: np.ndarray, y: np.ndarray, length: float, buffer: float, origin_x: float, origin_y: float) -> list[np.ndarray]:
    """The views of PDAL 2.8.4's filters.splitter, as point indices, in a shuffled-free
    order of cells: its own cell of each point (truncation toward zero, one less below the
    origin), then at most one west/east, one south/north and one diagonal neighbour whose
    open buffered box holds the point (the C++ if/else-if chains)."""
    cells: dict[tuple[int, int], list[int]] = {}

    def contains(cx, cy, px, py):
        minx = origin_x + cx * length - buffer
        maxx = minx + length + 2 * buffer
        miny = origin_y + cy * length - buffer
        maxy = miny + length + 2 * buffer
        return minx < px < maxx and miny < py < maxy

    for i, (px, py) in enumerate(zip(x.tolist(), y.tolist())):
        dx, dy = px - origin_x, py - origin_y
        xpos, ypos = int(dx / length), int(dy / length)
        xpos -= dx < 0
        ypos -= dy < 0
        cells.setdefault((xpos, ypos), []).append(i)
        if buffer > 0:
            for group in (((-1, 0), (1, 0)), ((0, -1), (0, 1)), ((-1, -1), (-1, 1), (1, -1), (1, 1))):
                for ox, oy in group:
                    if contains(xpos + ox, ypos + oy, px, py):
                        cells.setdefault((xpos + ox, ypos + oy), []).append(i)
                        break
    return [np.asarray(v, dtype=np.uint64) for v in cells.values()]


def _block(path: Path, xyz: np.ndarray, scale: float = 0.01) -> Path:
    with LasBlockWriter(path, offsets=tuple(OFFSET), scales=(scale, scale, scale)) as w:
        w.write(xyz + OFFSET)
    return path


def _drop(*stores: WorkStore) -> None:
    """Delete memory stores: the process's memory file system is one, and listing a tile
    in any store of it walks every key it holds."""
    for store in stores:
        if store.fs.exists(store.root):
            store.fs.rm(store.root, recursive=True)


@pytest.fixture(autouse=True)
def _memory_stores_dropped():
    """Each test's stores (``_both``'s) deleted after it."""
    from fsspec.implementations.memory import MemoryFileSystem

    yield
    fs = MemoryFileSystem()
    for root in [p for p in fs.ls("/", detail=False) if p.lstrip("/").startswith("views-")]:
        fs.rm(root, recursive=True)


def _both(path: Path, tile_size: float, buffer: float, origin=None, views_of=None):
    """(laspy engine's index and store, views engine's index and store) of a block."""
    info = read_info(path)
    grid = plan_grid(info.mins, info.maxs, tile_size=tile_size, buffer=buffer, grid_origin=origin or info.origin[:2])
    ref = WorkStore(f"memory://views-ref-{path.stem}-{id(path)}")
    got = WorkStore(f"memory://views-got-{path.stem}-{id(path)}")
    ia = tile_block(info, grid, ref)
    las = laspy.read(path)
    ints = np.column_stack([las.X, las.Y, las.Z]).astype(np.int32)
    x = ints[:, 0] * info.scales[0] + info.offsets[0]
    y = ints[:, 1] * info.scales[1] + info.offsets[1]
    views = splitter_views(x, y, grid.tile_size, grid.buffer, *grid.origin)
    if views_of is not None:
        views = views_of(views)
    return info, grid, (ia, ref), (ints, views, got)


def _assert_same(ia, ref, ib, got):
    assert ia["tiles"] == ib["tiles"]
    assert got.get_json(INDEX_KEY) == ib
    for t in ia["tiles"]:
        assert np.array_equal(read_tile(ref, t["id"]), read_tile(got, t["id"])), t["id"]


def test_off_grid_buffer_views_are_dropped(tmp_path):
    # the shape: the grid starts at the block's minimum rounded down, so the
    # splitter adds buffer-only views of the cells west and south of it
    rng = np.random.default_rng(1)
    xyz = np.column_stack([rng.uniform(0.2, 59.8, 6000), rng.uniform(0.2, 39.8, 6000), rng.uniform(0, 5, 6000)])
    info, grid, (ia, ref), (ints, views, got) = _both(_block(tmp_path / "b.las", xyz), 20.0, 3.0)
    assert len(views) > len(ia["tiles"])  # off-grid views exist
    ib = tiles_from_views(ints, views, info, grid, got)
    _assert_same(ia, ref, ib, got)
    assert sum(t["n_core"] for t in ib["tiles"]) == info.n_points


def test_an_edge_tile_of_few_core_points_and_an_empty_cell(tmp_path):
    # tile (2, 0) holds 3 points, all within the buffer of tile (1, 0); the middle cell
    # of the top row holds none, only its neighbours' buffer points
    rng = np.random.default_rng(2)
    main = np.column_stack([rng.uniform(0.5, 39.5, 4000), rng.uniform(0.5, 59.5, 4000), rng.uniform(0, 5, 4000)])
    main = main[~((main[:, 0] > 20) & (main[:, 0] < 40) & (main[:, 1] > 40))]  # an empty cell
    few = np.array([[40.5, 5.0, 1.0], [40.7, 6.0, 1.0], [41.0, 7.0, 1.0]])
    info, grid, (ia, ref), (ints, views, got) = _both(_block(tmp_path / "b.las", np.vstack([main, few])), 20.0, 3.0)
    ib = tiles_from_views(ints, views, info, grid, got)
    _assert_same(ia, ref, ib, got)
    empty = [t for t in ib["tiles"] if t["n_core"] == 0]
    assert empty  # the buffer-only tile is kept, as the laspy engine keeps it


def test_the_sample_of_the_report_is_kept(tmp_path):
    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.uniform(0, 30, 5000), rng.uniform(0, 30, 5000), rng.uniform(0, 5, 5000)])
    info, grid, (ia, ref), (ints, views, got) = _both(_block(tmp_path / "b.las", xyz), 10.0, 2.0)
    tiles_from_views(ints, views, info, grid, got)
    a, b = read_sample(ref, info.n_points), read_sample(got, info.n_points)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


@pytest.mark.parametrize("damage", ["a view lost", "a point lost", "a point added", "views in any order, twice"])
def test_views_that_do_not_make_the_tiles_fail_loudly_or_are_dropped(tmp_path, damage):
    rng = np.random.default_rng(4)
    xyz = np.column_stack([rng.uniform(0, 30, 3000), rng.uniform(0, 30, 3000), rng.uniform(0, 5, 3000)])

    def damaged(views):
        views = sorted(views, key=len, reverse=True)
        if damage == "a view lost":
            return views[1:]
        if damage == "a point lost":
            return [views[0][1:]] + views[1:]
        if damage == "a point added":
            extra = np.setdiff1d(np.arange(3000, dtype=np.uint64), views[0])[:1]
            return [np.concatenate([views[0], extra])] + views[1:]
        return views[::-1] + views

    info, grid, (ia, ref), (ints, views, got) = _both(_block(tmp_path / "b.las", xyz), 10.0, 2.0, views_of=damaged)
    if damage.startswith("views in any order"):
        _assert_same(ia, ref, tiles_from_views(ints, views, info, grid, got), got)
        return
    with pytest.raises(TilesDoNotAddUp, match=r"no view equal to the buffered points of tile\(s\) \[\d+\]"):
        tiles_from_views(ints, views, info, grid, got)
    assert not got.exists(INDEX_KEY)  # no index: nothing downstream runs on such tiles


@st.composite
def blocks(draw):
    """Points on a coarse lattice (many on cell edges) or anywhere, in one or a few clumps,
    with a tile size, a buffer below half of it and an origin at or below the minimum."""
    n = draw(st.integers(1, 400))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    width = draw(st.sampled_from([3.0, 10.0, 25.0, 47.3]))
    lattice = draw(st.sampled_from([None, 0.5, 1.0, 2.5]))
    xy = rng.uniform(0, width, (n, 2))
    if draw(st.booleans()):  # a clump in a corner: edge tiles of few points
        k = max(1, n // 10)
        xy[:k] = rng.uniform(0, width / 7, (k, 2))
    if lattice is not None:
        xy = np.round(xy / lattice) * lattice
    xyz = np.column_stack([xy + 0.25, rng.uniform(0, 3, n)])
    size = draw(st.sampled_from([2.0, 2.5, 5.0, 7.3, 10.0]))
    buffer = draw(st.sampled_from([0.0, 0.5, 1.0, 2.0, 2.4])) * size / 5.0
    shift = draw(st.sampled_from([0.0, 0.25, 3.0, 17.5]))
    scale = draw(st.sampled_from([0.01, 0.001]))
    shuffle = draw(st.integers(0, 2**32 - 1))
    return xyz, size, min(buffer, size / 2 - 0.01), shift, scale, shuffle


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(blocks())
def test_any_splitter_output_gives_the_laspy_engines_tiles(case):
    """Property: whatever block, grid and order of views, the views of the splitter
    (with its off-grid and buffer-only cells) give the laspy engine's tiles exactly. With
    no buffer, a point within rounding of a cell edge may fall in the splitter's other
    cell (its cell rule does not settle the division's rounding, the grid's does): then
    the run stops loudly, and is never wrong. Every job has a buffer (at least the reach)."""
    xyz, size, buffer, shift, scale, shuffle = case
    note(f"{len(xyz)} points, tile size {size}, buffer {buffer}, origin shift {shift}, scale {scale}")
    with tempfile.TemporaryDirectory() as tmp:
        path = _block(Path(tmp) / "b.las", xyz, scale)
        info = read_info(path)
        origin = (info.origin[0] - shift, info.origin[1] - shift)

        def shuffled(views):
            order = np.random.default_rng(shuffle).permutation(len(views))
            return [views[i] for i in order]

        info, grid, (ia, ref), (ints, views, got) = _both(path, size, buffer, origin, views_of=shuffled)
        try:
            try:
                ib = tiles_from_views(ints, views, info, grid, got)
            except TilesDoNotAddUp:
                assert buffer == 0
                assert not got.exists(INDEX_KEY)
                return
            _assert_same(ia, ref, ib, got)
        finally:
            _drop(ref, got)  # (one test of many examples)


def test_tiles_that_do_not_add_up_fail_loudly_for_every_engine(small_block, tmp_path, monkeypatch):
    with pytest.raises(TilesDoNotAddUp, match="hold 9 core points, the block has 10"):
        check_tiles_add_up({"tiles": [{"n_core": 4}, {"n_core": 5}]}, 10, "laspy")
    check_tiles_add_up({"tiles": [{"n_core": 4}, {"n_core": 6}]}, 10, "laspy")
    # the laspy engine losing the last point of every chunk is caught before the index is written
    import workers.tiler as tiler

    real = tiler._write_parts
    monkeypatch.setattr(tiler, "_write_parts", lambda store, part, ints, index, xy, *rest: real(store, part, ints[:-1], index[:-1], xy[:-1], *rest))
    info = read_info(small_block)
    grid = plan_grid(info.mins, info.maxs, tile_size=10.0, buffer=3.0, grid_origin=info.origin[:2])
    store = WorkStore(str(tmp_path / "w"))
    with pytest.raises(TilesDoNotAddUp, match="the 'laspy' engine hold"):
        tile_block(info, grid, store, chunk_points=50_000)
    assert not store.exists(INDEX_KEY)


class _FakePdal(types.ModuleType):
    """``pdal`` as the tiler uses it: ``readers.las`` (by laspy, scaled doubles as PDAL
    gives them) and ``filters.splitter`` (by :func:`splitter_views`)."""

    def __init__(self):
        super().__init__("pdal")

        class Pipeline:
            def __init__(self, spec, arrays=None):
                self.stages, self.inputs, self.arrays = json.loads(spec)["pipeline"], arrays, None

            def execute(self):
                stage = self.stages[0]
                if stage["type"] == "readers.las":
                    las = laspy.read(stage["filename"])
                    arr = np.empty(len(las.points), dtype=[("X", "f8"), ("Y", "f8"), ("Z", "f8"), ("Intensity", "u2")])
                    arr["X"], arr["Y"], arr["Z"] = las.x, las.y, las.z
                    arr["Intensity"] = las.intensity
                    self.arrays = [arr]
                else:
                    arr = self.inputs[0]
                    views = splitter_views(arr["X"], arr["Y"], stage["length"], stage["buffer"], stage["origin_x"], stage["origin_y"])
                    self.arrays = [arr[v.astype(np.int64)] for v in views]
                return len(self.arrays[0])

        self.Pipeline = Pipeline


def test_the_pdal_engine_through_a_model_of_pdal(tmp_path, monkeypatch):
    """tile_block(engine="pdal") end to end on a model of PDAL: its glue (OriginIndex, the
    scaled doubles back to the file's integers) gives the laspy engine's tiles."""
    monkeypatch.setitem(sys.modules, "pdal", _FakePdal())
    rng = np.random.default_rng(5)
    xyz = np.column_stack([rng.uniform(0.3, 59.7, 8000), rng.uniform(0.3, 39.7, 8000), rng.uniform(0, 5, 8000)])
    path = _block(tmp_path / "b.laz", xyz, 0.001)
    info = read_info(path)
    grid = plan_grid(info.mins, info.maxs, tile_size=20.0, buffer=3.0, grid_origin=info.origin[:2])
    ref, got = WorkStore(str(tmp_path / "a")), WorkStore(str(tmp_path / "b"))
    ia = tile_block(info, grid, ref)
    ib = tile_block(info, grid, got, engine="pdal")
    assert ib["engine"] == "pdal"
    ib = dict(ib, engine="laspy")
    ia_tiles = ia["tiles"]
    assert ia_tiles == ib["tiles"] and len(ia_tiles) == 6
    _assert_same(ia, ref, got.get_json(INDEX_KEY), got)


def test_a_point_the_splitter_puts_in_another_cell_stops_the_run(tmp_path):
    # a grid origin inside the block: PDAL's rule for cells below the origin
    # (truncate, then one less) puts a point exactly on such an edge one cell too far
    # west; with no buffer to hold it in both cells, no view is then that tile, and the
    # run says so instead of losing points (with a buffer, the views are the tiles)
    rng = np.random.default_rng(6)
    xyz = np.column_stack([rng.uniform(0.5, 39.5, 2000), rng.uniform(0.5, 19.5, 2000), rng.uniform(0, 5, 2000)])
    xyz = np.vstack([xyz, [[10.0, 5.0, 1.0]]])  # x = origin - 10: on the edge of cell -1
    path = _block(tmp_path / "b.las", xyz)
    info = read_info(path)
    origin = (OFFSET[0] + 20.0, OFFSET[1])
    info, grid, (ia, ref), (ints, views, got) = _both(path, 10.0, 2.0, origin)
    _assert_same(ia, ref, tiles_from_views(ints, views, info, grid, got), got)
    info, grid, (ia, ref), (ints, views, got) = _both(path, 10.0, 0.0, origin)
    with pytest.raises(TilesDoNotAddUp, match="no view equal to the buffered points"):
        tiles_from_views(ints, views, info, grid, got)


@pytest.mark.parametrize("buffer", [2.0, 0.0])
def test_a_point_outside_the_headers_bounds(tmp_path, buffer):
    # up to 1 m outside the header's bounds is read; the grid gives such a point its
    # nearest edge tile, the splitter a cell off the grid, which the buffer covers
    import struct

    rng = np.random.default_rng(8)
    xyz = np.column_stack([rng.uniform(0.5, 29.5, 2000), rng.uniform(0.5, 19.5, 2000), rng.uniform(0, 5, 2000)])
    xyz = np.vstack([xyz, [[30.4, 5.0, 1.0]]])
    path = _block(tmp_path / "b.las", xyz)
    data = bytearray(path.read_bytes())
    struct.pack_into("<d", data, 179, OFFSET[0] + 29.9)  # the header's max x, 0.5 m short
    path.write_bytes(bytes(data))
    info, grid, (ia, ref), (ints, views, got) = _both(path, 10.0, buffer, (OFFSET[0], OFFSET[1]))
    if buffer:
        _assert_same(ia, ref, tiles_from_views(ints, views, info, grid, got), got)
    else:
        with pytest.raises(TilesDoNotAddUp, match=r"tile\(s\) \[2\]"):
            tiles_from_views(ints, views, info, grid, got)
