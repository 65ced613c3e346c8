"""Hostile LAS/LAZ headers: every size, count and offset is checked before laspy or lazrs
walks it, valid files still pass, and a fuzz over every header field finds nothing that
hangs, grows or escapes as anything but an InputError."""

from __future__ import annotations

import struct
import tracemalloc
from datetime import timedelta
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline import lasheader
from pipeline.blockinfo import read_info
from pipeline.errors import InputError
from pipeline.reading import read_points

EASTING, NORTHING = 512_345.0, 6_234_567.0
REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real"
REAL_BLOCKS = sorted(REAL.glob("*/*.la[sz]"))
#: tracemalloc peak allowed for reading one header [bytes]
PEAK_BYTES = 50 << 20


def _block(path: Path, *, version="1.4", fmt=6, n=300, evlr=False, minor=None, seed=0) -> Path:
    """A small valid block with one custom VLR (and a WKT EVLR if ``evlr``), written by laspy;
    ``minor`` rewrites the version's minor byte afterwards (laspy cannot write 1.0/1.1)."""
    header = laspy.LasHeader(version=version, point_format=fmt)
    header.scales, header.offsets = [0.001] * 3, [EASTING, NORTHING, 0.0]
    header.vlrs.append(laspy.VLR(user_id="orchard-test", record_id=7, description="padding", record_data=b"x" * 40))
    las = laspy.LasData(header)
    xyz = np.random.default_rng(seed).uniform(0, 20, (n, 3)) + [EASTING, NORTHING, 100.0]
    las.x, las.y, las.z = xyz.T
    if evlr:
        wkt = pyproj.CRS.from_epsg(32633).to_wkt()
        las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.vlrs.known.WktCoordinateSystemVlr(wkt)])
        las.header.global_encoding.wkt = True
    las.write(path)
    if minor is not None:
        _patch(path, 25, "B", minor)
    return path


def _patch(path: Path, offset: int, fmt: str, *values) -> Path:
    data = bytearray(path.read_bytes())
    struct.pack_into("<" + fmt, data, offset, *values)
    path.write_bytes(bytes(data))
    return path


def _refused(path: Path) -> str:
    """read_info's one-line message for ``path``, which it must refuse with little memory."""
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as e:
            read_info(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < PEAK_BYTES
    msg = str(e.value)
    assert "\n" not in msg and len(msg) < 300 and msg.startswith(path.name + ": ")
    return msg


# -- hostile headers, one field at a time -----------------------------------------------------


def test_two_to_the_31_vlrs(tmp_path):
    path = _patch(_block(tmp_path / "b.las", version="1.2", fmt=3), 100, "I", 2**31)
    assert "corrupt header: it claims 2,147,483,648 VLRs but only 1 fit before the point data" in _refused(path)


def test_200_000_vlrs_past_the_end_of_the_file(tmp_path):
    path = _block(tmp_path / "b.las", version="1.2", fmt=0, n=10)
    _patch(path, 96, "I", path.stat().st_size)  # the point data "starts" at the end: room for a few VLRs only
    _patch(path, 100, "I", 200_000)
    assert "it claims 200,000 VLRs but only" in _refused(path)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_two_to_the_31_evlrs(tmp_path, suffix):
    path = _block(tmp_path / f"b{suffix}", evlr=True)
    _patch(path, 243, "I", 2**31)
    assert "it claims 2,147,483,648 EVLRs but only" in _refused(path)


def test_a_header_size_of_65535(tmp_path):
    path = _patch(_block(tmp_path / "b.las"), 94, "H", 65_535)
    assert "corrupt header: its point data starts at byte" in _refused(path)
    assert "inside its 65535-byte header" in _refused(path)


def test_a_header_size_below_its_version(tmp_path):
    path = _patch(_block(tmp_path / "b.las"), 94, "H", 227)  # a LAS 1.4 header is 375 bytes
    assert "header size 227 is below the 375 bytes of a LAS 1.4 header" in _refused(path)


def test_point_data_past_the_end_of_the_file(tmp_path):
    path = _block(tmp_path / "b.las")
    _patch(path, 96, "I", 2**32 - 1)
    assert "its point data starts at byte 4,294,967,295, beyond the end of the file" in _refused(path)


def test_a_vlr_longer_than_the_file(tmp_path):
    path = _block(tmp_path / "b.las")
    _patch(path, 375 + 20, "H", 65_535)  # the first VLR's record length
    assert "VLR 1 of 1 (record length 65,535 bytes) runs past the start of the point data" in _refused(path)


def test_evlrs_starting_past_the_end_of_the_file(tmp_path):
    path = _block(tmp_path / "b.las", evlr=True)
    _patch(path, 235, "Q", 2**40)
    assert "its EVLRs start at byte 1,099,511,627,776, beyond the end of the file" in _refused(path)


def test_an_evlr_longer_than_the_file(tmp_path):
    path = _block(tmp_path / "b.las", evlr=True)
    start = lasheader.check_header(path).evlrs[0].start
    _patch(path, start + 20, "Q", 2**63)
    assert "EVLR 1 of 1 (record length 9,223,372,036,854,775,808 bytes) runs past the end of the file" in _refused(path)


@pytest.mark.parametrize("version, offset, fmt", [("1.2", 107, "I"), ("1.4", 247, "Q")])
def test_a_forged_point_count_of_a_las_file(tmp_path, version, offset, fmt):
    path = _block(tmp_path / "b.las", version=version, fmt=1)
    if version == "1.4":
        _patch(path, 107, "I", 0)  # the legacy count left at 0, as the 64-bit one rules
    _patch(path, offset, fmt, 2**32 - 1)
    assert "truncated: the header announces 4,294,967,295 points but the file holds only 300" in _refused(path)


def test_legacy_and_64_bit_point_counts_that_differ(tmp_path):
    path = _patch(_block(tmp_path / "b.las", fmt=1), 107, "I", 299)
    assert "its legacy point count 299 differs from its point count 300" in _refused(path)


def test_a_point_record_shorter_than_its_format(tmp_path):
    path = _patch(_block(tmp_path / "b.las", fmt=7), 105, "H", 30)
    assert "point record length 30 is below the 36 bytes of point format 7" in _refused(path)


@pytest.mark.parametrize("raw", [11, 0x46, 0xC6, 255])
def test_an_unknown_point_format(tmp_path, raw):
    path = _patch(_block(tmp_path / "b.las"), 104, "B", raw)
    assert f"unsupported point format {raw}" in _refused(path)


def test_a_las_file_marked_compressed(tmp_path):
    path = _patch(_block(tmp_path / "b.las", version="1.2", fmt=1), 104, "B", 0x81)
    assert "its point format says LAZ (compressed) but it has no LASzip record" in _refused(path)


def _chunk_table(path: Path) -> int:
    start = lasheader.check_header(path).offset_to_point_data
    return struct.unpack_from("<q", path.read_bytes(), start)[0]


@pytest.mark.parametrize("count", [2**31, 2**32 - 1, 3])
def test_a_forged_laz_chunk_count(tmp_path, count):
    # lazrs allocates what the count claims (2^31 chunks: 32 GB) and aborts the process
    path = _block(tmp_path / "b.laz", n=3000)
    _patch(path, _chunk_table(path) + 4, "I", count)
    assert f"its LAZ chunk table claims {count:,} chunks but at most 2 fit" in _refused(path)


def test_a_forged_laz_chunk_count_found_through_the_last_8_bytes(tmp_path):
    # a chunk-table offset of -1 sends lazrs to the file's last 8 bytes for it
    path = _block(tmp_path / "b.laz", n=3000)
    _patch(path, lasheader.check_header(path).offset_to_point_data, "q", -1)
    data = path.read_bytes()
    path.write_bytes(data + struct.pack("<IIq", 0, 2**31, len(data)))  # a table of 2^31 chunks, then its offset
    assert "its LAZ chunk table claims 2,147,483,648 chunks" in _refused(path)


@pytest.mark.parametrize(
    "where, words",
    [(2**40, "truncated: the LAZ chunk table lies beyond the end of the file"),
     (0, "its LAZ chunk table offset 0 lies before its compressed data"),
     (-5, "its LAZ chunk table offset -5 lies before its compressed data")],
)
def test_a_forged_laz_chunk_table_offset(tmp_path, where, words):
    path = _block(tmp_path / "b.laz", version="1.2", fmt=3)
    _patch(path, lasheader.check_header(path).offset_to_point_data, "q", where)
    assert words in _refused(path)


def test_a_laz_whose_chunk_table_offset_is_in_its_last_8_bytes(tmp_path):
    # what a LAZ writer that could not seek back leaves: -1 first, the offset at the end
    path = _block(tmp_path / "b.laz", version="1.2", fmt=1, n=3000)
    expected, _ = read_points(path)
    start, table = lasheader.check_header(path).offset_to_point_data, _chunk_table(path)
    _patch(path, start, "q", -1)
    path.write_bytes(path.read_bytes() + struct.pack("<q", table))
    assert lasheader.check_header(path).chunk_table == table
    points, info = read_points(path)
    assert info.n_points == 3000 and np.array_equal(points, expected)


def test_laz_chunks_larger_than_the_compressed_data(tmp_path):
    # lazrs allocates a chunk's byte count as it reads it: 100 bytes cut out of the only
    # chunk, the table moved up to match, and the table still says the chunk is whole
    path = _block(tmp_path / "b.laz", version="1.2", fmt=3, n=3000)
    start, table = lasheader.check_header(path).offset_to_point_data, _chunk_table(path)
    data = path.read_bytes()
    path.write_bytes(data[: table - 100] + data[table:])
    _patch(path, start, "q", table - 100)
    assert f"its LAZ chunk table gives {table - start - 8:,} bytes of chunks but its compressed data holds " \
           f"{table - start - 108:,}" in _refused(path)


@pytest.mark.parametrize("field, value, words", [
    (32, 0, "its LASzip record's 0 items take 0 bytes a point, but its point records take 30"),  # lazrs panicked
    (34 + 2, 31, "its LASzip record's 1 items take 31 bytes a point, but its point records take 30"),
])
def test_laszip_items_that_do_not_make_up_a_point(tmp_path, field, value, words):
    path = _block(tmp_path / "b.laz", fmt=6)
    rec = next(r for r in lasheader.check_header(path).vlrs if r.user_id == lasheader.LASZIP_USER_ID)
    _patch(path, rec.start + lasheader.VLR_HEADER_SIZE + field, "H", value)
    assert words in _refused(path)


def test_a_laz_chunk_size_of_zero(tmp_path):
    path = _block(tmp_path / "b.laz")
    rec = next(r for r in lasheader.check_header(path).vlrs if r.user_id == lasheader.LASZIP_USER_ID)
    _patch(path, rec.start + lasheader.VLR_HEADER_SIZE + 12, "I", 0)
    assert "its LASzip record gives a chunk size of 0 points" in _refused(path)


# -- valid files still pass ------------------------------------------------------------------

VALID = [("1.2", 0, ".las", None), ("1.2", 1, ".laz", 0), ("1.2", 1, ".las", 1), ("1.2", 3, ".laz", None),
         ("1.3", 2, ".las", None), ("1.3", 5, ".laz", None), ("1.4", 6, ".las", None), ("1.4", 7, ".laz", None),
         ("1.4", 8, ".las", None), ("1.4", 10, ".laz", None)]


@pytest.mark.parametrize("version, fmt, suffix, minor, evlr",
                         [v + (False,) for v in VALID] + [v + (True,) for v in VALID if v[0] == "1.4"])
def test_valid_blocks_pass_and_agree_with_laspy(tmp_path, version, fmt, suffix, minor, evlr):
    path = _block(tmp_path / f"b{suffix}", version=version, fmt=fmt, minor=minor, evlr=evlr)
    layout = lasheader.check_header(path)
    header = laspy.open(path).header
    assert layout.version == (f"1.{minor}" if minor is not None else version)
    assert (layout.point_format, layout.compressed, layout.point_count) == (fmt, suffix == ".laz", 300)
    assert layout.offset_to_point_data == header.offset_to_point_data
    assert [(r.user_id, r.record_id) for r in layout.vlrs] == [(v.user_id, v.record_id) for v in header.vlrs]
    assert len(layout.evlrs) == int(evlr)
    info = read_info(path)
    assert info.n_points == 300
    assert (info.crs_wkt is not None) == evlr  # the CRS is still found in its EVLR


@pytest.mark.skipif(not REAL_BLOCKS, reason=f"no real LAS/LAZ blocks in {REAL}")
@pytest.mark.parametrize("path", REAL_BLOCKS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_real_blocks_pass(path):
    layout = lasheader.check_header(path)
    with laspy.open(path) as reader:
        assert layout.point_count == reader.header.point_count > 0
    assert read_info(path).n_points == layout.point_count


def test_the_check_reads_a_bounded_number_of_bytes(tmp_path, monkeypatch):
    # the header, the VLR and EVLR headers, the LASzip record and the chunk table's first
    # bytes: not the points, however many there are
    path = _block(tmp_path / "big.laz", n=200_000, evlr=True)
    read = []

    class Counting:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def seek(self, *a):
            return self.f.seek(*a)

        def read(self, n=-1):
            assert n >= 0  # never "the rest of the file"
            data = self.f.read(n)
            read.append(len(data))
            return data

    monkeypatch.setattr(lasheader, "open", lambda p, mode: Counting(open(p, mode)), raising=False)
    lasheader.check_header(path)
    assert sum(read) < 4096 < path.stat().st_size


# -- fuzz: every field of the header, the VLRs, the EVLRs and the LAZ chunk table ------------

_HEADER = [(4, "H"), (6, "H"), (24, "B"), (25, "B"), (94, "H"), (96, "I"), (100, "I"), (104, "B"), (105, "H"),
           (107, "I")] + [(111 + 4 * i, "I") for i in range(5)] + [(131 + 8 * i, "d") for i in range(12)]
_HEADER_13 = [(227, "Q")]
_HEADER_14 = [(235, "Q"), (243, "I"), (247, "Q")] + [(255 + 8 * i, "Q") for i in range(15)]
_VLR = [(0, "H"), (2, "16s"), (18, "H"), (20, "H")]
_EVLR = [(0, "H"), (2, "16s"), (18, "H"), (20, "Q")]
_LASZIP = [(0, "H"), (2, "H"), (8, "I"), (12, "I"), (16, "q"), (24, "q"), (32, "H"), (34, "H"), (36, "H")]
_USER_IDS = [b"LASF_Projection", b"LASF_Spec", b"laszip encoded", b"copc", b"\xff" * 16, b""]
_BASES = [("1.2", 0, ".las", 0), ("1.2", 1, ".laz", 1), ("1.2", 3, ".las", None), ("1.3", 5, ".laz", None),
          ("1.4", 6, ".las", "evlr"), ("1.4", 7, ".laz", "evlr"), ("1.4", 10, ".laz", None)]


@pytest.fixture(scope="module")
def bases(tmp_path_factory):
    """The valid blocks the fuzz mutates: bytes and the offsets of their fields."""
    root = tmp_path_factory.mktemp("bases")
    out = []
    for i, (version, fmt, suffix, extra) in enumerate(_BASES):
        minor = extra if isinstance(extra, int) else None
        path = _block(root / f"b{i}{suffix}", version=version, fmt=fmt, n=400, evlr=extra == "evlr", minor=minor, seed=i)
        layout = lasheader.check_header(path)
        fields = list(_HEADER) + (_HEADER_13 if int(layout.version[2]) >= 3 else []) + (
            _HEADER_14 if layout.version == "1.4" else [])
        fields += [(r.start + at, fmt) for r in layout.vlrs for at, fmt in _VLR]
        fields += [(r.start + at, fmt) for r in layout.evlrs for at, fmt in _EVLR]
        if layout.compressed:
            data = path.read_bytes()
            laz = next(r for r in layout.vlrs if r.user_id == lasheader.LASZIP_USER_ID)
            fields += [(laz.start + lasheader.VLR_HEADER_SIZE + at, fmt) for at, fmt in _LASZIP]
            table = struct.unpack_from("<q", data, layout.offset_to_point_data)[0]
            fields += [(layout.offset_to_point_data, "q"), (table, "I"), (table + 4, "I"), (len(data) - 8, "q")]
        out.append((path.read_bytes(), fields))
    return out


_LIMITS = {"B": 2**8, "H": 2**16, "I": 2**32, "Q": 2**64, "q": 2**64}


def _value(fmt: str, draw, data: bytes, at: int):
    """A hostile value for a field: a boundary, a size of the file give or take, the
    field's own value give or take, or anything."""
    if fmt == "16s":
        return draw(st.sampled_from(_USER_IDS) | st.binary(min_size=16, max_size=16))
    if fmt == "d":
        return draw(st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([0.0, -0.001, 1e-300, 1e300]))
    limit = _LIMITS[fmt]
    own = struct.unpack_from("<" + fmt, data, at)[0] if at + struct.calcsize(fmt) <= len(data) else 0
    near = st.integers(-70, 70)
    value = draw(st.one_of(
        st.sampled_from([0, 1, 2, limit - 1, limit // 2, limit // 2 - 1, 2**31, 54, 60, 227, 375]),
        near.map(lambda d: len(data) + d),
        near.map(lambda d: own + d),
        st.integers(0, limit - 1),
    ))
    value %= limit
    return value - limit if fmt == "q" and value >= limit // 2 else value


@st.composite
def _mutants(draw, bases):
    data, fields = draw(st.sampled_from(bases))
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 3))):
        at, fmt = draw(st.sampled_from(fields))
        if at + struct.calcsize(fmt) <= len(out):
            struct.pack_into("<" + fmt, out, at, _value(fmt, draw, data, at))
    if draw(st.integers(0, 9)) == 9:  # now and then the file is cut short too (hypothesis favours 0)
        out = out[: draw(st.integers(len(out) // 2, len(out)) | st.integers(0, 400))]
    return bytes(out)


def _fuzz_one(tmp_dir: Path, blob: bytes) -> None:
    path = tmp_dir / "fuzz.laz"
    path.write_bytes(blob)
    tracemalloc.start()
    try:
        try:
            info = read_info(path)
        except InputError as exc:
            msg = str(exc)
            assert "\n" not in msg and msg.startswith("fuzz.laz: "), msg
        else:
            assert info.n_points > 0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < PEAK_BYTES


def _fuzz(bases, tmp_dir: Path, n: int):
    @settings(max_examples=n, deadline=timedelta(seconds=5), derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(st.data())
    def run(data):
        _fuzz_one(tmp_dir, data.draw(_mutants(bases)))

    run()


def test_fuzz_every_header_field(bases, tmp_path):
    # read_info returns or raises InputError, within the per-example deadline and 50 MB
    _fuzz(bases, tmp_path, 300)


@pytest.mark.slow
def test_fuzz_every_header_field_at_length(bases, tmp_path):
    _fuzz(bases, tmp_path, 1000)
