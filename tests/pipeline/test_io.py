"""Reading blocks and writing outputs: round trips, CRS, precision and every bad input."""

from __future__ import annotations

import json
import struct

import laspy
import numpy as np
import pyarrow.parquet as pq
import pyproj
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pipeline.blockinfo import read_info
from pipeline.errors import InputError
from pipeline.laswriting import LasBlockWriter, write_labelled_las
from pipeline.parquet import PointsParquetWriter, read_trees_parquet, write_trees_parquet
from pipeline.reading import iter_points, read_points

EASTING, NORTHING = 512_345.0, 6_234_567.0


def _cloud(n=5000, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 40, (n, 3)) + [EASTING, NORTHING, 100.0]


def _write(path, xyz, **kw):
    kw.setdefault("offsets", (EASTING, NORTHING, 0.0))
    with LasBlockWriter(path, **kw) as w:
        half = len(xyz) // 2
        w.write(xyz[:half])
        w.write(xyz[half:])
    return path


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
    xyz = _cloud()
    path = _write(tmp_path / f"b{suffix}", xyz, version=version, point_format=fmt, crs_epsg=28356)
    info = read_info(path)
    assert (info.version, info.point_format, info.compressed) == (version, fmt, suffix == ".laz")
    assert info.n_points == len(xyz)
    assert info.origin == tuple(np.floor(xyz.min(axis=0)))
    pts, info2 = read_points(path)
    assert info2 == info
    assert np.abs(pts + info.origin - xyz).max() <= 0.0005 + 1e-9  # half the 1 mm scale
    assert pyproj.CRS.from_wkt(info.crs_wkt).to_epsg() == 28356


@pytest.mark.parametrize("version,fmt,wkt", [("1.2", 3, False), ("1.4", 1, True), ("1.4", 6, True)])
def test_crs_is_kept(tmp_path, version, fmt, wkt):
    """GeoTIFF keys for LAS 1.2 formats 0-5, a WKT VLR otherwise; both read back."""
    path = _write(tmp_path / "b.las", _cloud(100), version=version, point_format=fmt, crs_epsg=32755)
    with laspy.open(path) as r:
        kinds = {type(v).__name__ for v in r.header.vlrs}
    assert ("WktCoordinateSystemVlr" in kinds) == wkt
    assert ("GeoKeyDirectoryVlr" in kinds) == (not wkt)
    assert pyproj.CRS.from_wkt(read_info(path).crs_wkt).to_epsg() == 32755


def test_custom_crs_without_geotiff_encoding(tmp_path):
    custom = pyproj.CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=151.1 +k=1 +x_0=50000 +y_0=0 +ellps=GRS80 +units=m")
    path = _write(tmp_path / "b.las", _cloud(100), version="1.2", point_format=3, crs_wkt=custom.to_wkt())
    assert pyproj.CRS.from_wkt(read_info(path).crs_wkt).equals(custom)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_crs_in_an_extended_vlr_is_read(tmp_path, suffix):
    # LAS 1.4 may keep its WKT in an EVLR after the points: it was not looked at, and
    # trees.parquet said "unknown CRS"
    src = _write(tmp_path / f"src{suffix}", _cloud(500), version="1.4", point_format=6)
    las = laspy.read(src)
    las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.vlrs.known.WktCoordinateSystemVlr(pyproj.CRS.from_epsg(32633).to_wkt())])
    las.header.global_encoding.wkt = True
    path = tmp_path / f"evlr{suffix}"
    las.write(path)
    assert pyproj.CRS.from_wkt(read_info(path).crs_wkt).to_epsg() == 32633


@pytest.mark.parametrize(
    "epsg, words",
    [(2227, "US survey foot"), (2277, "US survey foot"), (4326, "longitude/latitude in degrees")],
)
def test_a_crs_not_in_metres_is_refused(tmp_path, epsg, words):
    # every length (parameters, heights, diameters, areas) is in metres: a block in feet
    # gave 14 m "heights" for 4 m trees and split trees; one in degrees found no trees
    path = _write(tmp_path / "b.las", _cloud(100), version="1.4", point_format=6,
                  crs_wkt=pyproj.CRS.from_epsg(epsg).to_wkt())
    with pytest.raises(InputError, match=f"{words}.*reproject"):
        read_info(path)


def test_a_compound_crs_in_metres_is_fine(tmp_path):
    crs = pyproj.CRS.from_user_input("EPSG:28355+5711")  # GDA94 / MGA 55 + AHD height
    path = _write(tmp_path / "b.las", _cloud(100), version="1.4", point_format=6, crs_wkt=crs.to_wkt())
    assert pyproj.CRS.from_wkt(read_info(path).crs_wkt).equals(crs)


def _with_geo_keys(path, keys):
    """A LAS 1.2 file whose only CRS record is a GeoKeyDirectory holding ``keys`` ({id: value})."""
    src = laspy.read(_write(path.with_name("src.las"), _cloud(100)))
    header = laspy.LasHeader(version="1.2", point_format=1)
    header.scales, header.offsets = src.header.scales, src.header.offsets
    vlr = laspy.vlrs.known.GeoKeyDirectoryVlr()
    vlr.geo_keys_header.key_directory_version = vlr.geo_keys_header.key_revision = 1
    vlr.geo_keys = []
    for key_id, value in {1024: 1, **keys}.items():  # 1024: GTModelType projected
        entry = laspy.vlrs.geotiff.GeoKeyEntryStruct()
        entry.id, entry.tiff_tag_location, entry.count, entry.value_offset = key_id, 0, 1, value
        vlr.geo_keys.append(entry)
    vlr.geo_keys_header.number_of_keys = len(vlr.geo_keys)
    header.vlrs.append(vlr)
    las = laspy.LasData(header)
    las.x, las.y, las.z = src.x, src.y, src.z
    las.write(path)
    return path


@pytest.mark.parametrize(
    "keys, words",
    [
        ({3072: 32767, 3076: 9003}, "coordinate unit as US survey foot"),  # user-defined CRS in feet
        ({3072: 26918, 4096: 6360, 4099: 9003}, "height unit as US survey foot"),  # UTM, heights in feet
        ({3072: 2264}, "US survey foot"),  # an EPSG CRS in feet, as before
    ],
)
def test_geotiff_keys_in_feet_are_refused(tmp_path, keys, words):
    # laspy reads only the CRS codes of GeoTIFF keys: both files passed as metres
    with pytest.raises(InputError, match=f"{words}.*reproject"):
        read_info(_with_geo_keys(tmp_path / "b.las", keys))


def test_geotiff_keys_keep_the_vertical_crs(tmp_path):
    info = read_info(_with_geo_keys(tmp_path / "b.las", {3072: 28356, 4096: 5711, 4099: 9001}))
    crs = pyproj.CRS.from_wkt(info.crs_wkt)
    assert crs.is_compound and [c.to_epsg() for c in crs.sub_crs_list] == [28356, 5711]
    assert read_info(_with_geo_keys(tmp_path / "c.las", {3072: 28356})).crs_wkt == pyproj.CRS.from_epsg(28356).to_wkt()


def test_a_geocentric_crs_is_refused(tmp_path):
    path = _write(tmp_path / "b.las", _cloud(100), version="1.4", point_format=6,
                  crs_wkt=pyproj.CRS.from_epsg(4978).to_wkt())
    with pytest.raises(InputError, match="Earth-centred.*reproject"):
        read_info(path)


def test_no_crs_is_none(tmp_path):
    assert read_info(_write(tmp_path / "b.las", _cloud(10))).crs_wkt is None


def test_utm_coordinates_lose_nothing(tmp_path):
    """Local float64 coordinates equal the stored integers times the scale exactly (to 1e-9 m)."""
    xyz = _cloud(20_000) + [0.0, 3_000_000.0, 0.0]  # a northing near 9.2e6 m
    path = _write(tmp_path / "b.laz", xyz, offsets=(EASTING, NORTHING + 3e6, 0.0), scales=(0.0001, 0.0001, 0.0001))
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
    mm = np.round(_cloud(50_000), 3)
    mm[:5000, 0] = EASTING + np.round(np.arange(5000) * 0.1, 1)  # on the 0.1 m planes
    mm[:5000, 2] = 100.0 + np.round(np.arange(5000) % 300 * 0.1, 1)
    paths = [
        _write(tmp_path / "a.laz", mm),
        _write(tmp_path / "b.laz", mm, offsets=(EASTING - 999.0, NORTHING + 123.456, 99.0)),
        _write(tmp_path / "c.laz", mm, offsets=(500_000.0, 6_000_000.0, 0.0)),
        _write(tmp_path / "d.laz", mm, scales=(0.0001, 0.0001, 0.0001)),
    ]
    local = [read_points(p)[0] for p in paths]
    assert len({read_info(p).origin for p in paths}) == 1
    naive = [(laspy.read(p).X * 0.001 + read_info(p).offsets[0] - read_info(p).origin[0]) for p in paths[:3]]
    assert not all(np.array_equal(naive[0], n) for n in naive[1:])  # what the rounding is for
    for other in local[1:]:
        assert np.array_equal(local[0], other)
    assert np.abs(local[0] + read_info(paths[0]).origin - mm).max() < 1e-6


def test_iter_points_chunks_cover_the_file_in_order(tmp_path):
    xyz = _cloud(10_001)
    path = _write(tmp_path / "b.laz", xyz)
    starts, total = [], 0
    whole, info = read_points(path)
    for start, chunk in iter_points(path, chunk_points=3000):
        assert chunk.shape[1] == 3 and chunk.dtype == np.float64 and len(chunk) <= 3000
        assert np.array_equal(chunk, whole[start : start + len(chunk)])
        starts.append(start)
        total += len(chunk)
    assert total == len(xyz) and starts[0] == 0 and starts == sorted(starts)


def test_custom_origin(tmp_path):
    path = _write(tmp_path / "b.las", _cloud(100))
    pts, info = read_points(path, origin=(EASTING, NORTHING, 0.0))
    pts2, _ = read_points(path)
    assert np.allclose(pts + [EASTING, NORTHING, 0.0], pts2 + info.origin, atol=1e-9)


# ------------------------------------------------------------------------- bad input


def _one_line(err: pytest.ExceptionInfo) -> str:
    msg = str(err.value)
    assert "\n" not in msg and len(msg) < 300
    return msg


def test_not_las(tmp_path):
    p = tmp_path / "notes.laz"
    p.write_text("hello, this is a text file\n")
    with pytest.raises(InputError) as e:
        read_info(p)
    assert "not a LAS/LAZ file" in _one_line(e)


def test_garbage_after_magic(tmp_path):
    p = tmp_path / "g.las"
    p.write_bytes(b"LASF" + np.random.default_rng(1).bytes(400))
    with pytest.raises(InputError) as e:
        read_info(p)
    _one_line(e)


def test_tiny_file(tmp_path):
    p = tmp_path / "t.las"
    p.write_bytes(b"LASF\x00")
    with pytest.raises(InputError) as e:
        read_info(p)
    assert "truncated" in _one_line(e)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_info(tmp_path / "nope.las")


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_truncated(tmp_path, suffix):
    path = _write(tmp_path / f"b{suffix}", _cloud(50_000))
    data = path.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as e:
        read_points(cut)
    assert "truncated" in _one_line(e)


@pytest.mark.parametrize("table", ["kept", "unknown"])
def test_a_laz_whose_header_claims_more_points_than_its_chunks_hold(tmp_path, table):
    # a forged count (1e12 points in a file of 50,000) had the tiler plan 500,000 tasks
    path = _write(tmp_path / "b.laz", _cloud(50_000), version="1.4", point_format=6)
    assert read_info(path).n_points == 50_000
    _patch(path, 247, "<Q", 10**12)  # LAS 1.4: number of point records
    if table == "unknown":  # a LAZ written without a chunk table: bounded by its size
        with laspy.open(path) as reader:
            start = reader.header.offset_to_point_data
        _patch(path, start, "<q", -1)
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "corrupt: the header announces 1,000,000,000,000 points but its compressed data holds at most" in _one_line(e)


def test_empty_header_only(tmp_path):
    header = laspy.LasHeader(version="1.4", point_format=6)
    with laspy.open(tmp_path / "e.las", mode="w", header=header):
        pass
    with pytest.raises(InputError) as e:
        read_info(tmp_path / "e.las")
    assert "empty" in _one_line(e)


def _patch(path, offset, fmt, *values):
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("value", [float("nan"), float("inf"), 0.0])
def test_bad_scale(tmp_path, value):
    path = _write(tmp_path / "b.las", _cloud(100))
    _patch(path, 131, "<d", value)  # x scale factor
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "scale" in _one_line(e)


def test_absurd_offsets(tmp_path):
    path = _write(tmp_path / "b.las", _cloud(100))
    _patch(path, 155, "<d", 1e12)  # x offset
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "absurd" in _one_line(e)


def test_nan_bounds(tmp_path):
    path = _write(tmp_path / "b.las", _cloud(100))
    _patch(path, 179, "<d", float("nan"))  # max x
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "NaN" in _one_line(e)


def test_absurd_extent(tmp_path):
    xyz = _cloud(100)
    xyz[0, 0] += 150_000.0
    path = _write(tmp_path / "b.las", xyz)
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "absurd" in _one_line(e)


def test_points_outside_header_bounds(tmp_path):
    path = _write(tmp_path / "b.las", _cloud(100))
    _patch(path, 187, "<d", EASTING + 30.0)  # min x: many points now lie outside
    with pytest.raises(InputError) as e:
        read_points(path)
    assert "outside" in _one_line(e)


def test_unsupported_version(tmp_path):
    path = _write(tmp_path / "b.las", _cloud(100))
    _patch(path, 24, "<BB", 2, 0)
    with pytest.raises(InputError) as e:
        read_info(path)
    assert "version 2.0" in _one_line(e)


# --------------------------------------------------------------------------- writers


def test_writer_leaves_nothing_on_error(tmp_path):
    with pytest.raises(RuntimeError):
        with LasBlockWriter(tmp_path / "x.laz") as w:
            w.write(_cloud(10))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_writer_extra_dims(tmp_path):
    xyz = _cloud(1000)
    with LasBlockWriter(tmp_path / "x.laz", offsets=(EASTING, NORTHING, 0), extra_dims={"tree_id": np.int32, "flag": bool}) as w:
        w.write(xyz, tree_id=np.arange(1000), flag=np.arange(1000) % 2 == 0)
    las = laspy.read(tmp_path / "x.laz")
    assert np.array_equal(las.tree_id, np.arange(1000))
    assert np.array_equal(las.flag, (np.arange(1000) % 2 == 0).astype(np.uint8))


def test_labelled_las(tmp_path):
    xyz = _cloud(3000)
    src = _write(tmp_path / "b.las", xyz, point_format=3, crs_epsg=28356)
    n = len(xyz)
    labels = {"tree_id": np.arange(n) % 7, "is_wood": np.arange(n) % 3 == 0, "wood_score": np.linspace(0, 1, n, dtype=np.float32)}
    write_labelled_las(src, tmp_path / "out.laz", labels=labels, chunk_points=1000)
    las = laspy.read(tmp_path / "out.laz")
    assert np.array_equal(las.tree_id, labels["tree_id"])
    assert np.array_equal(las.is_wood.astype(bool), labels["is_wood"])
    assert np.array_equal(las.wood_score, labels["wood_score"])
    orig = laspy.read(src)
    assert np.array_equal(las.X, orig.X) and np.array_equal(las.Z, orig.Z)
    assert las.header.parse_crs().to_epsg() == 28356


def _tree_columns(k, rng):
    cols = {
        "tree_id": np.arange(1, k + 1, dtype=np.int64),
        "trunk_x": rng.uniform(0, 100, k) + EASTING,
        "trunk_y": rng.uniform(0, 100, k) + NORTHING,
        "trunk_z": rng.uniform(50, 60, k),
    }
    for name in ("height_m", "crown_diameter_m", "crown_area_m2", "crown_volume_m3", "trunk_diameter_m", "wood_fraction"):
        cols[name] = rng.uniform(0, 10, k)
    cols["n_points"] = rng.integers(0, 10_000, k).astype(np.int64)
    return cols


@pytest.mark.parametrize("epsg", [28356, None])
def test_trees_geoparquet(tmp_path, epsg):
    cols = _tree_columns(12, np.random.default_rng(3))
    wkt = pyproj.CRS.from_epsg(epsg).to_wkt() if epsg else None
    write_trees_parquet(tmp_path / "trees.parquet", cols, crs_wkt=wkt)
    table = pq.read_table(tmp_path / "trees.parquet")
    geo = json.loads(table.schema.metadata[b"geo"])
    assert geo["version"] == "1.1.0" and geo["primary_column"] == "geometry"
    col = geo["columns"]["geometry"]
    assert col["encoding"] == "WKB" and col["geometry_types"] == ["Point"]
    if epsg:
        assert pyproj.CRS.from_json_dict(col["crs"]).to_epsg() == epsg
    else:
        assert col["crs"] is None
    assert col["bbox"] == [cols["trunk_x"].min(), cols["trunk_y"].min(), cols["trunk_x"].max(), cols["trunk_y"].max()]
    for wkb, x, y in zip(table.column("geometry").to_pylist(), cols["trunk_x"], cols["trunk_y"]):
        assert struct.unpack("<BIdd", wkb) == (1, 1, x, y)
    back, _ = read_trees_parquet(tmp_path / "trees.parquet")
    for name, values in cols.items():
        assert back[name].dtype == values.dtype and np.array_equal(back[name], values)


def test_trees_geoparquet_empty(tmp_path):
    write_trees_parquet(tmp_path / "t.parquet", _tree_columns(0, np.random.default_rng(0)), crs_wkt=None)
    assert pq.read_table(tmp_path / "t.parquet").num_rows == 0


_float = st.floats(allow_nan=False, allow_infinity=False, width=64, min_value=-1e7, max_value=1e7)


@settings(max_examples=25, deadline=None)
@given(
    k=st.integers(0, 30),
    seed=st.integers(0, 2**32 - 1),
    xs=hnp.arrays(np.float64, 30, elements=_float),
)
def test_trees_parquet_round_trip_property(tmp_path_factory, k, seed, xs):
    path = tmp_path_factory.mktemp("trees") / "trees.parquet"
    cols = _tree_columns(k, np.random.default_rng(seed))
    cols["trunk_x"] = xs[:k]
    write_trees_parquet(path, cols, crs_wkt=None)
    back, geo = read_trees_parquet(path)
    for name, values in cols.items():
        assert np.array_equal(back[name], values)
    wkb = pq.read_table(path).column("geometry").to_pylist()
    assert [struct.unpack("<BIdd", w)[2:] for w in wkb] == list(zip(cols["trunk_x"], cols["trunk_y"]))


@settings(max_examples=25, deadline=None)
@given(
    sizes=st.lists(st.integers(0, 200), min_size=1, max_size=5),
    seed=st.integers(0, 2**32 - 1),
    scores=st.lists(st.floats(width=32, allow_nan=False), min_size=1, max_size=5),
)
def test_points_parquet_round_trip_property(tmp_path_factory, sizes, seed, scores):
    path = tmp_path_factory.mktemp("points") / "points.parquet"
    rng = np.random.default_rng(seed)
    parts = []
    with PointsParquetWriter(path, row_group_size=64) as w:
        for i, m in enumerate(sizes):
            part = (
                rng.integers(0, 2**64 - 1, m, dtype=np.uint64, endpoint=True),
                rng.integers(-(2**63), 2**63 - 1, m, dtype=np.int64),
                rng.random(m) < 0.5,
                rng.random(m) < 0.5,
                np.full(m, scores[i % len(scores)], dtype=np.float32),
            )
            w.write(*part)
            parts.append(part)
    table = pq.read_table(path)
    assert table.schema.names == ["point_index", "tree_id", "is_ground", "is_wood", "wood_score"]
    for j, name in enumerate(table.schema.names):
        expect = np.concatenate([p[j] for p in parts])
        got = table.column(name).to_numpy()
        assert got.dtype == expect.dtype and np.array_equal(got, expect)


def test_points_writer_aborts_cleanly(tmp_path):
    with pytest.raises(ValueError):
        with PointsParquetWriter(tmp_path / "points.parquet") as w:
            w.write([1], [1], [True], [False], [0.5])
            raise ValueError("stop")
    assert list(tmp_path.iterdir()) == []


def test_points_parquet_stores_the_point_index_delta_encoded(tmp_path):
    path = tmp_path / "points.parquet"
    n = 100_000
    with PointsParquetWriter(path) as w:
        w.write(np.arange(n), np.zeros(n, np.int64), np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, np.float32))
    column = pq.ParquetFile(path).metadata.row_group(0).column(0)
    assert column.path_in_schema == "point_index" and "DELTA_BINARY_PACKED" in column.encodings
    assert column.total_compressed_size < n // 10  # a counter costs next to nothing, not 8 bytes a row


def _labels(n):
    return {"tree_id": np.arange(n) % 7, "is_wood": np.arange(n) % 3 == 0, "wood_score": np.linspace(0, 1, n, dtype=np.float32)}


def test_labelled_las_keeps_scaled_extra_dimensions(tmp_path):
    # an input's own extra bytes keep their scales and offsets: the stored integers keep
    # their meaning (they were truncated to whole numbers: 1.55 -> 1)
    n = 2000
    rng = np.random.default_rng(3)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.offsets, header.scales = [EASTING, NORTHING, 0.0], [0.001] * 3
    header.add_extra_dims([
        laspy.ExtraBytesParams(name="scaled", type=np.int16, scales=np.array([0.01]), offsets=np.array([0.0])),
        laspy.ExtraBytesParams(name="plain", type=np.uint16),
    ])
    las = laspy.LasData(header)
    xyz = _cloud(n)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.scaled = np.round(rng.random(n) * 10, 2)
    las.plain = np.arange(n, dtype=np.uint16)
    src = tmp_path / "extra.laz"
    las.write(src)
    write_labelled_las(src, tmp_path / "out.laz", labels=_labels(n), chunk_points=700)
    out, orig = laspy.read(tmp_path / "out.laz"), laspy.read(src)
    assert np.array_equal(out.points.array["scaled"], orig.points.array["scaled"])  # the stored integers
    np.testing.assert_allclose(out.scaled, orig.scaled)  # and what they mean
    assert not np.allclose(out.scaled, np.floor(orig.scaled))
    assert np.array_equal(out.plain, orig.plain)
    assert np.array_equal(out.tree_id, _labels(n)["tree_id"])


def test_labelled_las_keeps_an_inputs_own_tree_id_and_the_files_identity(tmp_path):
    # an input's own extra dimension called tree_id vanished under ours, and the copy's
    # file source id, project GUID and system identifier were reset
    import uuid as uuidlib

    n = 1500
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.offsets, header.scales = [EASTING, NORTHING, 0.0], [0.001] * 3
    header.add_extra_dims([laspy.ExtraBytesParams(name="tree_id", type=np.uint8),
                           laspy.ExtraBytesParams(name="input_tree_id", type=np.uint16)])
    header.file_source_id = 4242
    header.uuid = uuidlib.UUID("12345678-1234-5678-1234-567812345678")
    header.system_identifier = "SCANNER-7"
    las = laspy.LasData(header)
    xyz = _cloud(n)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.tree_id = np.arange(n) % 200
    las.input_tree_id = np.arange(n)
    src = tmp_path / "own.laz"
    las.write(src)
    write_labelled_las(src, tmp_path / "out.laz", labels=_labels(n), chunk_points=600)
    out = laspy.read(tmp_path / "out.laz")
    assert np.array_equal(out.tree_id, _labels(n)["tree_id"])  # ours
    assert np.array_equal(out.input_tree_id_2, np.arange(n) % 200)  # theirs, under a free name
    assert np.array_equal(out.input_tree_id, np.arange(n))
    assert out.header.file_source_id == 4242 and out.header.uuid == header.uuid
    assert out.header.system_identifier == "SCANNER-7"


@pytest.mark.parametrize("minor", [0, 1])
def test_labelled_las_of_a_las_1_0_or_1_1_block(tmp_path, minor):
    # laspy cannot write LAS 1.0/1.1: the labelled copy of such a block is LAS 1.2 (same
    # point formats 0-1, same points); it used to fail after the whole block was processed
    xyz = _cloud(1500)
    src = _write(tmp_path / "old.las", xyz, point_format=1, version="1.2")
    with open(src, "r+b") as fh:
        fh.seek(25)  # version minor
        fh.write(bytes([minor]))
    assert read_info(src).version == f"1.{minor}"
    write_labelled_las(src, tmp_path / "out.laz", labels=_labels(len(xyz)))
    out = laspy.read(tmp_path / "out.laz")
    assert str(out.header.version) == "1.2"
    orig = laspy.read(src)
    for dim in ("X", "Y", "Z", "intensity", "gps_time"):
        assert np.array_equal(out[dim], orig[dim])
    assert np.array_equal(out.tree_id, _labels(len(xyz))["tree_id"])


def test_labelled_las_of_a_block_with_undocumented_extra_bytes(tmp_path):
    # bytes at the end of each point that no ExtraBytes record describes: the labelled copy
    # keeps them as one uint8 dimension per byte (laspy could not read its own
    # "undocumented" record back, so the copy did not open)
    n = 500
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.offsets, header.scales = [EASTING, NORTHING, 0.0], [0.001] * 3
    header.add_extra_dims([laspy.ExtraBytesParams(name="pad", type="10u1")])
    las = laspy.LasData(header)
    xyz = _cloud(n)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.pad = np.arange(n * 10, dtype=np.uint8).reshape(n, 10)
    src = tmp_path / "undocumented.las"
    las.write(src)
    raw = bytearray(src.read_bytes())
    at = raw.find(b"LASF_Spec")
    raw[at + 16 : at + 18] = struct.pack("<H", 9999)  # the ExtraBytes record becomes an unknown one
    src.write_bytes(bytes(raw))
    orig = laspy.read(src)
    assert "ExtraBytes" in list(orig.point_format.extra_dimension_names)
    write_labelled_las(src, tmp_path / "out.laz", labels=_labels(n))
    out = laspy.read(tmp_path / "out.laz")
    for i in range(10):
        assert np.array_equal(out[f"ExtraBytes_{i}"], orig.points.array["ExtraBytes"][:, i])
    assert np.array_equal(out.tree_id, _labels(n)["tree_id"]) and np.array_equal(out.X, orig.X)
