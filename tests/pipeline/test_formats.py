"""PLY, PCD, E57 and text inputs: each gives exactly the points of the same block in
LAZ (so the same trees), and hostile files of each are refused with one line in
bounded memory."""

from __future__ import annotations

import contextlib
import resource
import tracemalloc
from pathlib import Path

import laspy
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from format_files import every_format, write_e57, write_pcd, write_ply, write_text
from pipeline.errors import InputError, ParameterError
from pipeline.formats import sniff
from pipeline.formats.convert import parse_crs_option, to_laz
from pipeline.laswriting import LasBlockWriter
from simulator.simparams import SimulationParams
from simulator.truth import write_simulation


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    """A small generated orchard (3 trees) in local metres at millimetres, as LAZ, and
    its points in every other format."""
    folder = tmp_path_factory.mktemp("formats")
    sim = folder / "sim.laz"
    write_simulation(SimulationParams(rows=1, trees_per_row=3, density=0.04, seed=3), str(sim), str(folder / "t.parquet"))
    las = laspy.read(sim)
    xyz = np.column_stack([las.x, las.y, las.z])
    xyz = np.round((xyz - np.floor(xyz.min(axis=0))) * 1000) / 1000  # local, mm: every format holds it
    ref = folder / "ref.laz"
    with LasBlockWriter(ref, scales=(0.001, 0.001, 0.001), offsets=(0.0, 0.0, 0.0)) as w:
        w.write(xyz)
    return {"xyz": xyz, "laz": ref, "files": every_format(folder / "in", xyz), "folder": folder}


def _ints(path):
    las = laspy.read(path)
    return np.column_stack([las.X, las.Y, las.Z]), tuple(las.header.scales), tuple(las.header.offsets)


@pytest.mark.parametrize("kind", ["ply-binary", "ply-binary-float", "ply-ascii", "pcd-ascii", "pcd-binary",
                                  "pcd-binary_compressed", "e57", "text-header", "text-bare", "text-csv"])
def test_each_format_gives_the_points_of_the_laz(block, tmp_path, kind):
    src = block["files"][kind]
    assert sniff(src) == kind.split("-")[0]
    done = to_laz(src, tmp_path / "c.laz", chunk_points=7_000)  # several chunks
    assert done.n_points == len(block["xyz"]) and done.n_dropped == 0
    got, ref = _ints(tmp_path / "c.laz"), _ints(block["laz"])
    assert got[1:] == ref[1:]
    assert np.array_equal(got[0], ref[0])  # same stored integers, in the same order: the same trees


def test_non_finite_rows_are_left_out_and_counted(tmp_path):
    xyz = np.array([[1.0, 2.0, 3.0], [np.nan, np.nan, np.nan], [4.0, 5.0, 6.0], [7.0, np.inf, 1.0]])
    done = to_laz(write_pcd(tmp_path / "o.pcd", xyz, "binary"), tmp_path / "o.laz")
    assert (done.n_points, done.n_dropped) == (2, 2)
    assert np.allclose(_ints(tmp_path / "o.laz")[0], [[1000, 2000, 3000], [4000, 5000, 6000]])
    nothing = np.full((3, 3), np.nan)
    with pytest.raises(InputError, match="holds no points with finite coordinates"):
        to_laz(write_pcd(tmp_path / "n.pcd", nothing, "ascii"), tmp_path / "n.laz")
    assert not (tmp_path / "n.laz").exists()


def test_text_columns_from_an_option_or_a_header(tmp_path):
    rows = "# made by hand\nid,east,x,y,z\n1,0,10.5,20.25,3\n2,0,11,21,4\n"
    (tmp_path / "c.csv").write_text(rows)
    with pytest.raises(InputError, match=r"its header line has no x, y, z \(it has id, east"):
        to_laz(tmp_path / "c.csv", tmp_path / "bad.laz", columns=None) if False else to_laz(
            _text(tmp_path / "d.csv", "id,east,n,e,h\n1,0,10.5,20.25,3\n"), tmp_path / "bad.laz")
    to_laz(tmp_path / "c.csv", tmp_path / "c.laz")
    assert _ints(tmp_path / "c.laz")[0].tolist() == [[10500, 20250, 3000], [11000, 21000, 4000]]
    to_laz(_text(tmp_path / "o.txt", "1 0 10.5 20.25 3\n"), tmp_path / "o.laz", columns="id,skip,x,y,z")
    assert _ints(tmp_path / "o.laz")[0].tolist() == [[10500, 20250, 3000]]
    to_laz(_text(tmp_path / "p.pts", "2\n1 2 3 9 9 9 9\n4 5 6 9 9 9 9\n"), tmp_path / "p.laz")  # a PTS count line
    assert _ints(tmp_path / "p.laz")[0].tolist() == [[1000, 2000, 3000], [4000, 5000, 6000]]


def _text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_a_crs_option(tmp_path):
    assert parse_crs_option("EPSG:28356") == 28356 and parse_crs_option(" epsg:32755 ") == 32755
    assert parse_crs_option(None) is None
    for bad, words in (("28356x", "not of the form EPSG:NNNN"), ("EPSG:4326", "degrees"), ("EPSG:99999", "no such EPSG code")):
        with pytest.raises(ParameterError, match=words):
            parse_crs_option(bad)
    to_laz(_text(tmp_path / "a.xyz", "1 2 3\n"), tmp_path / "a.laz", crs_epsg=28356)
    assert laspy.read(tmp_path / "a.laz").header.parse_crs().to_epsg() == 28356


HOSTILE = {
    "ply-count": (b"ply\nformat binary_little_endian 1.0\nelement vertex 999999999999\nproperty float x\n"
                  b"property float y\nproperty float z\nend_header\n" + bytes(24), "claims 999999999999 vertex rows"),
    "ply-face-count": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
                       b"element face 4000000000\nproperty list uchar int vertex_indices\nend_header\n1 2 3\n", "face rows"),
    "ply-no-end": (b"ply\nformat ascii 1.0\nelement vertex 1\n" + b"comment " + b"a" * 200_000, "longer than 65536 bytes"),
    "ply-no-xyz": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n", "has no x, y, z"),
    "ply-truncated": (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                      b"end_header\n1 2 3\n4 5 6\n" + b" " * 40, "is a blank line"),
    "pcd-count": (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
                  b"POINTS 999999999999\nDATA binary\n" + bytes(12), "claims 999999999999 points"),
    "pcd-lzf-bomb": (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 300000000\nHEIGHT 1\n"
                     b"POINTS 300000000\nDATA binary_compressed\n" + (16).to_bytes(4, "little") + (3_600_000_000).to_bytes(4, "little")
                     + bytes(16), "unpacked whole"),
    "pcd-lzf-lie": (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
                    b"POINTS 2\nDATA binary_compressed\n" + (5000).to_bytes(4, "little") + (24).to_bytes(4, "little")
                    + bytes(16), "does not match"),
    "pcd-field-count": (b"VERSION 0.7\nFIELDS x y z i\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 177777777\nWIDTH 1\n"
                        b"HEIGHT 1\nPOINTS 1\nDATA binary\n" + bytes(16), "claims 177777780 values a point"),
    "pcd-bad-type": (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F Q\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
                     b"POINTS 1\nDATA binary\n" + bytes(12), "not a valid PCD header"),
    "e57-truncated": (None, "E57"),
    "text-long-line": (b"1 2 3\n" + b"4" * 100_000 + b"\n", "longer than 65536 bytes"),
    "text-words": (b"1 2 3\n4 five 6\n", "line 2 ('4 five 6'): x, y or z is not a number"),
    "text-two-columns": (b"1 2\n3 4\n", "has 2 column(s), not x y z"),
    "binary-junk": (b"\x00\x01\x02junk" * 10, "not a LAS, LAZ, PLY, PCD, E57 or text point file"),
    "empty": (b"", "empty"),
}


@pytest.fixture(scope="module")
def small_files(tmp_path_factory):
    """Small valid files of every format (seeds of the fuzz test)."""
    rng = np.random.default_rng(9)
    xyz = np.round(rng.uniform(0, 50, (40, 3)), 3)
    folder = tmp_path_factory.mktemp("seeds")
    files = {"ply-binary": write_ply(folder / "b.ply", xyz), "ply-ascii": write_ply(folder / "a.ply", xyz, text=True),
             "pcd-ascii": write_pcd(folder / "a.pcd", xyz, "ascii"), "pcd-binary": write_pcd(folder / "b.pcd", xyz, "binary"),
             "e57": write_e57(folder / "s.e57", xyz), "text": write_text(folder / "t.xyz", xyz)}
    z = np.zeros((64, 3))  # LZF shrinks only data that repeats
    files["pcd-binary_compressed"] = write_pcd(folder / "c.pcd", z, "binary_compressed")
    return {k: v.read_bytes() for k, v in files.items()}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_files_are_refused_with_one_line_before_allocating(case, tmp_path, small_files):
    data, words = HOSTILE[case]
    if data is None:
        data = small_files["e57"][: len(small_files["e57"]) // 2]
    src = tmp_path / f"h.{case.split('-')[0]}"
    src.write_bytes(data)
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as err:
            to_laz(src, tmp_path / "h.laz")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    message = str(err.value)
    assert words in message and "\n" not in message and message.startswith(src.name), message
    assert peak < 32 << 20, peak  # nothing sized by the header's claim was allocated
    assert not (tmp_path / "h.laz").exists()


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(kind=st.sampled_from(["ply-binary", "ply-ascii", "pcd-ascii", "pcd-binary", "pcd-binary_compressed", "e57", "text"]),
       edits=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255), st.sampled_from(["set", "cut", "insert"])),
                      min_size=1, max_size=4))
def test_mutated_files_are_read_or_refused_with_one_line(small_files, tmp_path, kind, edits):
    """Fuzz: byte mutations of small valid files of every format either convert or raise
    InputError (one line), in bounded memory, and leave no file behind on error."""
    data = bytearray(small_files[kind])
    for at, byte, how in edits:
        i = int(at * len(data))
        if how == "set":
            data[i] = byte
        elif how == "cut":
            del data[i:]
        else:
            data[i:i] = bytes([byte]) * 8
        if not data:
            break
    src = tmp_path / f"m.{kind.split('-')[0]}"
    src.write_bytes(bytes(data))
    dst = tmp_path / "m.laz"
    dst.unlink(missing_ok=True)
    tracemalloc.start()
    try:
        try:
            with _address_space_capped(1 << 30):
                to_laz(src, dst)
        except InputError as exc:
            assert "\n" not in str(exc) and str(exc).startswith(src.name)
            assert not dst.exists()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 << 20, peak


@contextlib.contextmanager
def _address_space_capped(more: int):
    """This process may map at most ``more`` bytes beyond what it maps now: a reader that
    allocates by a corrupt claim raises MemoryError here (the test fails with its
    example) instead of the kernel's OOM killer ending the test process (a COUNT of
    10^8 once took 23 GB)."""
    with open("/proc/self/status") as fh:
        now = next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmSize:"))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = now + more if hard == resource.RLIM_INFINITY else min(now + more, hard)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _pdal():
    from workers.tiler import pdal_available

    return pdal_available()


@pytest.mark.parametrize("kind", ["ply-binary", "ply-ascii", "pcd-ascii", "pcd-binary", "text-header", "e57"])
def test_pdals_readers_give_the_same_points(block, tmp_path, kind):
    """Where PDAL is installed, its readers are an alternative path to the same points."""
    if not _pdal():
        pytest.skip("PDAL's Python bindings are not installed")
    from pdal import libpdalpython

    if kind == "e57" and "readers.e57" not in {d["name"] for d in libpdalpython.getDrivers()}:
        pytest.skip("PDAL was built without its E57 plugin")
    to_laz(block["files"][kind], tmp_path / "p.laz", reader="pdal", chunk_points=7_000)
    got, ref = _ints(tmp_path / "p.laz"), _ints(block["laz"])
    assert got[1:] == ref[1:] and np.array_equal(got[0], ref[0])


def test_pdals_readers_without_pdal_are_a_clear_error(block, tmp_path):
    if _pdal():
        pytest.skip("PDAL is installed")
    with pytest.raises(ParameterError, match="import pdal failed"):
        to_laz(block["files"]["ply-binary"], tmp_path / "p.laz", reader="pdal")
