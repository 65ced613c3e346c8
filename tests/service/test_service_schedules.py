"""Overnight schedules: cron times, inbox validation, scans that never take a capture twice."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import pytest
from service_fixtures import tenant_inbox, write_las

from pipeline.errors import InputError, ParameterError
from service.db.jobstore import Store
from service.jobrequests import request_tiling
from service.schedules import (
    ScheduleClock,
    check_inbox_use,
    next_run_time,
    run_schedule,
    tenant_inbox_root,
    validate_cron,
    validate_inbox,
)
from service.settings import Settings


def test_next_run_default_is_one_in_the_morning_local_time():
    evening = datetime(2026, 3, 10, 22, 30)  # naive = local time
    nxt = next_run_time("0 1 * * *", evening)
    assert nxt.tzinfo is not None
    local = nxt.replace(tzinfo=None)
    assert local == datetime(2026, 3, 11, 1, 0)
    # exactly at the time: the next one is a day later
    assert next_run_time("0 1 * * *", nxt).replace(tzinfo=None) == datetime(2026, 3, 12, 1, 0)


def test_next_run_from_timestamp_and_weekdays():
    monday_noon = datetime(2026, 11, 23, 12, 0).astimezone()
    nxt = next_run_time("30 2 * * 6", monday_noon.timestamp())  # Saturdays 02:30
    assert nxt.replace(tzinfo=None) == datetime(2026, 11, 28, 2, 30)
    assert nxt.weekday() == 5


@pytest.fixture
def local_zone(monkeypatch):
    """Set the process's local time zone (``TZ``) for one test."""

    def use(name: str) -> None:
        monkeypatch.setenv("TZ", name)
        time.tzset()

    yield use
    monkeypatch.undo()
    time.tzset()


@pytest.mark.skipif(not hasattr(time, "tzset") or not Path("/usr/share/zoneinfo/Europe/Berlin").exists(),
                    reason="needs time.tzset and the system's zone files")
def test_cron_keeps_local_time_across_daylight_saving_changes(local_zone):
    # a fixed UTC offset taken from the start put the night after a change an hour off
    # (02:00 CEST in spring, 00:00 CET in autumn)
    local_zone("Europe/Berlin")
    cases = [
        (datetime(2026, 3, 29, 1, 30), "0 1 * * *", datetime(2026, 3, 30, 1, 0), 2),  # after the spring change
        (datetime(2026, 10, 25, 1, 30), "0 1 * * *", datetime(2026, 10, 26, 1, 0), 1),  # after the autumn change
        (datetime(2026, 3, 28, 12, 0), "0 1 * * *", datetime(2026, 3, 29, 1, 0), 1),
    ]
    for start, expr, expected, utc_offset_h in cases:
        nxt = next_run_time(expr, start)
        assert nxt.replace(tzinfo=None) == expected
        assert nxt.utcoffset().total_seconds() == utc_offset_h * 3600
    # 02:30 does not exist on 2026-03-29 (02:00 -> 03:00): it runs once the clock is past it
    skipped = next_run_time("30 2 * * *", datetime(2026, 3, 29, 1, 0))
    assert skipped.replace(tzinfo=None) == datetime(2026, 3, 29, 3, 30)
    # 02:30 happens twice on 2026-10-25: one run, then the next night
    first = next_run_time("30 2 * * *", datetime(2026, 10, 25, 0, 0))
    assert first.replace(tzinfo=None) == datetime(2026, 10, 25, 2, 30)
    assert next_run_time("30 2 * * *", first).replace(tzinfo=None) == datetime(2026, 10, 26, 2, 30)


@pytest.mark.parametrize(
    "expr, words",
    [
        ("", "it has 0 field"),
        ("every night", "it has 2 field"),
        ("* * * *", "it has 4 field"),
        ("0 1 * * * *", "it has 6 field"),
        ("61 1 * * *", "minute field '61'"),
        ("0 25 * * *", "hour field '25'"),
        ("*/0 * * * *", "minute field '\\*/0'"),  # a five-field expression was told to use 5 fields
        ("0 0 32 * *", "day-of-month field '32'"),
        ("0 0 * 13 *", "month field '13'"),
        ("0 0 * * 8", "weekday field '8'"),
        ("R 1 * * *", "minute field 'R'"),  # croniter's random minute: drawn again at each run
        ("0 H * * *", "hour field 'H'"),
    ],
)
def test_invalid_cron_is_refused_naming_the_field(expr, words):
    with pytest.raises(ParameterError, match=f"invalid cron expression.*{words}"):
        validate_cron(expr)


@pytest.mark.parametrize("expr", ["0 1 * * *", "0 0 L * *", "0 0 * * 1#5", "30 2 * MAR,OCT THU", "*/15 22-2 * * 7", "0 1 15W * *"])
def test_valid_cron_is_kept(expr):
    assert validate_cron(f"  {expr} ") == expr


@pytest.mark.parametrize("expr", ["0 0 31 2 *", "0 0 30 2 *", "15 3 31 4,6,9,11 *"])
def test_cron_that_never_matches_is_refused(expr):
    # valid fields, but the day never comes: croniter would fail at the first next run
    with pytest.raises(ParameterError, match="never matches"):
        validate_cron(expr)
    with pytest.raises(ParameterError):
        next_run_time(expr, datetime(2026, 1, 1))


def test_leap_day_cron_is_accepted():
    assert next_run_time("0 1 29 2 *", datetime(2026, 3, 1)).replace(tzinfo=None) == datetime(2028, 2, 29, 1, 0)


def test_inbox_validation(tmp_path):
    (tmp_path / "file.las").write_bytes(b"x")
    assert validate_inbox(str(tmp_path)) == tmp_path.resolve()
    with pytest.raises(ParameterError, match="does not exist"):
        validate_inbox(str(tmp_path / "missing"))
    with pytest.raises(ParameterError, match="not a folder"):
        validate_inbox(str(tmp_path / "file.las"))
    for relative in ("relative/inbox", "~", "~nosuchuser\u00ad/x"):
        with pytest.raises(ParameterError, match="absolute"):
            validate_inbox(relative)
    with pytest.raises(ParameterError):
        validate_inbox("~nosuchuser\u00ad/x", base=tmp_path)
    (tmp_path / "sub").mkdir()
    assert validate_inbox("sub", base=tmp_path) == (tmp_path / "sub").resolve()
    root = tmp_path / "root"
    (root / "farm").mkdir(parents=True)
    assert validate_inbox(str(root / "farm"), root=root) == (root / "farm").resolve()
    with pytest.raises(ParameterError, match="outside"):
        validate_inbox(str(tmp_path), root=root)
    with pytest.raises(ParameterError, match="outside"):
        validate_inbox(str(root / "farm" / ".." / ".."), root=root)


def test_outside_root_is_refused_before_the_path_is_looked_up(tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    (tmp_path / "present").mkdir()
    # the same message whether the folder exists, is a file or does not: nothing is given away
    for outside in ("/etc", "/etc/passwd", "/no/such/folder", str(tmp_path / "present")):
        with pytest.raises(ParameterError, match="outside this farm's folder") as err:
            validate_inbox(outside, root=root, root_label="this farm's folder")
        assert "does not exist" not in str(err.value) and "not a folder" not in str(err.value)
    # nor where a link leads: the message shows the path as given
    (root / "escape").symlink_to(tmp_path / "present")
    for given in (str(root / "escape"), "/proc/self/cwd"):
        with pytest.raises(ParameterError) as err:
            validate_inbox(given, root=root, root_label="this farm's folder")
        assert str(err.value) == f"inbox {given!r} is outside this farm's folder {str(root)!r}"


def test_tenant_inbox_root_is_the_tenants_own_folder(tmp_path):
    settings = Settings(data_dir=tmp_path / "data")
    assert tenant_inbox_root(settings, "farm-a") == tmp_path / "data" / "inboxes" / "farm-a"
    assert (tmp_path / "data" / "inboxes" / "farm-a").is_dir()  # created, ready for captures
    settings = Settings(data_dir=tmp_path / "data", inbox_root=tmp_path / "drop")
    assert tenant_inbox_root(settings, "farm-b") == tmp_path / "drop" / "farm-b"
    for name in ("..", ".", "a/b", "a\\b"):
        with pytest.raises(ParameterError, match="no inbox folder"):
            tenant_inbox_root(settings, name)


def test_inbox_use_refuses_service_folders_and_other_tenants_inboxes(tmp_path):
    settings = Settings(data_dir=tmp_path / "data")
    store = Store(settings.store_path)
    try:
        a, b = store.accounts.ensure_tenant("a"), store.accounts.ensure_tenant("b")
        data = settings.data_dir.resolve()
        for folder in (data, data / "blocks", data / "jobs" / "x" / "_work", data / "tmp"):
            with pytest.raises(ParameterError, match="service's own data"):
                check_inbox_use(folder, settings=settings, store=store, tenant_id=a["id"])
        inbox = (tmp_path / "in").resolve()
        check_inbox_use(inbox, settings=settings, store=store, tenant_id=a["id"])  # free: fine
        _schedule(store, a, inbox)
        with pytest.raises(ParameterError, match="another tenant"):
            check_inbox_use(inbox, settings=settings, store=store, tenant_id=b["id"])
        # a second schedule of a's own on it would take every capture twice
        with pytest.raises(ParameterError, match="already has schedule"):
            check_inbox_use(inbox, settings=settings, store=store, tenant_id=a["id"])
        check_inbox_use(data / "inboxes" / "b", settings=settings, store=store, tenant_id=b["id"])
    finally:
        store.close()


@pytest.fixture()
def local(tmp_path):
    # captures are written just before each scan here: take them at once (the settle
    # time has its own tests)
    settings = Settings(data_dir=tmp_path / "data", capture_settle_s=0)
    store = Store(settings.store_path)
    tenant = store.accounts.ensure_tenant("farm")
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    yield settings, store, tenant, inbox
    store.close()


def _schedule(store, tenant, inbox, cron="0 1 * * *"):
    return store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron=cron, job={}, next_run_at=None)


def test_run_schedule_takes_each_capture_once(local):
    settings, store, tenant, inbox = local
    write_las(inbox / "a.laz", 500, seed=1)
    write_las(inbox / "b.las", 600, seed=2)
    (inbox / "notes.txt").write_text("not a capture")
    sched = _schedule(store, tenant, inbox)
    first = run_schedule(store, settings, sched)
    assert len(first["jobs"]) == 2 and first["skipped"] == 0 and first["rejected"] == []
    jobs = store.jobs.list(tenant["id"], schedule_id=sched["id"])
    assert {j["state"] for j in jobs} == {"queued"}
    again = run_schedule(store, settings, sched)
    assert again["jobs"] == [] and again["skipped"] == 2
    # the same capture copied under another name is not processed again either
    shutil.copy(inbox / "a.laz", inbox / "a-copy.laz")
    assert run_schedule(store, settings, sched)["jobs"] == []
    # a new capture is
    write_las(inbox / "c.laz", 700, seed=3)
    assert len(run_schedule(store, settings, sched)["jobs"]) == 1


def test_a_capture_still_being_copied_in_waits_for_a_later_scan(local):
    # a copy tool that sets the final size first and fills the file in afterwards (SMB,
    # robocopy, rsync --preallocate) passed every check half-written, and its job ended
    # "done" with the wrong trees
    settings, store, tenant, inbox = local
    settings = settings.model_copy(update={"capture_settle_s": 30.0})
    write_las(inbox / "a.laz", 500, seed=1)
    sched = _schedule(store, tenant, inbox)
    now = time.time()
    first = run_schedule(store, settings, sched, now=now)
    assert first["waiting"] == ["a.laz"] and first["jobs"] == [] and first["rejected"] == []
    assert store.schedules.files(sched["id"]) == []  # not recorded: it is looked at again
    later = run_schedule(store, settings, sched, now=now + 31)
    assert len(later["jobs"]) == 1 and later["waiting"] == []


@pytest.mark.skipif(sys.platform != "linux", reason="needs a file system that takes any bytes as a name")
def test_control_characters_in_a_captures_name_are_not_shown(local):
    # an escape sequence or newline in an inbox file's name reached the API, the block's
    # filename and the report's title raw (uploads' names were already cleaned)
    settings, store, tenant, inbox = local
    write_las(inbox / "row\x1b[31m 4\n\u202e.las", 500, seed=1)
    sched = _schedule(store, tenant, inbox)
    res = run_schedule(store, settings, sched)
    assert len(res["jobs"]) == 1
    job = store.jobs.get(tenant["id"], res["jobs"][0])
    assert store.blocks.get(tenant["id"], job["block_id"])["filename"] == "row[31m 4.las"


def test_a_capture_handled_before_is_not_read_again(local, monkeypatch):
    # every scan hashed every file in the inbox, captures handled long ago included: a
    # season's captures left there were all re-read every night
    from service import schedules

    settings, store, tenant, inbox = local
    write_las(inbox / "a.laz", 500, seed=1)
    write_las(inbox / "junk.las", 10, seed=2).write_bytes(b"not a LAS file")
    sched = _schedule(store, tenant, inbox)
    read = []
    real = schedules.file_sha256
    monkeypatch.setattr(schedules, "file_sha256", lambda p: read.append(p.name) or real(p))
    first = run_schedule(store, settings, sched)
    assert len(first["jobs"]) == 1 and len(first["rejected"]) == 1 and sorted(read) == ["a.laz", "junk.las"]
    read.clear()
    again = run_schedule(store, settings, sched)
    assert again["skipped"] == 2 and again["jobs"] == [] and read == []
    # a file written to since is read again (and, being new, taken)
    write_las(inbox / "a.laz", 700, seed=3)
    third = run_schedule(store, settings, sched)
    assert read == ["a.laz"] and len(third["jobs"]) == 1


def test_a_scan_by_hand_that_finds_a_capture_arriving_looks_again_once_it_settled(local):
    # "POST /schedules/{id}/run" and "orchard schedules run" said "waiting" and left the
    # capture to the next cron time, a month away for a monthly schedule
    settings, store, tenant, inbox = local
    settings = settings.model_copy(update={"capture_settle_s": 60.0})
    now = time.time()
    sched = store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron="0 1 1 * *", job={}, next_run_at=next_run_time("0 1 1 * *", now).timestamp())
    write_las(inbox / "a.laz", 500, seed=1)
    assert run_schedule(store, settings, sched, now=now)["waiting"] == ["a.laz"]
    assert store.schedules.get(tenant["id"], sched["id"])["next_run_at"] == pytest.approx(now + 60)
    ScheduleClock(store, settings).tick(now + 61)
    assert len(store.jobs.list(tenant["id"], schedule_id=sched["id"])) == 1
    rec = store.schedules.get(tenant["id"], sched["id"])
    assert rec["next_run_at"] == next_run_time("0 1 1 * *", now + 61).timestamp()  # the cron again
    # a scan that finds nothing arriving leaves the next run alone
    assert run_schedule(store, settings, rec, now=now + 62)["waiting"] == []
    assert store.schedules.get(tenant["id"], sched["id"])["next_run_at"] == rec["next_run_at"]


def test_a_capture_dated_in_the_future_settles_by_the_servers_clock(local):
    # copied with its times kept from a device whose clock runs ahead: "written just now"
    # until that date came round, and the inbox re-read at every settle interval meanwhile
    settings, store, tenant, inbox = local
    settings = settings.model_copy(update={"capture_settle_s": 30.0})
    path = write_las(inbox / "a.laz", 500, seed=1)
    ahead = time.time() + 5 * 365 * 86400
    os.utime(path, (ahead, ahead))
    sched = _schedule(store, tenant, inbox)
    now = time.time()
    assert run_schedule(store, settings, sched, now=now)["waiting"] == ["a.laz"]  # its times were just set
    assert len(run_schedule(store, settings, sched, now=now + 31)["jobs"]) == 1


def test_the_clock_looks_again_soon_at_a_capture_still_arriving(local):
    settings, store, tenant, inbox = local
    settings = settings.model_copy(update={"capture_settle_s": 120.0})
    now = time.time()
    sched = store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron="0 1 * * *", job={}, next_run_at=now - 1)
    write_las(inbox / "a.laz", 500, seed=1)
    ScheduleClock(store, settings).tick(now)
    rec = store.schedules.get(tenant["id"], sched["id"])
    assert rec["next_run_at"] == pytest.approx(now + 120)  # not tomorrow at 01:00
    os.utime(inbox / "a.laz", (now - 600, now - 600))  # the copy has finished
    ScheduleClock(store, settings).tick(now + 121)
    assert len(store.jobs.list(tenant["id"], schedule_id=sched["id"])) == 1
    rec = store.schedules.get(tenant["id"], sched["id"])
    assert rec["next_run_at"] == next_run_time("0 1 * * *", now + 121).timestamp()


@pytest.mark.skipif(sys.platform != "linux", reason="needs a file system that takes any bytes as a name")
def test_a_file_name_that_is_not_utf8_does_not_stop_the_scan(local):
    # a Latin-1 name from a USB stick: SQLite refused the name, the scan stopped there
    # every night, and no capture sorted after it was ever taken
    settings, store, tenant, inbox = local
    bad = os.fsencode(inbox) + b"/B\xe4ume.las"
    with open(bad, "wb") as fh:
        fh.write(write_las(inbox / "tmp.las", 500, seed=1).read_bytes())
    (inbox / "tmp.las").unlink()
    write_las(inbox / "zz new capture.laz", 600, seed=2)
    sched = _schedule(store, tenant, inbox)
    res = run_schedule(store, settings, sched)
    assert len(res["jobs"]) == 1
    assert res["rejected"] == [{"file": "B\\xe4ume.las", "error": res["rejected"][0]["error"]}]
    assert "not valid UTF-8" in res["rejected"][0]["error"]
    json.dumps(res)  # the API returns it as it is
    assert [f["path"] for f in store.schedules.files(sched["id"])] == [str(inbox / "zz new capture.laz")]
    # renamed, it is taken
    os.rename(bad, os.fsencode(inbox) + b"/Baeume.las")
    assert len(run_schedule(store, settings, sched)["jobs"]) == 1


def test_an_unexpected_failure_of_one_capture_does_not_stop_the_scan(local, monkeypatch):
    settings, store, tenant, inbox = local
    write_las(inbox / "a.laz", 500, seed=1)
    write_las(inbox / "b.laz", 600, seed=2)
    from service import schedules

    real = schedules.accept_block

    def flaky(store, **kw):
        if kw["filename"] == "a.laz":
            raise RuntimeError("disk hiccup")
        return real(store, **kw)

    monkeypatch.setattr(schedules, "accept_block", flaky)
    sched = _schedule(store, tenant, inbox)
    res = run_schedule(store, settings, sched)
    assert len(res["jobs"]) == 1 and res["rejected"][0]["file"] == "a.laz"
    assert res["rejected"][0]["error"] == "could not be taken (RuntimeError); it is tried again at the next scan"
    monkeypatch.setattr(schedules, "accept_block", real)
    assert len(run_schedule(store, settings, sched)["jobs"]) == 1  # and it is


def test_a_schedule_made_again_does_not_take_old_captures_again(local):
    # a farm deletes its schedule and makes a new one on the same inbox (to change its
    # cron): the captures the old one took are not processed a second time
    settings, store, tenant, inbox = local
    write_las(inbox / "a.laz", 500, seed=1)
    write_las(inbox / "b.las", 600, seed=2)
    old = _schedule(store, tenant, inbox)
    assert len(run_schedule(store, settings, old)["jobs"]) == 2
    store.schedules.delete(tenant["id"], old["id"])
    new = _schedule(store, tenant, inbox, cron="30 2 * * *")
    write_las(inbox / "c.laz", 700, seed=3)
    res = run_schedule(store, settings, new)
    assert len(res["jobs"]) == 1 and res["skipped"] == 2
    # another farm with the same capture is another matter: it gets its own job
    from service.schedules import file_sha256

    sha = file_sha256(inbox / "a.laz")
    other = store.accounts.ensure_tenant("other")
    assert store.schedules.capture_scheduled(tenant["id"], sha) and not store.schedules.capture_scheduled(other["id"], sha)


def test_unusable_capture_is_rejected_once(local):
    settings, store, tenant, inbox = local
    (inbox / "broken.laz").write_bytes(b"garbage" * 100)
    sched = _schedule(store, tenant, inbox)
    res = run_schedule(store, settings, sched)
    assert res["jobs"] == [] and len(res["rejected"]) == 1
    assert "broken.laz" in res["rejected"][0]["error"]
    assert run_schedule(store, settings, sched)["rejected"] == []


def test_clock_runs_due_schedules_and_sets_next_run(local):
    settings, store, tenant, inbox = local
    write_las(inbox / "a.laz", 500, seed=1)
    sched = _schedule(store, tenant, inbox)
    clock = ScheduleClock(store, settings)
    now = time.time()
    clock.tick(now)  # first look: computes the next run, runs nothing
    rec = store.schedules.get_any_tenant(sched["id"])
    assert rec["next_run_at"] == next_run_time("0 1 * * *", now).timestamp()
    assert store.jobs.list(tenant["id"]) == []
    clock.tick(rec["next_run_at"] + 1)  # the night comes
    assert len(store.jobs.list(tenant["id"])) == 1
    rec2 = store.schedules.get_any_tenant(sched["id"])
    assert rec2["last_run_at"] == rec["next_run_at"] + 1
    assert rec2["next_run_at"] > rec["next_run_at"]


def test_api_schedules_run_now(client_a, api_data):
    inbox = tenant_inbox(api_data, "farm-a", "run-now")
    write_las(inbox / "one.laz", 800, seed=21)
    write_las(inbox / "two.las", 900, seed=22)
    r = client_a.post("/v1/schedules", json={"inbox": str(inbox), "tiling": {"tile_size": 20}})
    assert r.status_code == 201, r.text
    sched = r.json()
    assert sched["cron"] == "0 1 * * *" and sched["id"]
    assert datetime.fromisoformat(sched["next_run_at"]).hour == 1
    assert sched["id"] in [s["id"] for s in client_a.get("/v1/schedules").json()]
    run = client_a.post(f"/v1/schedules/{sched['id']}/run").json()
    assert len(run["jobs"]) == 2
    captures = set()
    for jid in run["jobs"]:
        job = client_a.get(f"/v1/jobs/{jid}").json()
        assert job["schedule_id"] == sched["id"] and job["tiling"]["tile_size"] == 20
        captures.add(job["capture"])
    assert captures == {"one.laz", "two.las"}
    assert client_a.post(f"/v1/schedules/{sched['id']}/run").json()["jobs"] == []
    listed = client_a.get("/v1/jobs", params={"schedule_id": sched["id"]}).json()["items"]
    assert sorted(j["id"] for j in listed) == sorted(run["jobs"])
    for jid in run["jobs"]:
        client_a.delete(f"/v1/jobs/{jid}")


@pytest.mark.parametrize(
    "body, fragment",
    [
        ({"inbox": "/definitely/not/here"}, "outside this tenant's inbox folder"),
        ({"inbox": "relative"}, "absolute"),
        ({"inbox": "~\ud872\ude05N\u00adl\u0014\u00a2\r"}, "absolute"),  # found by schemathesis: was a 500
        ({"inbox": "/tmp", "cron": "whenever"}, "cron"),
        ({"inbox": "{farm-a}", "cron": "0 0 31 2 *"}, "never matches"),  # was a 500
        ({"inbox": "{farm-a}/missing"}, "does not exist"),
        ({"inbox": "{farm-a}", "tiling": {"tile_size": 10, "buffer": 1}}, "tiling.buffer"),  # every night's job would fail
        ({"inbox": "{farm-a}", "tiling": {"tile_size": 0}}, "tile_size"),
        ({"inbox": "{farm-a}", "tiling": {"tile_size": 0.5}}, "greater than or equal to 1"),  # the job model's bound
    ],
)
def test_api_bad_schedule_is_422(client_a, api_data, body, fragment):
    own = str(tenant_inbox(api_data, "farm-a", "bad-schedule"))
    body = {k: v.replace("{farm-a}", own) if isinstance(v, str) else v for k, v in body.items()}
    r = client_a.post("/v1/schedules", content=json.dumps(body), headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert fragment in r.json()["detail"]
    assert all(s["inbox"] != own for s in client_a.get("/v1/schedules").json())  # nothing stored


def test_api_inbox_is_confined_to_the_tenants_folder(client_a, client_b, api_data):
    """A farm cannot watch the service's uploads, server folders or another farm's
    inbox: each would hand it files that are not its own."""
    data = api_data.resolve()
    own_b = tenant_inbox(api_data, "farm-b", "captures")
    for outside in (data / "blocks", data, Path("/etc"), Path("/root"), data / "inboxes",
                    data / "inboxes" / "farm-a", own_b / ".." / ".." / "farm-a"):
        r = client_b.post("/v1/schedules", json={"inbox": str(outside)})
        assert r.status_code == 422, (outside, r.text)
        assert "outside this tenant's inbox folder" in r.json()["detail"]
    # symlinks are followed before the check: a link in its own folder does not get out
    link = own_b / "link-to-blocks"
    if not link.exists():
        link.symlink_to(data / "blocks")
    r = client_b.post("/v1/schedules", json={"inbox": str(link)})
    assert r.status_code == 422 and "outside" in r.json()["detail"]
    # its own folder, and the folder itself, are fine
    for inbox in (own_b, own_b.parent):
        r = client_b.post("/v1/schedules", json={"inbox": str(inbox)})
        assert r.status_code == 201, r.text
        assert client_b.delete(f"/v1/schedules/{r.json()['id']}").status_code == 204


def _orchard(*args, env_data_dir=None):
    import os

    env = dict(os.environ)
    if env_data_dir:
        env["ORCHARD_DATA_DIR"] = str(env_data_dir)
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True, env=env, timeout=60)


def test_cli_schedules_create_and_list(tmp_path, monkeypatch, capsys):
    from service.cli import main

    data = tmp_path / "data"
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    monkeypatch.setenv("ORCHARD_DATA_DIR", str(data))
    assert main(["schedules", "create", "--tenant", "farm-x", "--inbox", str(inbox), "--cron", "15 2 * * *"]) == 0
    sid = capsys.readouterr().out.strip()
    monkeypatch.delenv("ORCHARD_DATA_DIR")
    assert main(["schedules", "list", "--data-dir", str(data)]) == 0
    out = capsys.readouterr().out
    assert sid in out and "15 2 * * *" in out and "farm-x" in out
    assert main(["schedules", "create", "--tenant", "farm-x", "--inbox", str(tmp_path / "nope"), "--data-dir", str(data)]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and "Traceback" not in err
    assert main(["schedules", "create", "--tenant", "farm-x", "--inbox", str(inbox), "--cron", "bad", "--data-dir", str(data)]) == 2
    assert "cron" in capsys.readouterr().err
    write_las(inbox / "a.laz", 300, seed=8)
    monkeypatch.setenv("ORCHARD_CAPTURE_SETTLE_S", "0")  # just written
    assert main(["schedules", "run", sid, "--data-dir", str(data)]) == 0
    assert '"jobs": [' in capsys.readouterr().out
    store = Store(data / "orchard.sqlite")
    assert len(store.jobs.list(store.accounts.tenant_by_name("farm-x")["id"], schedule_id=sid)) == 1
    store.close()


def test_cli_tokens_create_prints_only_the_token(tmp_path, monkeypatch, capsys):
    data = tmp_path / "data"
    r = _orchard("tokens", "create", "--tenant", "farm-y", "--data-dir", str(data))
    assert r.returncode == 0, r.stderr
    token = r.stdout.strip()
    assert r.stdout == token + "\n" and token.startswith("orch_") and len(token) > 30
    assert token.encode() not in Path(data / "orchard.sqlite").read_bytes()
    store = Store(data / "orchard.sqlite")
    from service.auth import authenticate

    assert authenticate(store, f"Bearer {token}")["name"] == "farm-y"
    store.close()
    from service.cli import main

    monkeypatch.setenv("ORCHARD_DATA_DIR", str(data))
    assert main(["tokens", "list"]) == 0
    listed = [line.split("\t") for line in capsys.readouterr().out.splitlines()[1:]]
    assert [(row[0], row[2]) for row in listed] == [("farm-y", token[:13])]


def test_one_schedule_per_inbox_in_the_store_and_one_job_per_capture(local):
    # requests at the same moment both passed the API's check (5 schedules on one inbox),
    # and two scans at once queued every capture twice: the store now refuses both
    settings, store, tenant, inbox = local
    sched = _schedule(store, tenant, inbox)
    with pytest.raises(ParameterError, match="already has a schedule"):
        _schedule(store, tenant, inbox)
    block, _ = store.blocks.insert(tenant_id=tenant["id"], sha256="cd" * 32, path=str(inbox / "x.laz"),
                                  filename="x.laz", size_bytes=1, info={})
    first = store.schedules.create_job(schedule=sched, block_id=block["id"], sha256="cd" * 32, path="x.laz")
    again = store.schedules.create_job(schedule=sched, block_id=block["id"], sha256="cd" * 32, path="x.laz")
    assert first["schedule_id"] == sched["id"] and again is None
    assert len(store.jobs.list(tenant["id"])) == 1


def test_links_in_an_inbox_are_not_followed(local, tmp_path):
    # a farm able to place links in its inbox (rsync -a) could hand itself any file on the
    # server, another farm's capture included
    settings, store, tenant, inbox = local
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    write_las(elsewhere / "theirs.laz", 500, seed=4)
    (inbox / "stolen.laz").symlink_to(elsewhere / "theirs.laz")
    write_las(inbox / "mine.laz", 500, seed=5)
    sched = _schedule(store, tenant, inbox)
    res = run_schedule(store, settings, sched)
    assert len(res["jobs"]) == 1 and res["skipped"] == 0
    assert store.blocks.get(tenant["id"], store.jobs.get(tenant["id"], res["jobs"][0])["block_id"])["filename"] == "mine.laz"
    # the inbox itself swapped for a link to another folder after the schedule was made
    sub = tmp_path / "sub"
    sub.mkdir()
    sched2 = _schedule(store, tenant, sub.resolve())
    sub.rmdir()
    sub.symlink_to(elsewhere)
    with pytest.raises(InputError, match="now a link"):
        run_schedule(store, settings, sched2)


def test_a_paused_schedule_is_skipped_by_the_clock_and_resumes_at_its_next_cron_time(local):
    from service.jobrequests import schedule_changes

    settings, store, tenant, inbox = local
    write_las(inbox / "a.laz", 500, seed=1)
    sched = _schedule(store, tenant, inbox)
    clock = ScheduleClock(store, settings)
    now = time.time()
    clock.tick(now)
    due = store.schedules.get_any_tenant(sched["id"])["next_run_at"]
    sched = store.schedules.get_any_tenant(sched["id"])
    store.schedules.update(tenant["id"], sched["id"], schedule_changes(sched, {"paused": True}))
    paused = store.schedules.get_any_tenant(sched["id"])
    assert paused["paused"] == 1 and paused["next_run_at"] is None
    for night in range(3):  # three nights pass: nothing is scanned, nothing is set
        clock.tick(due + 1 + night * 86400)
    assert store.jobs.list(tenant["id"]) == []
    assert store.schedules.get_any_tenant(sched["id"])["next_run_at"] is None
    # a scan by hand still runs, and does not bring a paused schedule forward
    assert len(run_schedule(store, settings, paused)["jobs"]) == 1
    assert store.schedules.get_any_tenant(sched["id"])["next_run_at"] is None
    # resumed three nights later: from the next cron time, the missed nights not made up
    later = datetime.fromtimestamp(due + 3 * 86400 + 3600).astimezone()
    changes = schedule_changes(paused, {"paused": False}, now=later)
    assert changes == {"paused": False, "next_run_at": next_run_time("0 1 * * *", later).timestamp()}
    store.schedules.update(tenant["id"], sched["id"], changes)
    rec = store.schedules.get_any_tenant(sched["id"])
    assert rec["paused"] == 0 and rec["next_run_at"] == changes["next_run_at"]


def test_the_clock_does_not_undo_a_pause_or_a_new_cron_made_while_it_ran(local):
    # the clock computes the next run from the cron it read; a pause or cron change
    # stored meanwhile must win
    _, store, tenant, inbox = local
    sched = _schedule(store, tenant, inbox)
    store.schedules.update(tenant["id"], sched["id"], {"paused": True, "next_run_at": None})
    store.schedules.set_times(sched["id"], cron=sched["cron"], last_run_at=1.0, next_run_at=2.0)
    assert store.schedules.get_any_tenant(sched["id"])["next_run_at"] is None
    store.schedules.update(tenant["id"], sched["id"], {"paused": False, "cron": "0 3 * * *", "next_run_at": 5.0})
    store.schedules.set_times(sched["id"], cron="0 1 * * *", last_run_at=1.0, next_run_at=2.0)
    assert store.schedules.get_any_tenant(sched["id"])["next_run_at"] == 5.0
    store.schedules.set_times(sched["id"], cron="0 3 * * *", last_run_at=1.0, next_run_at=7.0)
    rec = store.schedules.get_any_tenant(sched["id"])
    assert rec["next_run_at"] == 7.0 and rec["last_run_at"] == 1.0


def test_a_store_from_before_pausing_gains_the_column(tmp_path):
    import sqlite3

    path = tmp_path / "old.sqlite"
    Store(path).close()
    con = sqlite3.connect(path)
    con.execute("ALTER TABLE schedules DROP COLUMN paused")
    con.execute("INSERT INTO tenants (id, name, created_at) VALUES ('t', 'farm', 0)")
    con.execute("INSERT INTO schedules (id, tenant_id, inbox, cron, job, created_at) VALUES ('s', 't', '/x', '0 1 * * *', '{}', 0)")
    con.commit()
    con.close()
    store = Store(path)
    assert store.schedules.get_any_tenant("s")["paused"] == 0
    store.close()


def test_api_pause_resume_and_change_a_schedule(client_a, client_b, api_data):
    inbox = tenant_inbox(api_data, "farm-a", "patch-me")
    sched = client_a.post("/v1/schedules", json={"inbox": str(inbox)}).json()
    assert sched["paused"] is False and sched["next_run_at"]
    url = f"/v1/schedules/{sched['id']}"
    r = client_a.patch(url, json={"paused": True})
    assert r.status_code == 200, r.text
    assert r.json()["paused"] is True and r.json()["next_run_at"] is None
    assert client_a.get(url).json()["paused"] is True
    # another farm cannot see it, let alone change it
    assert client_b.patch(url, json={"paused": False}).status_code == 404
    assert client_a.get(url).json()["paused"] is True
    r = client_a.patch(url, json={"paused": False, "cron": "30 2 * * 6"})
    got = r.json()
    assert r.status_code == 200 and got["paused"] is False and got["cron"] == "30 2 * * 6"
    nxt = datetime.fromisoformat(got["next_run_at"])
    assert (nxt.weekday(), nxt.hour, nxt.minute) == (5, 2, 30)
    # tiling and parameters: checked as at creation, and nothing stored when refused
    r = client_a.patch(url, json={"tiling": {"tile_size": 30, "buffer": 7}, "params": {"trunks": {"min_tree_height": 1.5}}})
    assert r.status_code == 200, r.text
    assert r.json()["tiling"] == {"tile_size": 30, "buffer": 7} and r.json()["params"]["trunks"]["min_tree_height"] == 1.5
    for body, fragment in (
        ({"tiling": {"tile_size": 10, "buffer": 1}}, "tiling.buffer"),
        ({"params": {"segment": {"max_crown_radius": 10}}}, "tiling.buffer"),  # its reach outgrows the stored buffer
        ({"cron": "0 0 31 2 *"}, "never matches"),
        ({"cron": None}, "cron"),
        ({"paused": None}, "paused"),
        ({"inbox": "/elsewhere"}, "inbox"),
    ):
        r = client_a.patch(url, json=body)
        assert r.status_code == 422, (body, r.text)
        assert fragment in r.json()["detail"], (body, r.text)
    kept = client_a.get(url).json()
    assert kept["cron"] == "30 2 * * 6" and kept["tiling"]["tile_size"] == 30 and kept["paused"] is False
    r = client_a.patch(url, json={"tiling": None})
    assert r.status_code == 200 and r.json()["tiling"] is None
    assert client_a.patch("/v1/schedules/nope", json={"paused": True}).status_code == 404
    assert client_a.delete(url).status_code == 204


def test_cli_schedules_pause_resume_and_update(tmp_path, capsys):
    from service.cli import main

    data, inbox = tmp_path / "data", tmp_path / "inbox"
    inbox.mkdir()
    assert main(["schedules", "create", "--tenant", "farm-x", "--inbox", str(inbox), "--data-dir", str(data)]) == 0
    sid = capsys.readouterr().out.strip()
    assert main(["schedules", "pause", sid, "--data-dir", str(data)]) == 0
    assert "paused" in capsys.readouterr().out
    assert main(["schedules", "list", "--data-dir", str(data)]) == 0
    assert f"{sid}\tfarm-x\t0 1 * * *\tpaused\t" in capsys.readouterr().out
    assert main(["schedules", "resume", sid, "--data-dir", str(data)]) == 0
    assert "next run" in capsys.readouterr().out
    assert main(["schedules", "update", sid, "--cron", "15 3 * * *", "--tile-size", "40", "--data-dir", str(data)]) == 0
    capsys.readouterr()
    store = Store(data / "orchard.sqlite")
    rec = store.schedules.get_any_tenant(sid)
    store.close()
    assert rec["cron"] == "15 3 * * *" and request_tiling(rec["job"]) == {"tile_size": 40.0, "buffer": None} and rec["paused"] == 0
    for args, fragment in ((["--cron", "61 * * * *"], "minute field"), ([], "nothing to change"),
                           (["--untiled", "--tile-size", "5"], "--untiled"), (["--tile-size", "0.5"], "--tile-size: Input should be"),
                           (["--tile-size", "10", "--buffer", "1"], "buffer")):
        assert main(["schedules", "update", sid, *args, "--data-dir", str(data)]) == 2, args
        err = capsys.readouterr().err
        assert fragment in err and "Traceback" not in err, (args, err)
    assert main(["schedules", "update", sid, "--buffer", "9", "--data-dir", str(data)]) == 0  # keeps its 40 m tiles
    assert main(["schedules", "update", sid, "--tile-size", "30", "--data-dir", str(data)]) == 0  # keeps its 9 m buffer
    store = Store(data / "orchard.sqlite")
    assert request_tiling(store.schedules.get_any_tenant(sid)["job"]) == {"tile_size": 30.0, "buffer": 9.0}
    store.close()
    # a check of the tiling speaks of the command's options, not the API's fields
    assert main(["schedules", "update", sid, "--buffer", "3", "--data-dir", str(data)]) == 2
    err = capsys.readouterr().err
    assert "--buffer" in err and "tiling.buffer" not in err, err
    # pipeline options change those parameters and keep the others; the advice of that
    # error (a smaller crown radius) can be followed from here
    assert main(["schedules", "update", sid, "--trunks-min-tree-height", "1.5", "--data-dir", str(data)]) == 0
    assert main(["schedules", "update", sid, "--buffer", "3", "--segment-max-crown-radius", "1.5",
                 "--data-dir", str(data)]) == 0
    capsys.readouterr()
    store = Store(data / "orchard.sqlite")
    rec = store.schedules.get_any_tenant(sid)
    store.close()
    params = rec["job"]["pipeline"]
    assert params["trunks"]["min_tree_height"] == 1.5 and params["segment"]["max_crown_radius"] == 1.5
    assert request_tiling(rec["job"]) == {"tile_size": 30.0, "buffer": 3.0}
    assert main(["schedules", "update", sid, "--segment-max-crown-radius", "5", "--data-dir", str(data)]) == 2
    assert "--buffer" in capsys.readouterr().err  # 5 m crowns need more than the 3 m buffer
    assert main(["schedules", "update", sid, "--untiled", "--data-dir", str(data)]) == 0
    capsys.readouterr()
    assert main(["schedules", "update", sid, "--buffer", "9", "--data-dir", str(data)]) == 2
    assert "the schedule processes each capture as one tile" in capsys.readouterr().err
    for action in (["pause"], ["run"], ["delete"], ["update", "--cron", "1 * * * *"]):
        assert main(["schedules", action[0], "nope", *action[1:], "--data-dir", str(data)]) == 3
        assert "list them with 'orchard schedules list'" in capsys.readouterr().err


def test_a_change_or_pause_during_a_long_scan_applies_to_the_captures_queued_after_it(local, monkeypatch):
    # the scan queued every capture with the settings read before it started: a farm that
    # paused or fixed its parameters during a night's multi-GB scan still got the old jobs
    from service import schedules

    settings, store, tenant, inbox = local
    for i in range(3):
        write_las(inbox / f"c{i}.laz", 400 + i, seed=40 + i)
    sched = _schedule(store, tenant, inbox)
    real_copy = schedules._copy_hashed
    change = {}

    def copy_and_change(src, dst):
        if change:
            store.schedules.update(tenant["id"], sched["id"], change.copy())
            change.clear()
        return real_copy(src, dst)

    monkeypatch.setattr(schedules, "_copy_hashed", copy_and_change)
    change.update(paused=True)  # paused while the clock's scan reads its first capture
    res = run_schedule(store, settings, sched, by_clock=True)
    assert res["jobs"] == [] and store.jobs.list(tenant["id"]) == []
    new = {"segment": {"max_crown_radius": 3.0}}
    change.update(job={"pipeline": new})  # a scan by hand of the paused schedule runs on, with the new parameters
    res = run_schedule(store, settings, store.schedules.get_any_tenant(sched["id"]))
    assert len(res["jobs"]) == 3
    assert all(j["job"]["pipeline"] == new for j in store.jobs.list(tenant["id"]))


def test_two_changes_at_once_cannot_store_a_buffer_below_the_reach(local):
    # each PATCH was checked against the schedule read before either wrote: new default
    # parameters (reach 6.15 m) and a 3.5 m buffer (fine for the old 2 m crowns) were both
    # stored, and every night's job then failed at planning
    import threading

    from service.jobrequests import schedule_changes

    settings, store, tenant, inbox = local
    sched = store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron="0 1 * * *",
                                  job={"pipeline": {"segment": {"max_crown_radius": 2.0}}, "tiling": {"tile_size": 30.0}},
                                  next_run_at=None)
    inside = threading.Event()

    def slow_params(current):
        changes = schedule_changes(current, {"params": {}})
        inside.set()
        time.sleep(0.5)  # still in its write transaction
        return changes

    first = threading.Thread(target=store.schedules.update, args=(tenant["id"], sched["id"], slow_params))
    first.start()
    assert inside.wait(10)
    other = Store(settings.store_path)  # another request's connection
    try:
        with pytest.raises(ParameterError, match="buffer"):
            other.schedules.update(tenant["id"], sched["id"],
                                  lambda current: schedule_changes(current, {"tiling": {"tile_size": 30, "buffer": 3.5}}))
    finally:
        first.join(10)
        other.close()
    rec = store.schedules.get_any_tenant(sched["id"])
    assert request_tiling(rec["job"]) == {"tile_size": 30.0, "buffer": None}
    assert rec["job"]["pipeline"]["segment"]["max_crown_radius"] == 5.0
