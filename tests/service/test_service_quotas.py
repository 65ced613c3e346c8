"""Per-tenant quotas over HTTP and in inbox scans, and inbox scans that do not wait for
another tenant's: a farm over its quota gets a clear 4xx/507 and nothing is stored, the
others are not affected."""

from __future__ import annotations

import threading

import pytest
from fastapi.testclient import TestClient
from service_fixtures import make_token, temp_files, write_las

from service import schedules
from service.app import create_app
from service.db.jobstore import Store
from service.schedules import run_schedule, scan_lock
from service.settings import Settings


@pytest.fixture()
def api(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", runner=False, scheduling=False)
    tokens = {name: make_token(settings.data_dir, name) for name in ("farm-a", "farm-b")}
    with TestClient(create_app(settings)) as client:
        store = client.app.state.store
        tenants = {name: store.accounts.tenant_by_name(name) for name in tokens}

        def as_(name):
            return {"Authorization": f"Bearer {tokens[name]}"}

        yield settings, client, store, tenants, as_


def _stored_files(settings):
    return sorted(p.name for p in settings.blocks_dir.glob("*") if p.is_file())


@pytest.mark.parametrize("room", [0, -1], ids=["nothing left: refused before the body", "one byte short: refused once received"])
def test_an_upload_over_the_storage_quota_is_507_and_keeps_nothing(api, tmp_path, room):
    settings, c, store, tenants, as_ = api
    data = write_las(tmp_path / "b.laz", 3000, seed=3).read_bytes()
    store.quotas.set_limits(tenants["farm-a"]["id"], storage_bytes=0 if room == 0 else len(data) + room)
    r = c.post("/v1/blocks", files={"file": ("b.laz", data)}, headers=as_("farm-a"))
    assert r.status_code == 507, r.text
    detail = r.json()["detail"]
    assert "'farm-a' is at its storage quota" in detail and "nothing of it was kept" in detail
    assert "Traceback" not in r.text
    assert c.get("/v1/blocks", headers=as_("farm-a")).json() == []
    assert _stored_files(settings) == [] and temp_files(settings.data_dir) == []
    # another farm uploads the same file as before
    assert c.post("/v1/blocks", files={"file": ("b.laz", data)}, headers=as_("farm-b")).status_code == 201
    # with the quota raised the farm's upload goes through
    store.quotas.set_limits(tenants["farm-a"]["id"], storage_bytes=len(data))
    assert c.post("/v1/blocks", files={"file": ("b.laz", data)}, headers=as_("farm-a")).status_code == 201


def test_a_job_past_the_queue_quota_is_429_and_queues_nothing(api, tmp_path):
    settings, c, store, tenants, as_ = api
    data = write_las(tmp_path / "b.laz", 3000, seed=4).read_bytes()
    blocks = {f: c.post("/v1/blocks", files={"file": ("b.laz", data)}, headers=as_(f)).json()["id"] for f in tenants}
    store.quotas.set_limits(tenants["farm-a"]["id"], queued_jobs=1)
    first = c.post("/v1/jobs", json={"block_id": blocks["farm-a"]}, headers=as_("farm-a"))
    assert first.status_code == 201
    r = c.post("/v1/jobs", json={"block_id": blocks["farm-a"]}, headers=as_("farm-a"))
    assert r.status_code == 429, r.text
    assert r.json()["detail"] == ("tenant 'farm-a' has 1 job(s) queued, its limit of 1; wait until some have started "
                                  "(or cancel some) before queuing more")
    assert c.get("/v1/jobs", headers=as_("farm-a")).json()["total"] == 1
    for _ in range(3):  # the other farm is not limited
        assert c.post("/v1/jobs", json={"block_id": blocks["farm-b"]}, headers=as_("farm-b")).status_code == 201
    c.delete(f"/v1/jobs/{first.json()['id']}", headers=as_("farm-a"))  # a cancelled job makes room
    assert c.post("/v1/jobs", json={"block_id": blocks["farm-a"]}, headers=as_("farm-a")).status_code == 201


def test_quota_answers_are_in_the_api_document(api):
    _, c, *_ = api
    doc = c.get("/openapi.json").json()
    assert "429" in doc["paths"]["/v1/jobs"]["post"]["responses"]
    assert "507" in doc["paths"]["/v1/blocks"]["post"]["responses"]


def test_the_command_line_sets_quotas_that_a_running_service_applies(api, tmp_path, capsys):
    from service.cli import main

    settings, c, store, tenants, as_ = api
    assert main(["tenants", "quota", "farm-a", "--storage-gb", "0", "--max-queued", "5",
                 "--data-dir", str(settings.data_dir)]) == 0
    assert capsys.readouterr().out == "farm-a\tstorage 0.00 GB of 0.00 GB\tqueued jobs 0 of 5\n"
    data = write_las(tmp_path / "b.laz", 3000, seed=5).read_bytes()
    assert c.post("/v1/blocks", files={"file": ("b.laz", data)}, headers=as_("farm-a")).status_code == 507
    assert main(["tenants", "quota", "farm-a", "--storage-gb", "none", "--data-dir", str(settings.data_dir)]) == 0
    assert c.post("/v1/blocks", files={"file": ("b.laz", data)}, headers=as_("farm-a")).status_code == 201
    capsys.readouterr()
    assert main(["tenants", "list", "--data-dir", str(settings.data_dir)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("farm-a\tstorage 0.00 GB of unlimited\tqueued jobs 0 of 5")
    assert lines[1] == "farm-b\tstorage 0.00 GB of unlimited\tqueued jobs 0 of unlimited"
    assert main(["tenants", "quota", "nobody", "--max-queued", "1", "--data-dir", str(settings.data_dir)]) == 3


# -- inbox scans -----------------------------------------------------------------------


@pytest.fixture()
def farms(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", capture_settle_s=0)
    store = Store(settings.store_path)
    out = {}
    for name in ("farm-a", "farm-b"):
        tenant = store.accounts.ensure_tenant(name)
        inbox = tmp_path / name
        inbox.mkdir()
        sched = store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron="0 1 * * *", job={}, next_run_at=None)
        out[name] = (tenant, inbox, sched)
    yield settings, store, out
    store.close()


def test_a_file_without_the_las_signature_is_refused_without_a_copy(farms, monkeypatch):
    settings, store, out = farms
    _, inbox, sched = out["farm-a"]
    (inbox / "movie.laz").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(100_000))
    write_las(inbox / "real.laz", 500, seed=1)
    copied = []
    real = schedules._copy_hashed
    monkeypatch.setattr(schedules, "_copy_hashed", lambda src, dst: copied.append(src.name) or real(src, dst))
    res = run_schedule(store, settings, sched)
    assert copied == ["real.laz"] and len(res["jobs"]) == 1
    assert res["rejected"] == [{"file": "movie.laz", "error": "movie.laz: not a LAS or LAZ file (it does not begin "
                                                                "with the LAS signature 'LASF')"}]
    again = run_schedule(store, settings, sched)  # refused once, as any unusable capture
    assert again["rejected"] == [] and again["skipped"] == 2


def test_a_file_with_a_broken_header_is_refused_without_a_copy(farms, monkeypatch):
    settings, store, out = farms
    _, inbox, sched = out["farm-a"]
    (inbox / "junk.las").write_bytes(b"LASF" + bytes(100_000))  # the signature, then nothing of a header
    monkeypatch.setattr(schedules, "_copy_hashed", lambda src, dst: pytest.fail(f"{src.name} was copied"))
    (rej,) = run_schedule(store, settings, sched)["rejected"]
    assert rej["file"] == "junk.las" and rej["error"].startswith("junk.las: ") and "LAS version 0.0" in rej["error"]
    assert str(inbox) not in rej["error"]  # the farm sees its file's name, not the server's path


def test_a_capture_over_the_storage_quota_waits_for_room_without_a_copy(farms, monkeypatch):
    settings, store, out = farms
    tenant, inbox, sched = out["farm-a"]
    size = write_las(inbox / "a.laz", 2000, seed=2).stat().st_size
    store.quotas.set_limits(tenant["id"], storage_bytes=size - 1)
    copied = []
    real = schedules._copy_hashed
    monkeypatch.setattr(schedules, "_copy_hashed", lambda src, dst: copied.append(src.name) or real(src, dst))
    res = run_schedule(store, settings, sched)
    assert res["jobs"] == [] and copied == [] and _stored_files(settings) == []
    (rej,) = res["rejected"]
    assert "'farm-a' is at its storage quota" in rej["error"] and rej["error"].endswith("tried again at the next scan")
    store.quotas.set_limits(tenant["id"], storage_bytes=size)  # not recorded as handled: taken once there is room
    assert len(run_schedule(store, settings, sched)["jobs"]) == 1


def test_captures_past_the_queue_quota_are_taken_at_a_later_scan(farms):
    settings, store, out = farms
    tenant, inbox, sched = out["farm-a"]
    for i in range(3):
        write_las(inbox / f"c{i}.laz", 500, seed=10 + i)
    store.quotas.set_limits(tenant["id"], queued_jobs=2)
    first = run_schedule(store, settings, sched)
    assert len(first["jobs"]) == 2 and [r["file"] for r in first["rejected"]] == ["c2.laz"]
    assert "has 2 job(s) queued, its limit of 2" in first["rejected"][0]["error"]
    assert run_schedule(store, settings, sched)["rejected"][0]["file"] == "c2.laz"  # still full
    store.jobs.claim_next()  # one starts: room for one more
    again = run_schedule(store, settings, sched)
    assert len(again["jobs"]) == 1 and again["rejected"] == [] and again["skipped"] == 2


def test_a_farms_scan_does_not_wait_for_another_farms_copy(farms, monkeypatch):
    # one lock for every tenant's scans: a farm waited 8.7 s behind another copying 2 GB
    settings, store, out = farms
    write_las(out["farm-a"][1] / "big.laz", 2000, seed=3)
    write_las(out["farm-b"][1] / "small.laz", 500, seed=4)
    copying, release = threading.Event(), threading.Event()
    real = schedules._copy_hashed

    def slow_for_a(src, dst):
        if src.name == "big.laz":
            copying.set()
            assert release.wait(30)
        return real(src, dst)

    monkeypatch.setattr(schedules, "_copy_hashed", slow_for_a)
    results = {}
    a = threading.Thread(target=lambda: results.setdefault("a", run_schedule(store, settings, out["farm-a"][2])))
    a.start()
    try:
        assert copying.wait(30)
        assert scan_lock(out["farm-a"][0]["id"]).locked()  # farm a's own next scan would wait
        assert not scan_lock(out["farm-b"][0]["id"]).locked()
        results["b"] = run_schedule(store, settings, out["farm-b"][2])  # while a's copy is held up
        assert len(results["b"]["jobs"]) == 1 and "a" not in results
    finally:
        release.set()
        a.join(30)
    assert len(results["a"]["jobs"]) == 1


def test_a_block_refused_when_recorded_leaves_no_file(tmp_path, monkeypatch):
    # two uploads of a farm at once both pass the early check; the store's own check,
    # made when the block is recorded, refuses the second and its landed file goes
    from service.db.block_files import accept_block
    from service.db.tenant_quotas import TenantQuotas
    from service.quotas import StorageQuotaExceeded

    store = Store(tmp_path / "data" / "orchard.sqlite")
    tenant = store.accounts.ensure_tenant("farm")
    src = write_las(tmp_path / "b.laz", 2000, seed=6)
    store.quotas.set_limits(tenant["id"], storage_bytes=src.stat().st_size - 1)
    monkeypatch.setattr(TenantQuotas, "check_storage", lambda self, tenant_id, size: None)  # the race: passed meanwhile
    tmp = tmp_path / "upload.part"
    tmp.write_bytes(src.read_bytes())
    blocks_dir = tmp_path / "data" / "blocks"
    with pytest.raises(StorageQuotaExceeded):
        accept_block(store, blocks_dir=blocks_dir, tenant_id=tenant["id"], tmp_path=tmp, sha256="cd" * 32,
                     size_bytes=src.stat().st_size, filename="b.laz")
    assert list(blocks_dir.iterdir()) == [] and not tmp.exists() and store.blocks.list(tenant["id"]) == []
    store.close()
