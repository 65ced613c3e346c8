"""The runner's job on a real (in-process) dask cluster: the merge, which streams every
point's labels, and the report, which reads the block's points and draws the map, run as
tasks on its workers, and give the files the job gives without a cluster."""

from __future__ import annotations

import dataclasses

import pyarrow.parquet as pq
import pytest
from service_fixtures import simulated_block

from service.db.jobstore import Store
from service.jobfolders import job_dir
from service.reports.outputs import ensure_report
from service.runner import Runner
from service.settings import Settings
from workers.job import run_job


@pytest.fixture()
def env(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", runner_poll_s=0.05, job_retries=0)
    store = Store(settings.store_path)
    tenant = store.accounts.ensure_tenant("farm")
    path = simulated_block(tmp_path / "b.laz", rows=2, trees_per_row=3, seed=5, density=0.15)
    block, _ = store.blocks.insert(tenant_id=tenant["id"], sha256="cd" * 32, path=str(path), filename="b.laz",
                                  size_bytes=path.stat().st_size, info={})
    yield settings, store, tenant, block
    store.close()


def test_the_merge_and_the_report_run_on_a_worker_and_write_what_a_job_without_a_cluster_writes(
        env, dask_client, monkeypatch, tmp_path):
    settings, store, tenant, block = env
    store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={"tiling": {"tile_size": 20.0}})
    job = store.jobs.claim_next()
    keys, submit = [], dask_client.submit
    monkeypatch.setattr(dask_client, "submit", lambda fn, *a, **k: keys.append(k["key"]) or submit(fn, *a, **k))

    def after_done(done, **drawing):  # as the app's
        ensure_report(store, settings, done, **drawing)

    runner = Runner(store, settings, client_factory=lambda: dask_client, after_done=after_done)
    done = runner.run_job(job)
    assert done["state"] == "done", done.get("error")
    assert done["tiles_total"] > 1
    assert sum(k.startswith("orchard-merge-") for k in keys) == 1
    assert sum(k.startswith("orchard-report-") for k in keys) == 1
    monkeypatch.undo()

    out = job_dir(settings, job["id"])
    alone = dataclasses.replace(runner._spec(job, block), out_dir=str(tmp_path / "alone"), work_dir=str(tmp_path / "w"))
    here = run_job(alone)  # the same job's tiles, merge and outputs in this process
    assert here.n_trees == done["outcome"]["n_trees"] > 0
    for name in ("points.parquet", "trees.parquet", "rows.parquet"):
        assert pq.read_table(out / name).equals(pq.read_table(tmp_path / "alone" / name)), name

    # the report the worker drew from the job's sample is the one drawn here from the files
    drawn = {name: (out / name).read_bytes() for name in ("report.html", "map.png")}
    (out / "report.html").unlink()
    (out / "map.png").unlink()
    ensure_report(store, settings, done)
    assert (out / "map.png").read_bytes() == drawn["map.png"]
    assert (out / "report.html").read_bytes() == drawn["report.html"]
