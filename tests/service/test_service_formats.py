"""PLY, PCD, E57 and text inputs at the service's edges: an upload is stored as the LAZ
its points make, an inbox takes them, and a hostile file is a 422 / a rejected capture
with one line."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from service_fixtures import tenant_inbox

from service.db.jobstore import Store
from service.schedules import run_schedule
from service.settings import Settings

XYZ = np.round(np.random.default_rng(5).uniform(0, 40, (3000, 3)), 3) + [500_000.0, 6_950_000.0, 100.0]


def _text(xyz=XYZ, header="x y z") -> bytes:
    lines = [header] + [f"{x:.3f} {y:.3f} {z:.3f}" for x, y, z in xyz]
    return ("\n".join(lines) + "\n").encode()


def test_an_uploaded_text_file_is_stored_as_laz_with_the_crs_given(client_a, api_data):
    r = client_a.post("/v1/blocks?crs=EPSG:28356", files={"file": ("row7.xyz", _text())})
    assert r.status_code == 201, r.text
    block = r.json()
    assert block["filename"] == "row7.xyz" and block["n_points"] == len(XYZ)
    stored = list((api_data / "blocks").glob("*.laz"))
    path = next(p for p in stored if laspy.open(p).header.point_count == len(XYZ))
    las = laspy.read(path)
    assert las.header.parse_crs().to_epsg() == 28356
    assert np.allclose(np.column_stack([las.x, las.y, las.z]), XYZ, atol=5e-4)
    again = client_a.post("/v1/blocks?crs=EPSG:28356", files={"file": ("same.xyz", _text())})
    assert again.status_code == 200 and again.json()["id"] == block["id"]  # the same bytes: the same block


@pytest.mark.parametrize("name,data,query,words", [
    ("bad.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
                b"POINTS 999999999\nDATA binary\n" + bytes(12), "", "bad.pcd: the PCD header claims 999999999 points"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float a\nend_header\n1\n2\n", "", "bad.ply: the PLY vertex element has no x"),
    ("cols.xyz", b"1 2 3\n", "?columns=a,b,c", "cols.xyz: --columns has no x, y, z"),
    ("x.xyz", b"1 2 3\n", "?crs=EPSG:4326", "crs: CRS 'EPSG:4326'"),
    ("junk.bin", b"\x00\x01junk" * 20, "", "not a LAS, LAZ, PLY, PCD, E57 or text point file"),
])
def test_hostile_uploads_are_refused_with_one_line(client_a, name, data, query, words):
    r = client_a.post(f"/v1/blocks{query}", files={"file": (name, data)})
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert words in detail and "\n" not in detail and "upload-" not in detail, detail
    assert name not in [b["filename"] for b in client_a.get("/v1/blocks").json()]


@pytest.fixture()
def local(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", capture_settle_s=0)
    store = Store(settings.store_path)
    tenant = store.accounts.ensure_tenant("farm")
    inbox = tenant_inbox(settings.data_dir, "farm")
    yield settings, store, tenant, inbox
    store.close()


def test_an_inbox_takes_the_formats_and_rejects_a_hostile_one(local):
    settings, store, tenant, inbox = local
    (inbox / "row1.xyz").write_bytes(_text())
    (inbox / "row2.pcd").write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\n"
                                     b"HEIGHT 1\nPOINTS 999999999\nDATA binary\n" + bytes(12))
    (inbox / "notes.txt").write_text("not a capture")
    sched = store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron="0 1 * * *", job={}, next_run_at=None)
    scan = run_schedule(store, settings, sched)
    assert len(scan["jobs"]) == 1
    assert len(scan["rejected"]) == 1 and "row2.pcd: the PCD header claims 999999999 points" in str(scan["rejected"][0])
    block = store.blocks.list(tenant["id"])[0]
    assert block["filename"] == "row1.xyz" and Path(block["path"]).suffix == ".laz"
    assert laspy.open(block["path"]).header.point_count == len(XYZ)
    assert run_schedule(store, settings, sched)["jobs"] == []  # taken once
