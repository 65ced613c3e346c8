"""An inbox folder per orchard block (real folders, real SQLite): each file landing in it
is one more capture of that block, night after night, and two blocks' inboxes never mix;
and ``orchard blocks`` / ``orchard schedules --orchard-block`` on the command line."""

from __future__ import annotations

import json
import time

import pytest
from service_fixtures import write_las

from service.db.jobstore import Store
from service.schedules import ScheduleClock, run_schedule
from service.settings import Settings


@pytest.fixture()
def local(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", capture_settle_s=0)
    store = Store(settings.store_path)
    tenant = store.accounts.ensure_tenant("farm")
    yield settings, store, tenant, tmp_path
    store.close()


def _schedule(store, tenant, inbox, block):
    return store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron="0 1 * * *", job={},
                                 next_run_at=None, orchard_block_id=block["id"] if block else None)


def test_each_file_landing_in_a_blocks_inbox_is_one_more_capture(local):
    settings, store, tenant, root = local
    north, south = store.orchard_blocks.create(tenant["id"], "north"), store.orchard_blocks.create(tenant["id"], "south")
    inboxes = {}
    for ob in (north, south):
        inboxes[ob["name"]] = root / f"inbox-{ob['name']}"
        inboxes[ob["name"]].mkdir()
    s_north, s_south = _schedule(store, tenant, inboxes["north"], north), _schedule(store, tenant, inboxes["south"], south)
    # night 1: one capture in each inbox
    write_las(inboxes["north"] / "night1.laz", 300, seed=1)
    write_las(inboxes["south"] / "night1.laz", 300, seed=2)
    first = {s["id"]: run_schedule(store, settings, s) for s in (s_north, s_south)}
    assert all(len(r["jobs"]) == 1 for r in first.values())
    # night 2: the next capture of north lands; the clock's scan takes it (and nothing twice)
    write_las(inboxes["north"] / "night2.laz", 300, seed=3)
    for s in (s_north, s_south):
        store.schedules.update_any_tenant(s["id"], {"next_run_at": time.time() - 1})
    ScheduleClock(store, settings).tick()
    north_caps = store.orchard_blocks.list_captures(tenant["id"], north["id"])
    south_caps = store.orchard_blocks.list_captures(tenant["id"], south["id"])
    assert [c["seq"] for c in north_caps] == [1, 2] and len(south_caps) == 1
    files = {c["block_id"]: store.blocks.get(tenant["id"], c["block_id"])["filename"] for c in north_caps + south_caps}
    assert [files[c["block_id"]] for c in north_caps] == ["night1.laz", "night2.laz"]
    assert first[s_north["id"]]["jobs"] == [north_caps[0]["job_id"]]
    assert first[s_south["id"]]["jobs"] == [south_caps[0]["job_id"]]  # south's file is south's capture only
    # the second night's capture waits for the first of its block, not for the other block's
    claimed = [store.jobs.claim_next()["id"] for _ in range(2)]
    assert claimed == [north_caps[0]["job_id"], south_caps[0]["job_id"]] and store.jobs.claim_next() is None
    # a plain schedule beside them queues plain jobs, as before
    plain_inbox = root / "plain"
    plain_inbox.mkdir()
    write_las(plain_inbox / "x.laz", 300, seed=4)
    res = run_schedule(store, settings, _schedule(store, tenant, plain_inbox, None))
    assert len(res["jobs"]) == 1 and store.orchard_blocks.capture_of_job(tenant["id"], res["jobs"][0]) is None


def test_cli_blocks_create_list_captures_and_a_blocks_schedule(tmp_path, monkeypatch, capsys):
    from service.cli import main

    data = tmp_path / "data"
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    monkeypatch.setenv("ORCHARD_DATA_DIR", str(data))
    monkeypatch.setenv("ORCHARD_CAPTURE_SETTLE_S", "0")
    assert main(["blocks", "create", "North 12", "--tenant", "farm-x"]) == 0
    block_id = capsys.readouterr().out.strip()
    assert main(["blocks", "create", "North 12", "--tenant", "farm-x"]) == 2
    assert "already has an orchard block called 'North 12'" in capsys.readouterr().err
    assert main(["schedules", "create", "--tenant", "farm-x", "--inbox", str(inbox), "--orchard-block", "North 12"]) == 0
    sid = capsys.readouterr().out.strip()
    assert main(["schedules", "create", "--tenant", "farm-x", "--inbox", str(tmp_path), "--orchard-block", "South"]) == 3
    assert "no orchard block called 'South'" in capsys.readouterr().err
    write_las(inbox / "scan.laz", 300, seed=8)
    assert main(["schedules", "run", sid]) == 0
    jobs = json.loads(capsys.readouterr().out)["jobs"]
    assert main(["blocks", "list", "--tenant", "farm-x"]) == 0
    out = capsys.readouterr().out
    assert block_id in out and "North 12" in out
    assert main(["blocks", "captures", "North 12", "--tenant", "farm-x", "--json"]) == 0
    caps = json.loads(capsys.readouterr().out)
    assert [c["job_id"] for c in caps] == jobs and caps[0]["state"] == "queued"
    assert main(["blocks", "captures", block_id, "--tenant", "farm-x"]) == 0  # by id too
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("seq\t") and lines[1].startswith("1\t")
    assert main(["blocks", "captures", "nope", "--tenant", "farm-x"]) == 3
    err = capsys.readouterr().err
    assert "no orchard block" in err and "orchard blocks list" in err and "Traceback" not in err
    assert main(["schedules", "list", "--json"]) == 0
    assert [s["orchard_block_id"] for s in json.loads(capsys.readouterr().out)] == [block_id]
