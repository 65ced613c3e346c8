"""Overnight schedules: cron times, inbox validation, scans that never take a capture twice."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import pytest

from pipeline.errors import ParameterError
from service.schedules import ScheduleClock, next_run_time, run_schedule, validate_cron, validate_inbox
from service.settings import Settings
from service.store import Store
from service_fixtures import write_las


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


@pytest.mark.parametrize("expr", ["", "every night", "61 1 * * *", "0 25 * * *", "* * * *", "0 1 * * * *"])
def test_invalid_cron_is_refused(expr):
    with pytest.raises(ParameterError, match="cron"):
        validate_cron(expr)


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


@pytest.fixture()
def local(tmp_path):
    settings = Settings(data_dir=tmp_path / "data")
    store = Store(settings.store_path)
    tenant = store.ensure_tenant("farm")
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    yield settings, store, tenant, inbox
    store.close()


def _schedule(store, tenant, inbox, cron="0 1 * * *"):
    return store.create_schedule(tenant_id=tenant["id"], inbox=str(inbox), cron=cron, params={}, tiling=None, next_run_at=None)


def test_run_schedule_takes_each_capture_once(local):
    settings, store, tenant, inbox = local
    write_las(inbox / "a.laz", 500, seed=1)
    write_las(inbox / "b.las", 600, seed=2)
    (inbox / "notes.txt").write_text("not a capture")
    sched = _schedule(store, tenant, inbox)
    first = run_schedule(store, settings, sched)
    assert len(first["jobs"]) == 2 and first["skipped"] == 0 and first["rejected"] == []
    jobs = store.list_jobs(tenant["id"], schedule_id=sched["id"])
    assert {j["state"] for j in jobs} == {"queued"}
    again = run_schedule(store, settings, sched)
    assert again["jobs"] == [] and again["skipped"] == 2
    # the same capture copied under another name is not processed again either
    shutil.copy(inbox / "a.laz", inbox / "a-copy.laz")
    assert run_schedule(store, settings, sched)["jobs"] == []
    # a new capture is
    write_las(inbox / "c.laz", 700, seed=3)
    assert len(run_schedule(store, settings, sched)["jobs"]) == 1


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
    rec = store.get_schedule(None, sched["id"])
    assert rec["next_run_at"] == next_run_time("0 1 * * *", now).timestamp()
    assert store.list_jobs(tenant["id"]) == []
    clock.tick(rec["next_run_at"] + 1)  # the night comes
    assert len(store.list_jobs(tenant["id"])) == 1
    rec2 = store.get_schedule(None, sched["id"])
    assert rec2["last_run_at"] == rec["next_run_at"] + 1
    assert rec2["next_run_at"] > rec["next_run_at"]


def test_api_schedules_run_now(client_a, tmp_path):
    inbox = tmp_path / "inbox"
    inbox.mkdir()
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
    for jid in run["jobs"]:
        job = client_a.get(f"/v1/jobs/{jid}").json()
        assert job["schedule_id"] == sched["id"] and job["tiling"]["tile_size"] == 20
    assert client_a.post(f"/v1/schedules/{sched['id']}/run").json()["jobs"] == []
    listed = client_a.get("/v1/jobs", params={"schedule_id": sched["id"]}).json()
    assert sorted(j["id"] for j in listed) == sorted(run["jobs"])
    for jid in run["jobs"]:
        client_a.delete(f"/v1/jobs/{jid}")


@pytest.mark.parametrize(
    "body, fragment",
    [
        ({"inbox": "/definitely/not/here"}, "does not exist"),
        ({"inbox": "relative"}, "absolute"),
        ({"inbox": "~\ud872\ude05N\u00adl\u0014\u00a2\r"}, "absolute"),  # found by schemathesis: was a 500
        ({"inbox": "/tmp", "cron": "whenever"}, "cron"),
    ],
)
def test_api_bad_schedule_is_422(client_a, body, fragment):
    r = client_a.post("/v1/schedules", content=json.dumps(body), headers={"content-type": "application/json"})
    assert r.status_code == 422
    assert fragment in r.json()["detail"]


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
    assert main(["schedules", "run", sid, "--data-dir", str(data)]) == 0
    assert '"jobs": [' in capsys.readouterr().out
    store = Store(data / "orchard.sqlite")
    assert len(store.list_jobs(store.tenant_by_name("farm-x")["id"], schedule_id=sid)) == 1
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
    assert "farm-y\t1 token(s)" in capsys.readouterr().out
