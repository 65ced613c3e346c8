"""Reading points: local coordinates that lose nothing and do not depend on how a file
stores them, chunks in order, truncated or out-of-bounds point data."""

from __future__ import annotations

import laspy
import numpy as np
import pytest

from pipeline.blockinfo import read_info
from pipeline.errors import InputError
from pipeline.reading import LOCAL_STEPS_PER_M, TO_LOCAL_BLOCK, iter_points, read_points, sample_xy, to_local
from las_blocks import EASTING, NORTHING, cloud, one_line, patch, write_block


def test_utm_coordinates_lose_nothing(tmp_path):
    """Local float64 coordinates equal the stored integers times the scale exactly (to 1e-9 m)."""
    xyz = cloud(20_000) + [0.0, 3_000_000.0, 0.0]  # a northing near 9.2e6 m
    path = write_block(tmp_path / "b.laz", xyz, offsets=(EASTING, NORTHING + 3e6, 0.0), scales=(0.0001, 0.0001, 0.0001))
    info = read_info(path)
    las = laspy.read(path)
    exact = np.column_stack([las.X * 0.0001 + info.offsets[0], las.Y * 0.0001 + info.offsets[1], las.Z * 0.0001])
    pts, _ = read_points(path)
    assert np.abs(pts + info.origin - exact).max() < 1e-6
    assert np.abs(pts + info.origin - xyz).max() < 1e-3


def test_the_same_points_read_the_same_whatever_the_offset_and_scale(tmp_path):
    """A block re-saved by another tool with another offset (or a finer scale) holds the
    same millimetre points; ``X * scale + (offset - origin)`` differed in its last bit for
    most of them, enough to move points on a 0.1 m voxel boundary into the next voxel."""
    mm = np.round(cloud(50_000), 3)
    mm[:5000, 0] = EASTING + np.round(np.arange(5000) * 0.1, 1)  # on the 0.1 m planes
    mm[:5000, 2] = 100.0 + np.round(np.arange(5000) % 300 * 0.1, 1)
    paths = [
        write_block(tmp_path / "a.laz", mm),
        write_block(tmp_path / "b.laz", mm, offsets=(EASTING - 999.0, NORTHING + 123.456, 99.0)),
        write_block(tmp_path / "c.laz", mm, offsets=(500_000.0, 6_000_000.0, 0.0)),
        write_block(tmp_path / "d.laz", mm, scales=(0.0001, 0.0001, 0.0001)),
    ]
    local = [read_points(p)[0] for p in paths]
    assert len({read_info(p).origin for p in paths}) == 1
    naive = [(laspy.read(p).X * 0.001 + read_info(p).offsets[0] - read_info(p).origin[0]) for p in paths[:3]]
    assert not all(np.array_equal(naive[0], n) for n in naive[1:])  # what the rounding is for
    for other in local[1:]:
        assert np.array_equal(local[0], other)
    assert np.abs(local[0] + read_info(paths[0]).origin - mm).max() < 1e-6


def test_iter_points_chunks_cover_the_file_in_order(tmp_path):
    xyz = cloud(10_001)
    path = write_block(tmp_path / "b.laz", xyz)
    starts, total = [], 0
    whole, info = read_points(path)
    for start, chunk in iter_points(path, chunk_points=3000):
        assert chunk.shape[1] == 3 and chunk.dtype == np.float64 and len(chunk) <= 3000
        assert np.array_equal(chunk, whole[start : start + len(chunk)])
        starts.append(start)
        total += len(chunk)
    assert total == len(xyz) and starts[0] == 0 and starts == sorted(starts)


def test_custom_origin(tmp_path):
    path = write_block(tmp_path / "b.las", cloud(100))
    pts, info = read_points(path, origin=(EASTING, NORTHING, 0.0))
    pts2, _ = read_points(path)
    assert np.allclose(pts + [EASTING, NORTHING, 0.0], pts2 + info.origin, atol=1e-9)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_truncated(tmp_path, suffix):
    path = write_block(tmp_path / f"b{suffix}", cloud(50_000))
    data = path.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as e:
        read_points(cut)
    assert "truncated" in one_line(e)


def test_points_outside_header_bounds(tmp_path):
    path = write_block(tmp_path / "b.las", cloud(100))
    patch(path, 187, "<d", EASTING + 30.0)  # min x: many points now lie outside
    with pytest.raises(InputError) as e:
        read_points(path)
    assert "outside" in one_line(e)


def test_local_coordinates_in_blocks_equal_the_whole_column_arithmetic():
    # rows converted a block at a time, the last block partial: the same floats, bit for bit
    from types import SimpleNamespace

    rng = np.random.default_rng(4)
    n = 2 * TO_LOCAL_BLOCK + 123
    ints = rng.integers(-2**31, 2**31 - 1, (n, 3)).astype(np.int32)
    info = SimpleNamespace(origin=(500000.0, 6950000.0, 10.0), scales=(0.001, 0.00025, 0.01),
                           offsets=(500123.457, 6950001.0, 0.0))
    want = np.empty((n, 3))
    for j in range(3):
        col = ints[:, j] * info.scales[j] + (info.offsets[j] - info.origin[j])
        want[:, j] = np.rint(col * LOCAL_STEPS_PER_M) / LOCAL_STEPS_PER_M
    got = to_local(ints, info)
    assert np.array_equal(got.view(np.int64), want.view(np.int64))
    out = np.full((n, 3), np.nan)
    assert to_local(ints, info, out=out) is out and np.array_equal(out.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize("suffix", [".laz", ".las"])
@pytest.mark.parametrize("stride", [1, 7, 3000, 20_000])
def test_sample_xy_is_every_strideth_point_as_read_points_gives_it(tmp_path, suffix, stride):
    path = write_block(tmp_path / f"b{suffix}", cloud(10_001, seed=3))
    whole, info = read_points(path)
    xy, index = sample_xy(path, stride, info=info, chunk_points=3000)  # chunks not multiples of the stride
    assert np.array_equal(index, np.arange(0, len(whole), stride))
    assert xy.dtype == np.float64 and np.array_equal(xy, whole[::stride, :2])


@pytest.mark.parametrize("per_core", [1_000, 4_096, 50_000])
def test_a_block_decoded_in_small_pieces_reads_the_same(tmp_path, monkeypatch, per_core):
    """A whole block is decoded a few LAZ chunks per core at a time and converted from the
    records' X, Y and Z fields in place: the same points, to the bit, as chunks of 3,000
    converted from a copy of the stored integers, and a point out of bounds is still found."""
    import pipeline.reading

    xyz = cloud(20_001)
    xyz[15_000:, 0] += 50.0  # the last quarter east of the rest
    path = write_block(tmp_path / "b.laz", xyz)
    chunked = np.concatenate([c for _, c in iter_points(path, chunk_points=3000)])
    monkeypatch.setattr(pipeline.reading, "DECODE_POINTS_PER_CORE", per_core)
    monkeypatch.setattr(pipeline.reading.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert pipeline.reading.decode_points(2_000_000) == 2 * per_core
    assert pipeline.reading.decode_points(1_500) == 1_500  # never more than asked for
    whole, info = read_points(path)
    assert np.array_equal(whole, chunked)
    ints = np.stack([laspy.read(path).X, laspy.read(path).Y, laspy.read(path).Z], axis=1).astype(np.int32)
    assert np.array_equal(to_local((ints[:, 0], ints[:, 1], ints[:, 2]), info), to_local(ints, info))
    # the header's max x lowered under the points of the last quarter: the first of them is named
    patch(path, 179, "<d", xyz[:15_000, 0].max() + 1.5)
    with pytest.raises(InputError) as e:
        read_points(path)
    assert "point 15000 lies outside" in one_line(e)
