"""Every capture's fate: processed, rejected, still arriving, new, ignored; in the
schedule's resource, the command line's list and the nightly scan's log line."""

from __future__ import annotations

import logging
import os
import time

import pytest
from service_fixtures import tenant_inbox, write_las

from service.capturefates import capture_fates, fate_line
from service.db.jobstore import Store
from service.schedules import ScheduleClock, accepted_suffixes, ignored_why, run_schedule
from service.settings import Settings


@pytest.fixture()
def local(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", capture_settle_s=0)
    store = Store(settings.store_path)
    tenant = store.accounts.ensure_tenant("farm")
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    yield settings, store, tenant, inbox
    store.close()


def _schedule(store, tenant, inbox):
    return store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron="0 1 * * *", job={}, next_run_at=None)


def _fill(inbox):
    """A good capture, a text file named .laz, a truncated LAZ, and files of other types."""
    write_las(inbox / "good.laz", 400, seed=1)
    (inbox / "bad.laz").write_text("these are notes, not points\n" * 20)
    data = write_las(inbox / "cut.laz", 3000, seed=2).read_bytes()
    (inbox / "cut.laz").write_bytes(data[: len(data) // 3])
    (inbox / "scan.csv").write_text("1 2 3\n4 5 6\n")
    (inbox / "notes.txt").write_text("row 4 sprayed")
    (inbox / "old").mkdir()
    (inbox / ".DS_Store").write_bytes(b"\0")


def _by_file(fates):
    return {c["file"]: c for c in fates["captures"]}


def test_the_ignore_rule_follows_the_accepted_suffixes(tmp_path, monkeypatch):
    import service.schedules as schedules

    (tmp_path / "scan.csv").write_text("1 2 3\n")
    why = ignored_why(tmp_path / "scan.csv")
    assert why.startswith("a .csv file") and all(s in why for s in accepted_suffixes())
    # a format taken later (a reader for it added) is no longer ignored, with nothing else changed
    monkeypatch.setattr(schedules, "CAPTURE_SUFFIXES", (*accepted_suffixes(), ".csv"))
    assert ignored_why(tmp_path / "scan.csv") is None
    assert [p.name for p in schedules.captures(tmp_path)] == ["scan.csv"]


def test_every_file_of_an_inbox_has_a_fate(local):
    settings, store, tenant, inbox = local
    _fill(inbox)
    sched = _schedule(store, tenant, inbox)
    before = _by_file(capture_fates(store, settings, sched))
    assert {f: c["fate"] for f, c in before.items()} == {
        "good.laz": "new", "bad.laz": "new", "cut.laz": "new",
        "scan.csv": "ignored", "notes.txt": "ignored", "old": "ignored",
    }
    res = run_schedule(store, settings, sched)
    assert len(res["jobs"]) == 1 and len(res["rejected"]) == 2
    assert sorted(i["file"] for i in res["ignored"]) == ["notes.txt", "old", "scan.csv"]
    fates = capture_fates(store, settings, sched)
    got = _by_file(fates)
    assert got["good.laz"]["fate"] == "processed" and got["good.laz"]["job_id"] == res["jobs"][0]
    assert got["good.laz"]["job_state"] == "queued"
    assert got["bad.laz"]["fate"] == "rejected" and "LASF" in got["bad.laz"]["reason"]
    assert got["cut.laz"]["fate"] == "rejected" and got["cut.laz"]["reason"]
    assert got["scan.csv"]["fate"] == "ignored" and ".csv" in got["scan.csv"]["reason"]
    assert "folder" in got["old"]["reason"]
    assert ".DS_Store" not in got
    assert fates["counts"] == {"arriving": 0, "new": 0, "rejected": 2, "processed": 1, "ignored": 3}
    # a capture handled and then moved away is still told
    (inbox / "good.laz").unlink()
    assert _by_file(capture_fates(store, settings, sched))["good.laz"]["fate"] == "processed"
    assert fate_line(got["scan.csv"]).startswith("ignored   scan.csv  a .csv file")


def test_a_capture_being_copied_in_is_arriving(local, tmp_path):
    _, store, tenant, inbox = local
    settings = Settings(data_dir=tmp_path / "data", capture_settle_s=3600)
    write_las(inbox / "late.laz", 300, seed=3)
    sched = _schedule(store, tenant, inbox)
    got = _by_file(capture_fates(store, settings, sched))
    assert got["late.laz"]["fate"] == "arriving"
    assert run_schedule(store, settings, sched)["waiting"] == ["late.laz"]
    old = time.time() - 7200
    os.utime(inbox / "late.laz", (old, old))  # ctime is now: still arriving by the server's clock
    assert _by_file(capture_fates(store, settings, sched, now=time.time() + 7200))["late.laz"]["fate"] == "new"


def test_the_nightly_log_line_counts_rejected_and_ignored(local, caplog):
    settings, store, tenant, inbox = local
    _fill(inbox)
    sched = _schedule(store, tenant, inbox)
    store.schedules.update_any_tenant(sched["id"], {"next_run_at": time.time() - 1})
    with caplog.at_level(logging.INFO, logger="orchard.schedules"):
        ScheduleClock(store, settings).tick()
    line = [r.getMessage() for r in caplog.records if sched["id"] in r.getMessage()][-1]
    assert "1 new jobs" in line and "2 rejected" in line and "3 ignored" in line


def test_the_schedules_resource_tells_every_captures_fate(client_a, client_b, api_data):
    inbox = tenant_inbox(api_data, "farm-a", "fates")
    _fill(inbox)
    sid = client_a.post("/v1/schedules", json={"inbox": str(inbox)}).json()["id"]
    try:
        run = client_a.post(f"/v1/schedules/{sid}/run").json()
        assert sorted(i["file"] for i in run["ignored"]) == ["notes.txt", "old", "scan.csv"]
        body = client_a.get(f"/v1/schedules/{sid}").json()
        got = {c["file"]: c for c in body["captures"]}
        assert got["bad.laz"]["fate"] == "rejected" and "LASF" in got["bad.laz"]["reason"]
        assert got["notes.txt"]["fate"] == "ignored" and ".txt" in got["notes.txt"]["reason"]
        assert got["good.laz"]["fate"] == "processed" and got["good.laz"]["job_id"] == run["jobs"][0]
        assert got["bad.laz"]["seen_at"]
        assert body["capture_counts"]["rejected"] == 2 and body["capture_counts"]["ignored"] == 3
        assert client_b.get(f"/v1/schedules/{sid}").status_code == 404
    finally:
        for jid in run["jobs"]:
            client_a.delete(f"/v1/jobs/{jid}")
        client_a.delete(f"/v1/schedules/{sid}")


def test_the_command_lines_list_tells_every_captures_fate(tmp_path, monkeypatch, capsys):
    from service.cli import main

    data = tmp_path / "data"
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    _fill(inbox)
    monkeypatch.setenv("ORCHARD_CAPTURE_SETTLE_S", "0")
    assert main(["schedules", "create", "--tenant", "farm-x", "--inbox", str(inbox), "--data-dir", str(data)]) == 0
    sid = capsys.readouterr().out.strip()
    assert main(["schedules", "run", sid, "--data-dir", str(data)]) == 0
    capsys.readouterr()
    assert main(["schedules", "list", "--data-dir", str(data)]) == 0
    out = capsys.readouterr().out
    lines = {line.split()[1]: line for line in out.splitlines() if line.startswith("    ")}
    assert lines["bad.laz"].split()[0] == "rejected" and "LASF" in lines["bad.laz"]
    assert lines["scan.csv"].split()[0] == "ignored" and ".csv" in lines["scan.csv"]
    assert lines["good.laz"].split()[0] == "processed" and "(queued)" in lines["good.laz"]
    assert "captures: 2 rejected, 1 processed, 3 ignored" in out
    assert main(["schedules", "list", "--json", "--data-dir", str(data)]) == 0
    import json

    listed = json.loads(capsys.readouterr().out)[0]
    assert {c["fate"] for c in listed["captures"]} == {"processed", "rejected", "ignored"}
