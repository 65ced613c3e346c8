"""The server's own faults (a full disk, a busy job store) answered as such, on a real
uvicorn server on loopback running in this process, so the fault can be injected."""

from __future__ import annotations

import errno
import sqlite3

import httpx
import pytest
from service_fixtures import app_in_thread, make_token, write_las

from service.api.uploads import FilePart
from service.db.accounts import Accounts
from service.db.job_queue import JobQueue
from service.settings import Settings


@pytest.fixture()
def server(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", runner=False, scheduling=False)
    with app_in_thread(settings) as url:
        token = make_token(settings.data_dir, "farm")
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=30) as c:
            yield settings, c


def test_an_upload_to_a_full_disk_is_507_and_leaves_nothing(server, tmp_path, monkeypatch, caplog):
    # it was a 422 "the multipart body is malformed": the farm was told the fault was its
    # own, and the operator heard nothing
    settings, c = server
    block = write_las(tmp_path / "b.laz", 3000, seed=3)
    real = FilePart._data

    def full(self, data, start, end):
        real(self, data, start, min(end, start + 1000))  # the first kilobyte fits
        if self.size:
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(FilePart, "_data", full)
    with caplog.at_level("ERROR", logger="orchard.service"):
        r = c.post("/v1/blocks", files={"file": ("b.laz", block.read_bytes())})
    assert r.status_code == 507, r.text
    assert "no disk space left" in r.json()["detail"]
    assert any("disk is full" in rec.getMessage() for rec in caplog.records)
    assert c.get("/v1/blocks").json() == []
    assert not any(p.is_file() for p in settings.data_dir.rglob("*") if p.suffix in (".laz", ".part"))
    monkeypatch.setattr(FilePart, "_data", real)  # space again: the same upload goes through
    assert c.post("/v1/blocks", files={"file": ("b.laz", block.read_bytes())}).status_code == 201


def test_a_job_store_locked_for_too_long_is_503_with_retry_after(server, tmp_path, monkeypatch):
    # it was a 500 "internal error (OperationalError)", with the traceback logged twice
    _, c = server
    block = write_las(tmp_path / "b.laz", 3000, seed=4)
    up = c.post("/v1/blocks", files={"file": ("b.laz", block.read_bytes())}).json()

    def locked(self, **kw):
        raise sqlite3.OperationalError("database is locked")

    monkeypatch.setattr(JobQueue, "create", locked)
    r = c.post("/v1/jobs", json={"block_id": up["id"]})
    assert r.status_code == 503 and r.headers["retry-after"] == "5", r.text
    assert "busy" in r.json()["detail"]
    def full(self, **kw):
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(JobQueue, "create", full)  # the store's own disk is full: a 500 before
    r = c.post("/v1/jobs", json={"block_id": up["id"]})
    assert r.status_code == 507 and "no disk space left" in r.json()["detail"], r.text
    monkeypatch.undo()
    assert c.post("/v1/jobs", json={"block_id": up["id"]}).status_code == 201


def test_the_command_line_says_a_full_disk_is_one(tmp_path, monkeypatch, capsys):
    from service.cli import main

    def full(self, name):
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(Accounts, "ensure_tenant", full)
    assert main(["tokens", "create", "--tenant", "farm", "--data-dir", str(tmp_path / "d")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("orchard tokens: the disk is full (database or disk is full)") and "internal error" not in err
