"""read_info: what a block's header says, checked; every bad header is one InputError line."""

from __future__ import annotations

import laspy
import numpy as np
import pyproj
import pytest

from pipeline.blockinfo import read_info
from pipeline.errors import InputError
from pipeline.reading import read_points
from las_blocks import cloud, one_line, patch, write_block


@pytest.mark.parametrize(
    "version,fmt,suffix",
    [
        ("1.2", 0, ".las"),
        ("1.2", 1, ".laz"),
        ("1.2", 3, ".las"),
        ("1.3", 2, ".laz"),
        ("1.4", 1, ".las"),
        ("1.4", 6, ".laz"),
        ("1.4", 7, ".las"),
        ("1.4", 8, ".laz"),
        ("1.4", 10, ".laz"),
    ],
)
def test_round_trip_versions_and_formats(tmp_path, version, fmt, suffix):
    xyz = cloud()
    path = write_block(tmp_path / f"b{suffix}", xyz, version=version, point_format=fmt, crs_epsg=28356)
    info = read_info(path)
    assert (info.version, info.point_format, info.compressed) == (version, fmt, suffix == ".laz")
    assert info.n_points == len(xyz)
    assert info.origin == tuple(np.floor(xyz.min(axis=0)))
    pts, info2 = read_points(path)
    assert info2 == info
    assert np.abs(pts + info.origin - xyz).max() <= 0.0005 + 1e-9  # half the 1 mm scale
    assert pyproj.CRS.from_wkt(info.crs_wkt).to_epsg() == 28356


def test_not_las(tmp_path):
    p = tmp_path / "notes.laz"
    p.write_text("hello, this is a text file\n")
    with pytest.raises(InputError) as e:
        read_info(p)
    assert "not a LAS/LAZ file" in one_line(e)


def test_garbage_after_magic(tmp_path):
    p = tmp_path / "g.las"
    p.write_bytes(b"LASF" + np.random.default_rng(1).bytes(400))
    with pytest.raises(InputError) as e:
        read_info(p)
    one_line(e)


def test_tiny_file(tmp_path):
    p = tmp_path / "t.las"
    p.write_bytes(b"LASF\x00")
    with pytest.raises(InputError) as e:
        read_info(p)
    assert "truncated" in one_line(e)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_info(tmp_path / "nope.las")


@pytest.mark.parametrize("table", ["kept", "unknown"])
def test_a_laz_whose_header_claims_more_points_than_its_chunks_hold(tmp_path, table):
    # a forged count (1e12 points in a file of 50,000) had the tiler plan 500,000 tasks
    path = write_block(tmp_path / "b.laz", cloud(50_000), version="1.4", point_format=6)
    assert read_info(path).n_points == 50_000
    patch(path, 247, "<Q", 10**12)  # LAS 1.4: number of point records
    if table == "unknown":  # a LAZ written without a chunk table: bounded by its size
        with laspy.open(path) as reader:
            start = reader.header.offset_to_point_data
        patch(path, start, "<q", -1)
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "corrupt: the header announces 1,000,000,000,000 points but its compressed data holds at most" in one_line(e)


def test_empty_header_only(tmp_path):
    header = laspy.LasHeader(version="1.4", point_format=6)
    with laspy.open(tmp_path / "e.las", mode="w", header=header):
        pass
    with pytest.raises(InputError) as e:
        read_info(tmp_path / "e.las")
    assert "empty" in one_line(e)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), 0.0])
def test_bad_scale(tmp_path, value):
    path = write_block(tmp_path / "b.las", cloud(100))
    patch(path, 131, "<d", value)  # x scale factor
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "scale" in one_line(e)


def test_absurd_offsets(tmp_path):
    path = write_block(tmp_path / "b.las", cloud(100))
    patch(path, 155, "<d", 1e12)  # x offset
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "absurd" in one_line(e)


def test_nan_bounds(tmp_path):
    path = write_block(tmp_path / "b.las", cloud(100))
    patch(path, 179, "<d", float("nan"))  # max x
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "NaN" in one_line(e)


def test_absurd_extent(tmp_path):
    xyz = cloud(100)
    xyz[0, 0] += 150_000.0
    path = write_block(tmp_path / "b.las", xyz)
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "absurd" in one_line(e)


def test_unsupported_version(tmp_path):
    path = write_block(tmp_path / "b.las", cloud(100))
    patch(path, 24, "<BB", 2, 0)
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "version 2.0" in one_line(e)
