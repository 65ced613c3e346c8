"""CRS of a block: read from WKT or GeoTIFF keys (EVLRs too), refused unless in metres, written back."""

from __future__ import annotations

import laspy
import pyproj
import pytest

from pipeline.blockinfo import read_info
from pipeline.errors import InputError
from las_blocks import cloud, write_block


@pytest.mark.parametrize("version,fmt,wkt", [("1.2", 3, False), ("1.4", 1, True), ("1.4", 6, True)])
def test_crs_is_kept(tmp_path, version, fmt, wkt):
    """GeoTIFF keys for LAS 1.2 formats 0-5, a WKT VLR otherwise; both read back."""
    path = write_block(tmp_path / "b.las", cloud(100), version=version, point_format=fmt, crs_epsg=32755)
    with laspy.open(path) as r:
        kinds = {type(v).__name__ for v in r.header.vlrs}
    assert ("WktCoordinateSystemVlr" in kinds) == wkt
    assert ("GeoKeyDirectoryVlr" in kinds) == (not wkt)
    assert pyproj.CRS.from_wkt(read_info(path).crs_wkt).to_epsg() == 32755


def test_custom_crs_without_geotiff_encoding(tmp_path):
    custom = pyproj.CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=151.1 +k=1 +x_0=50000 +y_0=0 +ellps=GRS80 +units=m")
    path = write_block(tmp_path / "b.las", cloud(100), version="1.2", point_format=3, crs_wkt=custom.to_wkt())
    assert pyproj.CRS.from_wkt(read_info(path).crs_wkt).equals(custom)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_crs_in_an_extended_vlr_is_read(tmp_path, suffix):
    # LAS 1.4 may keep its WKT in an EVLR after the points: it was not looked at, and
    # trees.parquet said "unknown CRS"
    src = write_block(tmp_path / f"src{suffix}", cloud(500), version="1.4", point_format=6)
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
    path = write_block(tmp_path / "b.las", cloud(100), version="1.4", point_format=6,
                  crs_wkt=pyproj.CRS.from_epsg(epsg).to_wkt())
    with pytest.raises(InputError, match=f"{words}.*reproject"):
        read_info(path)


def test_a_compound_crs_in_metres_is_fine(tmp_path):
    crs = pyproj.CRS.from_user_input("EPSG:28355+5711")  # GDA94 / MGA 55 + AHD height
    path = write_block(tmp_path / "b.las", cloud(100), version="1.4", point_format=6, crs_wkt=crs.to_wkt())
    assert pyproj.CRS.from_wkt(read_info(path).crs_wkt).equals(crs)


def _with_geo_keys(path, keys):
    """A LAS 1.2 file whose only CRS record is a GeoKeyDirectory holding ``keys`` ({id: value})."""
    src = laspy.read(write_block(path.with_name("src.las"), cloud(100)))
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
    path = write_block(tmp_path / "b.las", cloud(100), version="1.4", point_format=6,
                  crs_wkt=pyproj.CRS.from_epsg(4978).to_wkt())
    with pytest.raises(InputError, match="Earth-centred.*reproject"):
        read_info(path)


def test_no_crs_is_none(tmp_path):
    assert read_info(write_block(tmp_path / "b.las", cloud(10))).crs_wkt is None
