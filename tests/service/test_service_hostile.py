"""Hostile LAS/LAZ headers uploaded to a real `orchard serve` on loopback: every one is
answered 4xx at once, the server's memory holds, it stays healthy, nothing is a 5xx."""

from __future__ import annotations

import struct
from pathlib import Path

import httpx
import laspy
import numpy as np
import psutil
import pyproj
import pytest
from service_fixtures import ServerProcess, make_token

from pipeline import lasheader

#: growth of the server's memory (its processes' resident set) allowed over the run [bytes]
RSS_GROWTH = 100 << 20
#: a request not answered within this is a hang [s]
ANSWER_S = 10.0


def _block(path: Path, *, version="1.4", fmt=6, n=3000, evlr=True) -> Path:
    header = laspy.LasHeader(version=version, point_format=fmt)
    header.scales, header.offsets = [0.001] * 3, [500_000.0, 6_000_000.0, 0.0]
    header.vlrs.append(laspy.VLR(user_id="orchard-test", record_id=7, description="padding", record_data=b"x" * 40))
    las = laspy.LasData(header)
    xyz = np.random.default_rng(0).uniform(0, 10, (n, 3)) + [500_000.0, 6_000_000.0, 0.0]
    las.x, las.y, las.z = xyz.T
    if evlr:
        las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.vlrs.known.WktCoordinateSystemVlr(pyproj.CRS.from_epsg(32633).to_wkt())])
        las.header.global_encoding.wkt = True
    las.write(path)
    return path


def _patched(data: bytes, *edits) -> bytes:
    out = bytearray(data)
    for offset, fmt, value in edits:
        struct.pack_into("<" + fmt, out, offset, value)
    return bytes(out)


def _hostile(root: Path) -> dict[str, bytes]:
    """Crafted headers, each of which read_info must refuse."""
    las = _block(root / "base.las").read_bytes()
    laz = _block(root / "base.laz").read_bytes()
    old = _block(root / "old.las", version="1.2", fmt=3, evlr=False).read_bytes()
    las_l, laz_l = lasheader.check_header(root / "base.las"), lasheader.check_header(root / "base.laz")
    start = laz_l.offset_to_point_data
    table = struct.unpack_from("<q", laz, start)[0]
    laszip = next(r for r in laz_l.vlrs if r.user_id == lasheader.LASZIP_USER_ID)
    thirty_kb = _patched(old, (100, "I", 2**31))[:30_000]
    return {
        "vlrs-2^31.las": _patched(old, (100, "I", 2**31)),
        "vlrs-2^31-30kb.las": _patched(thirty_kb, (107, "I", 800)),
        "vlrs-200000-past-eof.las": _patched(old, (96, "I", len(old)), (100, "I", 200_000)),
        "evlrs-2^31.las": _patched(las, (243, "I", 2**31)),
        "evlrs-2^31.laz": _patched(laz, (243, "I", 2**31)),
        "header-size-65535.las": _patched(las, (94, "H", 65_535)),
        "header-size-227-for-1.4.las": _patched(las, (94, "H", 227)),
        "point-data-past-eof.las": _patched(las, (96, "I", 2**32 - 1)),
        "vlr-length-past-eof.las": _patched(las, (375 + 20, "H", 65_535)),
        "evlr-start-past-eof.las": _patched(las, (235, "Q", 2**40)),
        "evlr-length-past-eof.laz": _patched(laz, (laz_l.evlrs[0].start + 20, "Q", 2**63)),
        "point-count-forged.las": _patched(las, (247, "Q", 2**40)),
        "legacy-count-differs.las": _patched(las, (107, "I", 7)),
        "point-count-forged.laz": _patched(laz, (247, "Q", 10**12)),
        "record-length-short.las": _patched(las, (105, "H", 20)),
        "point-format-255.las": _patched(las, (104, "B", 255)),
        "las-marked-compressed.las": _patched(old, (104, "B", 0x83)),
        "chunk-count-2^31.laz": _patched(laz, (table + 4, "I", 2**31)),
        "chunk-count-2^31-at-eof.laz": _patched(laz, (start, "q", -1)) + struct.pack("<IIq", 0, 2**31, len(laz)),
        "chunk-table-past-eof.laz": _patched(laz, (start, "q", 2**40)),
        "chunk-table-offset-0.laz": _patched(laz, (start, "q", 0)),
        "chunk-size-0.laz": _patched(laz, (laszip.start + lasheader.VLR_HEADER_SIZE + 12, "I", 0)),
        "laszip-no-items.laz": _patched(laz, (laszip.start + lasheader.VLR_HEADER_SIZE + 32, "H", 0)),
        "evlr-start-inside-points.las": _patched(las, (235, "Q", las_l.offset_to_point_data + 5)),
    }


def _rss(pid: int) -> int:
    proc = psutil.Process(pid)
    return sum(p.memory_info().rss for p in [proc, *proc.children(recursive=True)])


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    srv = ServerProcess(root / "data", ORCHARD_RUNNER="false", ORCHARD_SCHEDULING="false")
    srv.start()
    try:
        yield srv, make_token(srv.data_dir, "farm"), root
    finally:
        srv.stop()


@pytest.mark.slow
def test_hostile_headers_are_answered_4xx_and_the_server_holds(server, capsys):
    srv, token, root = server
    files = _hostile(root)
    counts = {"files": len(files), "requests": 0, "5xx": 0}
    with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=ANSWER_S) as c:
        valid = _block(root / "valid.laz", n=2000)
        assert c.post("/v1/blocks", files={"file": ("valid.laz", valid.read_bytes())}).status_code == 201  # warm
        before = _rss(srv.proc.pid)
        answers = {}
        for _ in range(3):  # each file three times: nothing may accumulate
            for name, data in files.items():
                r = c.post("/v1/blocks", files={"file": (name, data)})  # a hang fails here (ANSWER_S)
                counts["requests"] += 1
                counts["5xx"] += r.status_code >= 500
                answers[name] = (r.status_code, r.json().get("detail", ""))
        growth = _rss(srv.proc.pid) - before
        assert c.get("/healthz").status_code == 200
        assert [b["filename"] for b in c.get("/v1/blocks").json()] == ["valid.laz"]  # none was taken
    with capsys.disabled():
        print(f"\nhostile uploads: {counts['files']} files, {counts['requests']} requests, {counts['5xx']} 5xx, "
              f"server memory {growth / 2**20:+.1f} MB")
    wrong = {name: a for name, a in answers.items() if a[0] != 422 or name not in str(a[1])}
    assert not wrong
    assert counts["5xx"] == 0
    assert growth < RSS_GROWTH
