"""Tokens: ids, visible prefixes, listing, revoking by id, expiry, a store written
before tokens had ids, and a data folder readable by the service user only."""

from __future__ import annotations

import hashlib
import os
import sqlite3
import stat
import subprocess
import sys
import time

import pytest
from fastapi.testclient import TestClient
from service_fixtures import client_of, write_las

from service.app import create_app
from service.auth import TOUCH_INTERVAL_S, UnauthorizedError, authenticate, create_token, hash_token, issue_token
from service.cli import main
from service.db.jobstore import Store
from service.permissions import tighten
from service.settings import Settings


@pytest.fixture()
def store(tmp_path):
    s = Store(tmp_path / "data" / "orchard.sqlite")
    yield s
    s.close()


def _mode(path) -> int:
    return stat.S_IMODE(os.lstat(path).st_mode)


def test_a_token_has_an_id_and_a_visible_prefix_that_are_not_secret(store):
    token, rec = issue_token(store, "farm")
    prefix, sep, secret = token[:13], token[13], token[14:]  # (the secret may hold "_" too)
    assert sep == "_"
    assert rec["prefix"] == prefix and prefix.startswith("orch_") and len(prefix) == 13
    assert len(secret) == 43 and len(rec["id"]) == 12
    listed = store.accounts.list_tokens_any_tenant()
    assert [(t["tenant"], t["id"], t["prefix"]) for t in listed] == [("farm", rec["id"], prefix)]
    assert "hash" not in listed[0] and secret not in repr(listed)
    assert token.encode() not in store.path.read_bytes()
    other = create_token(store, "farm")
    assert other[:13] != prefix  # 36^8 prefixes: two tokens tell apart


def test_tokens_are_listed_per_tenant_with_their_last_use(store):
    a1, rec_a1 = issue_token(store, "farm-a")
    issue_token(store, "farm-b")
    t0 = time.time()
    assert authenticate(store, f"Bearer {a1}", now=t0)["name"] == "farm-a"
    tenant_a = store.accounts.tenant_by_name("farm-a")
    [row] = store.accounts.list_tokens(tenant_a["id"])
    assert row["id"] == rec_a1["id"] and row["last_used_at"] == t0
    # a request a second later writes nothing (one write a minute at most), a later one does
    authenticate(store, f"Bearer {a1}", now=t0 + 1)
    assert store.accounts.list_tokens(tenant_a["id"])[0]["last_used_at"] == t0
    authenticate(store, f"Bearer {a1}", now=t0 + TOUCH_INTERVAL_S)
    assert store.accounts.list_tokens(tenant_a["id"])[0]["last_used_at"] == t0 + TOUCH_INTERVAL_S
    assert [t["tenant"] for t in store.accounts.list_tokens_any_tenant()] == ["farm-a", "farm-b"]


def test_revoke_by_id_refuses_that_token_only(store):
    keep, _ = issue_token(store, "farm")
    gone, rec = issue_token(store, "farm")
    assert store.accounts.revoke_token_id(rec["id"])
    assert not store.accounts.revoke_token_id(rec["id"])
    with pytest.raises(UnauthorizedError, match="unknown or revoked"):
        authenticate(store, f"Bearer {gone}")
    assert authenticate(store, f"Bearer {keep}")["name"] == "farm"


def test_an_expired_token_is_refused_saying_so(store):
    token, rec = issue_token(store, "farm", expires_in_s=3600)
    assert rec["expires_at"] == pytest.approx(time.time() + 3600, abs=5)
    assert authenticate(store, f"Bearer {token}", now=rec["expires_at"] - 1)["name"] == "farm"
    with pytest.raises(UnauthorizedError, match=rf"token {rec['prefix']} expired at "):
        authenticate(store, f"Bearer {token}", now=rec["expires_at"])
    with pytest.raises(ValueError):
        issue_token(store, "farm", expires_in_s=0)


def test_a_store_written_before_token_ids_keeps_its_tokens(tmp_path):
    # the tokens table as an earlier version wrote it: hash, tenant, time, nothing else
    path = tmp_path / "orchard.sqlite"
    con = sqlite3.connect(path)
    con.executescript(
        "CREATE TABLE tenants (id TEXT PRIMARY KEY, name TEXT NOT NULL UNIQUE, created_at REAL NOT NULL);"
        "CREATE TABLE tokens (hash TEXT PRIMARY KEY, tenant_id TEXT NOT NULL REFERENCES tenants(id), created_at REAL NOT NULL);"
    )
    old = "orch_" + "x" * 43
    con.execute("INSERT INTO tenants VALUES ('t1', 'farm', 1.0)")
    con.execute("INSERT INTO tokens VALUES (?, 't1', 2.0)", (hashlib.sha256(old.encode()).hexdigest(),))
    con.commit()
    con.close()
    store = Store(path)
    try:
        assert authenticate(store, f"Bearer {old}")["name"] == "farm"
        [row] = store.accounts.list_tokens_any_tenant()
        assert row["prefix"] is None and row["expires_at"] is None and row["created_at"] == 2.0
        assert len(row["id"]) == 12 and row["last_used_at"] is not None
        store.close()
        store = Store(path)  # opening it again changes nothing
        assert [t["id"] for t in store.accounts.list_tokens_any_tenant()] == [row["id"]]
        assert store.accounts.revoke_token_id(row["id"])
        with pytest.raises(UnauthorizedError):
            authenticate(store, f"Bearer {old}")
    finally:
        store.close()


def test_cli_create_list_revoke(tmp_path, capsys):
    data = tmp_path / "data"
    assert main(["tokens", "create", "--tenant", "farm", "--expires-in", "2w", "--data-dir", str(data)]) == 0
    out, err = capsys.readouterr()
    token = out.strip()
    assert out == token + "\n"  # only the token on stdout: TOKEN=$(orchard tokens create ...)
    assert f"data folder {data}" in err and token[:13] in err and token not in err
    assert main(["tokens", "create", "--tenant", "other", "--data-dir", str(data)]) == 0
    capsys.readouterr()
    assert main(["tokens", "list", "--tenant", "farm", "--data-dir", str(data)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split("\t") == ["tenant", "id", "prefix", "created", "last used", "expires"]
    [row] = [line.split("\t") for line in lines[1:]]
    assert row[0] == "farm" and row[2] == token[:13] and row[4] == "never"
    assert row[5].startswith(time.strftime("%Y", time.gmtime(time.time() + 14 * 86400)))
    assert main(["tokens", "revoke", row[1], "--data-dir", str(data)]) == 0
    assert main(["tokens", "revoke", row[1], "--data-dir", str(data)]) == 3  # not found
    assert "tokens list" in capsys.readouterr().err
    assert main(["tokens", "list", "--data-dir", str(data)]) == 0
    assert [line.split("\t")[0] for line in capsys.readouterr().out.splitlines()[1:]] == ["other"]


@pytest.mark.parametrize("lifetime", ["90", "0d", "-1d", "5y", "100000w"])
def test_cli_refuses_a_lifetime_without_unit_or_out_of_range(tmp_path, lifetime):
    r = subprocess.run(
        [sys.executable, "-m", "service.cli", "tokens", "create", "--tenant", "farm", "--expires-in", lifetime,
         "--data-dir", str(tmp_path / "data")],
        capture_output=True, text=True, timeout=120,
    )
    assert r.returncode == 2 and "--expires-in" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_the_store_is_private_from_its_creation(tmp_path):
    store = Store(tmp_path / "data" / "orchard.sqlite")
    try:
        issue_token(store, "farm")  # (writes the -wal file)
        assert _mode(tmp_path / "data") == 0o700
        for name in ("orchard.sqlite", "orchard.sqlite-wal", "orchard.sqlite-shm"):
            assert _mode(tmp_path / "data" / name) == 0o600, name
    finally:
        store.close()


def test_the_service_tightens_its_data_folder_at_start_and_leaves_inboxes_alone(tmp_path):
    data = tmp_path / "data"
    (data / "jobs" / "j1").mkdir(parents=True)
    (data / "jobs" / "j1" / "trees.parquet").write_bytes(b"x")
    inbox = data / "inboxes" / "farm" / "in"
    inbox.mkdir(parents=True)
    (inbox / "capture.laz").write_bytes(b"x")
    for p in (data, data / "jobs", data / "jobs" / "j1", data / "inboxes", inbox):
        p.chmod(0o755)
    for p in (data / "jobs" / "j1" / "trees.parquet", inbox / "capture.laz"):
        p.chmod(0o644)
    os.symlink("/etc/hostname", data / "jobs" / "link")
    settings = Settings(data_dir=data, runner=False, scheduling=False)
    with TestClient(create_app(settings)) as started:
        c = client_of(started, token=create_token(Store(settings.store_path), "farm"))
        up = c.post("/v1/blocks", files={"file": ("b.laz", write_las(tmp_path / "b.laz", 300, seed=2).read_bytes())})
        assert up.status_code == 201, up.text
    for p in (data, data / "jobs", data / "jobs" / "j1", data / "blocks", data / "tmp"):
        assert _mode(p) == 0o700, p
    blocks = list((data / "blocks").iterdir())
    assert blocks and all(_mode(p) == 0o600 for p in blocks)
    assert _mode(data / "jobs" / "j1" / "trees.parquet") == 0o600
    assert _mode(data / "orchard.sqlite") == 0o600
    # the farm's inbox and capture as they were; the symlink's target untouched
    assert _mode(data / "inboxes") == 0o755 and _mode(inbox) == 0o755 and _mode(inbox / "capture.laz") == 0o644
    assert os.path.islink(data / "jobs" / "link")
    # once private, a start changes nothing more outside the inboxes (the server's own
    # temporary folder may be made private only now: in tests there is no umask 077)
    tighten(data, skip=[data / "inboxes"])
    assert tighten(data, skip=[data / "inboxes"]) == 0


def test_the_401_of_a_token_from_another_data_folder_says_how_to_make_one_for_this_server(tmp_path):
    settings = Settings(data_dir=tmp_path / "served", runner=False, scheduling=False)
    elsewhere = create_token(Store(tmp_path / "elsewhere" / "orchard.sqlite"), "farm")
    with TestClient(create_app(settings)) as c:
        r = c.get("/v1/jobs", headers={"Authorization": f"Bearer {elsewhere}"})
    assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    detail = r.json()["detail"]
    assert "unknown or revoked token" in detail and "--data-dir DIR" in detail and "on the server" in detail
    assert str(tmp_path) not in detail  # the server's paths are not the client's business


def test_the_server_log_names_its_data_folder(tmp_path, caplog):
    settings = Settings(data_dir=tmp_path / "data", runner=False, scheduling=False)
    with caplog.at_level("INFO", logger="orchard.service"):
        with TestClient(create_app(settings)):
            pass
    assert any(f"data folder {settings.data_dir}" in rec.getMessage() for rec in caplog.records)


def test_an_expired_token_is_a_401_over_http(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", runner=False, scheduling=False)
    store = Store(settings.store_path)
    token, rec = issue_token(store, "farm", expires_in_s=3600)
    store.db.connection().execute("UPDATE tokens SET expires_at = ? WHERE id = ?", (time.time() - 1, rec["id"]))
    store.close()
    with TestClient(create_app(settings)) as c:
        r = c.get("/v1/jobs", headers={"Authorization": f"Bearer {token}"})
    assert r.status_code == 401 and "expired at" in r.json()["detail"], r.text
    assert hash_token(token) not in r.text
