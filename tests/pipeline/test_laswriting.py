"""Writing LAS/LAZ: the streaming writer and the labelled copy of a block (every input dimension kept)."""

from __future__ import annotations

import struct

import laspy
import numpy as np
import pytest

from pipeline.blockinfo import read_info
from pipeline.laswriting import LasBlockWriter, write_labelled_las
from las_blocks import EASTING, NORTHING, cloud, write_block


def test_writer_leaves_nothing_on_error(tmp_path):
    with pytest.raises(RuntimeError):
        with LasBlockWriter(tmp_path / "x.laz") as w:
            w.write(cloud(10))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_writer_extra_dims(tmp_path):
    xyz = cloud(1000)
    with LasBlockWriter(tmp_path / "x.laz", offsets=(EASTING, NORTHING, 0), extra_dims={"tree_id": np.int32, "flag": bool}) as w:
        w.write(xyz, tree_id=np.arange(1000), flag=np.arange(1000) % 2 == 0)
    las = laspy.read(tmp_path / "x.laz")
    assert np.array_equal(las.tree_id, np.arange(1000))
    assert np.array_equal(las.flag, (np.arange(1000) % 2 == 0).astype(np.uint8))


def test_labelled_las(tmp_path):
    xyz = cloud(3000)
    src = write_block(tmp_path / "b.las", xyz, point_format=3, crs_epsg=28356)
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
    xyz = cloud(n)
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
    xyz = cloud(n)
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
    xyz = cloud(1500)
    src = write_block(tmp_path / "old.las", xyz, point_format=1, version="1.2")
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
    xyz = cloud(n)
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
