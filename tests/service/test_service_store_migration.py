"""A job store written before a job's parameters were stored whole: its ``params`` and
``tiling`` columns become the one ``job`` column, in place.

``data/store-before-job-column.sqlite`` was written by the code of commit 5a744fe (the
store's two columns) with::

    git archive 5a744fe service pipeline workers simulator | tar -x -C /tmp/oldtree
    cd /tmp/oldtree && PYTHONPATH=$PWD python $REPO/tests/service/data/make_old_store.py \
        $REPO/tests/service/data/store-before-job-column.sqlite

creating a tenant, a block, a running tiled job with its own parameters, a failed job
(its error stored as text), a tiled schedule and an untiled one.
"""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import pytest

from pipeline.jobparams import JobParams
from service.api.schemas import job_out, schedule_out
from service.db.jobstore import Store
from service.wording import job_error

OLD = Path(__file__).parent / "data" / "store-before-job-column.sqlite"


@pytest.fixture()
def old_store(tmp_path):
    path = tmp_path / "orchard.sqlite"
    shutil.copyfile(OLD, path)
    return path


def _columns(path, table):
    con = sqlite3.connect(path)
    try:
        return {r[1] for r in con.execute(f"PRAGMA table_info({table})")}
    finally:
        con.close()


def test_the_fixture_is_a_store_of_two_columns():
    assert {"params", "tiling"} <= _columns(OLD, "jobs") and "job" not in _columns(OLD, "jobs")
    assert {"params", "tiling"} <= _columns(OLD, "schedules")


def test_params_and_tiling_become_one_job_column_in_place(old_store):
    store = Store(old_store)
    try:
        for table in ("jobs", "schedules"):
            cols = _columns(old_store, table)
            assert "job" in cols and not {"params", "tiling"} & cols, table
        jobs = {j["state"]: j for j in store.jobs.list(store.accounts.tenant_by_name("farm")["id"])}
        tiled = jobs["running"]["job"]
        assert tiled == {"pipeline": {"segment": {"max_crown_radius": 2.0}}, "tiling": {"tile_size": 20.0, "buffer": 4.0}}
        job = JobParams.model_validate(tiled)  # what the runner makes of it
        assert job.pipeline.segment.max_crown_radius == 2.0 and job.buffer() == 4.0
        assert jobs["failed"]["job"] == {"pipeline": {}, "tiling": {}}
        assert JobParams.model_validate(jobs["failed"]["job"]) == JobParams()
        # the API shows them as before: the request's parameters and tiling (null: one tile)
        assert job_out(jobs["running"]).tiling == {"tile_size": 20.0, "buffer": 4.0}
        assert job_out(jobs["failed"]).tiling is None and job_out(jobs["failed"]).params == {}
        # an error stored as text before failures had kinds is said as it was
        assert job_error(jobs["failed"]) == "north.laz: no trees found in 100 points"
        assert job_out(jobs["failed"]).error == "north.laz: no trees found in 100 points"
        scheds = {s["inbox"]: s for s in store.schedules.list_any_tenant()}
        assert scheds["/in/a"]["job"] == {"pipeline": {"trunks": {"min_tree_height": 1.5}}, "tiling": {"tile_size": 30.0, "buffer": None}}
        assert schedule_out(scheds["/in/a"]).tiling == {"tile_size": 30.0, "buffer": None}
        assert schedule_out(scheds["/in/b"]).tiling is None
    finally:
        store.close()


def test_the_merged_store_keeps_working_and_is_not_merged_twice(old_store):
    store = Store(old_store)
    try:
        tenant = store.accounts.tenant_by_name("farm")
        assert store.jobs.requeue_running() == 1  # the running job of the old service
        again = store.jobs.claim_next()
        assert again["job"]["tiling"]["tile_size"] == 20.0
        store.jobs.finish(again["id"], "failed", error_kind="no_trees", error_fields={"message": "no trees found"})
        new = store.jobs.create(tenant_id=tenant["id"], block_id=again["block_id"], job=JobParams().model_dump(mode="json"))
        assert JobParams.model_validate(new["job"]) == JobParams()
    finally:
        store.close()
    second = Store(old_store)  # opened again (another process): nothing left to merge
    try:
        assert job_error(second.jobs.get_any_tenant(again["id"])) == "no trees found"
        assert len(second.jobs.list(tenant["id"])) == 3
    finally:
        second.close()


def test_a_merge_that_fails_leaves_the_store_as_it_was(old_store):
    con = sqlite3.connect(old_store)
    con.execute("UPDATE schedules SET params = 'not json' WHERE inbox = '/in/b'")
    con.commit()
    con.close()
    with pytest.raises(ValueError):
        Store(old_store)
    # one transaction: the jobs' merge, done before the schedules', was rolled back with it
    assert {"params", "tiling"} <= _columns(old_store, "jobs") and "job" not in _columns(old_store, "jobs")
    assert {"params", "tiling"} <= _columns(old_store, "schedules")
