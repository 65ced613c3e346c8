"""The job runner with captures of orchard blocks (real SQLite, the runner's own thread),
with `run_job` replaced by a fake that writes a capture's outputs by hand: a block's
captures run one at a time in arrival order, each told the output folder of the latest
capture done before it when it starts, and a failed capture leaves the block's history
as it was; and the report of a capture."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import threading

import pytest
from seasons_fixtures import write_capture_outputs
from service_fixtures import write_las
from test_service_report import _outputs

from pipeline.errors import ParameterError
from service import seasons
from service.db.block_files import accept_block
from service.db.jobstore import Store
from service.jobfolders import job_dir
from service.reports.outputs import ensure_report
from service.runner import Runner
from service.wording import job_error
from service.schedules import file_sha256
from service.settings import Settings

import workers.job as workers_job
import workers.jobspec as workers_jobspec

CAPTURE_FIELDS = ("previous", "capture_id", "captured_at", "captured_at_fallback")


@dataclasses.dataclass
class _CaptureSpec(workers_jobspec.JobSpec):
    """JobSpec with the capture fields of the contract (core's JobSpec has them once
    its branch is merged; this keeps the runner's side testable before)."""

    previous: str | None = None
    capture_id: str | None = None
    captured_at: str | None = None
    captured_at_fallback: str | None = None


@pytest.fixture()
def env(tmp_path, monkeypatch):
    if not {f.name for f in dataclasses.fields(workers_jobspec.JobSpec)} >= set(CAPTURE_FIELDS):
        monkeypatch.setattr(workers_jobspec, "JobSpec", _CaptureSpec)
    settings = Settings(data_dir=tmp_path / "data", runner_poll_s=0.05, job_retries=0)
    store = Store(settings.store_path)
    tenant = store.accounts.ensure_tenant("farm")
    yield settings, store, tenant
    store.close()


def _capture(store, tenant, ob, n, **kw):
    block, _ = store.blocks.insert(tenant_id=tenant["id"], sha256=f"{n:064x}", path=f"/x/{n}.laz", filename=f"scan{n}.laz",
                                  size_bytes=1, info={})
    return store.orchard_blocks.create_capture(tenant_id=tenant["id"], orchard_block_id=ob["id"], block_id=block["id"], job={}, **kw)
    return store.orchard_blocks.create_capture(tenant_id=tenant["id"], orchard_block_id=ob["id"], block_id=block["id"], job={}, **kw)


def _run_all(store, settings, fake, monkeypatch, expect: int) -> None:
    """Run the runner thread until ``expect`` jobs are final."""
    monkeypatch.setattr(workers_job, "run_job", fake)
    runner = Runner(store, settings, client_factory=lambda: None)
    runner.start()
    try:
        for _ in range(600):
            if sum(j["state"] in ("done", "failed", "cancelled") for j in store.jobs.list(store.accounts.list_tenants()[0]["id"])) >= expect:
                break
            threading.Event().wait(0.05)
    finally:
        runner.stop()


def test_captures_run_in_order_each_with_the_previous_done_one(env, monkeypatch):
    settings, store, tenant = env
    north, south = store.orchard_blocks.create(tenant["id"], "north"), store.orchard_blocks.create(tenant["id"], "south")
    n1 = _capture(store, tenant, north, 1, captured_at="2026-04-01")
    n2 = _capture(store, tenant, north, 2)  # fails: no overlap with n1
    n3 = _capture(store, tenant, north, 3)
    s1 = _capture(store, tenant, south, 4)
    seen = []

    def fake(spec, *, client, progress, cancel):
        seen.append({k: getattr(spec, k) for k in CAPTURE_FIELDS} | {"out": spec.out_dir})
        if spec.capture_id == n2["id"]:
            raise ParameterError("the capture does not overlap the block's previous capture")
        write_capture_outputs(spec.out_dir, "c1" if spec.previous is None else "c2")
        return workers_jobspec.JobOutcome(10, 7, 1, [], False, {}, {}, trees={})

    _run_all(store, settings, fake, monkeypatch, expect=4)
    by_capture = {s["capture_id"]: s for s in seen}
    assert [s["capture_id"] for s in seen if s["capture_id"] != s1["id"]] == [n1["id"], n2["id"], n3["id"]]
    assert by_capture[n1["id"]]["previous"] is None and by_capture[n1["id"]]["captured_at"] == "2026-04-01"
    first_out = str(job_dir(settings, n1["job_id"]).absolute())
    assert by_capture[n2["id"]]["previous"] == first_out
    # the failed capture is passed over: the third registers to the first
    assert by_capture[n3["id"]]["previous"] == first_out
    assert by_capture[s1["id"]]["previous"] is None  # another block's captures never mix in
    assert by_capture[n3["id"]]["captured_at"] is None and len(by_capture[n3["id"]]["captured_at_fallback"]) == 10
    caps = {c["id"]: c for c in store.orchard_blocks.list_captures(tenant["id"], north["id"])}
    assert [caps[c["id"]]["state"] for c in (n1, n2, n3)] == ["done", "failed", "done"]
    assert "does not overlap" in job_error(caps[n2["id"]]) and caps[n2["id"]]["record"] is None
    # each done capture keeps its outputs' record: date from the file, the registration
    assert caps[n3["id"]]["record"]["registration"]["residual_m"] == 0.021
    assert (caps[n3["id"]]["captured_at"], caps[n3["id"]]["captured_at_source"]) == ("2026-07-01", "file")
    assert store.orchard_blocks.latest_done_capture(tenant["id"], north["id"])["id"] == n3["id"]


def test_a_failed_capture_leaves_the_blocks_history_as_it_was(env, monkeypatch):
    settings, store, tenant = env
    ob = store.orchard_blocks.create(tenant["id"], "north")
    first = _capture(store, tenant, ob, 1)
    second = _capture(store, tenant, ob, 2)

    def fake(spec, *, client, progress, cancel):
        if spec.capture_id == second["id"]:
            raise RuntimeError("killed during registration")
        write_capture_outputs(spec.out_dir, "c1")
        return workers_jobspec.JobOutcome(10, 7, 1, [], False, {}, {}, trees={})

    _run_all(store, settings, fake, monkeypatch, expect=2)
    assert store.jobs.get_any_tenant(second["job_id"])["state"] == "failed"
    latest = store.orchard_blocks.latest_done_capture(tenant["id"], ob["id"])
    assert latest["id"] == first["id"]
    assert (job_dir(settings, latest["job_id"]) / seasons.HISTORY).is_file()


def test_a_plain_job_is_told_nothing_of_captures(env):
    settings, store, tenant = env
    block, _ = store.blocks.insert(tenant_id=tenant["id"], sha256="ab" * 32, path="/x/b.laz", filename="b.laz", size_bytes=1, info={})
    job = store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
    assert seasons.capture_job_fields(store, settings, job) == {}


def test_the_record_is_read_from_the_outputs(tmp_path):
    write_capture_outputs(tmp_path / "out", "c2")
    rec = seasons.capture_record(tmp_path / "out")
    assert rec["previous_capture_id"] == "c1" and rec["counts"]["removed"] == 1
    assert seasons.capture_record(tmp_path / "nothing") is None


def test_the_report_of_a_capture_names_its_block_and_carries_its_history(env, tmp_path):
    settings, store, tenant = env
    ob = store.orchard_blocks.create(tenant["id"], "North")
    src = write_las(tmp_path / "july.las", 2_000, seed=4)
    block, _ = accept_block(store, blocks_dir=settings.blocks_dir, tenant_id=tenant["id"], tmp_path=src,
                            sha256=file_sha256(src), size_bytes=src.stat().st_size, filename="july.las")
    cap = store.orchard_blocks.create_capture(tenant_id=tenant["id"], orchard_block_id=ob["id"], block_id=block["id"], job={})
    assert store.jobs.claim_next()["id"] == cap["job_id"]
    out = job_dir(settings, cap["job_id"])
    write_capture_outputs(out, "c2")
    points, _ = _outputs(tmp_path, 2_000)
    shutil.copy(points, out / "points.parquet")
    store.orchard_blocks.set_capture_record(cap["job_id"], seasons.capture_record(out))
    job = store.jobs.finish(cap["job_id"], "done", outcome={"n_trees": 8})
    text = ensure_report(store, settings, job).read_text()
    assert "North (capture 1)" in text and "2026-07-01" in text
    data = json.loads(re.search(r'<script type="application/json" id="orchard-data">(.*?)</script>', text, re.S).group(1))
    assert data["history"]["dates"] == ["2026-04-01", "2026-07-01"] and data["text"]["status"].count("same") == 6
    assert "Height change [m]" in text and "history.parquet" in text  # the static table's column, the download
