"""Tenants kept apart: every lookup of the store that serves a tenant takes the tenant and
gives another tenant's record to nobody (a NotFoundError, nothing, or a 404 at the
API), and the lookups that serve every tenant say so in their names."""

from __future__ import annotations

import inspect

import pytest
from service_fixtures import client_of, make_token, write_las

from service.db.errors import NotFoundError
from service.db.jobstore import Store


@pytest.fixture()
def two_farms(tmp_path):
    """A store where farm A has one of everything; farm B has nothing."""
    store = Store(tmp_path / "orchard.sqlite")
    a, b = store.accounts.ensure_tenant("farm-a"), store.accounts.ensure_tenant("farm-b")
    block, _ = store.blocks.insert(tenant_id=a["id"], sha256="ab" * 32, path="/x/a.las", filename="a.las",
                                   size_bytes=10, info={})
    job = store.jobs.create(tenant_id=a["id"], block_id=block["id"], job={})
    ob = store.orchard_blocks.create(a["id"], "north")
    capture = store.orchard_blocks.create_capture(tenant_id=a["id"], orchard_block_id=ob["id"], block_id=block["id"],
                                                  job={})
    with store.db.transaction() as con:  # the capture's job done, as the runner would leave it
        con.execute("UPDATE jobs SET state = 'done' WHERE id = ?", (capture["job_id"],))
    sched = store.schedules.create(tenant_id=a["id"], inbox=str(tmp_path / "inbox"), cron="0 2 * * *", job={}, next_run_at=None)
    hook = store.webhooks.create(tenant_id=a["id"], url="https://example.org/", secret="s" * 32, schedule_id=None,
                                 events=["job.done"])
    ids = {"block": block, "job": job, "ob": ob, "capture": capture, "schedule": sched, "webhook": hook}
    yield store, a, b, ids
    store.close()


#: (what, call): each lookup of the store that serves a tenant, asked by ``t`` for farm A's ``r``ecords
SCOPED = [
    ("block", lambda s, t, r: s.blocks.get(t, r["block"]["id"])),
    ("job", lambda s, t, r: s.jobs.get(t, r["job"]["id"])),
    ("cancel", lambda s, t, r: s.jobs.request_cancel(t, r["job"]["id"])),
    ("orchard block", lambda s, t, r: s.orchard_blocks.get(t, r["ob"]["id"])),
    ("orchard block by name", lambda s, t, r: s.orchard_blocks.by_name(t, "north")),
    ("captures", lambda s, t, r: s.orchard_blocks.list_captures(t, r["ob"]["id"])),
    ("capture", lambda s, t, r: s.orchard_blocks.get_capture(t, r["capture"]["id"])),
    ("capture a schedule", lambda s, t, r: s.schedules.create(tenant_id=t, inbox="/elsewhere", cron="0 2 * * *",
                                                              job={}, next_run_at=None,
                                                              orchard_block_id=r["ob"]["id"])),
    ("schedule", lambda s, t, r: s.schedules.get(t, r["schedule"]["id"])),
    ("schedule change", lambda s, t, r: s.schedules.update(t, r["schedule"]["id"], {"paused": True})),
    ("schedule deletion", lambda s, t, r: s.schedules.delete(t, r["schedule"]["id"])),
    ("webhook", lambda s, t, r: s.webhooks.get(t, r["webhook"]["id"])),
    ("webhook deliveries", lambda s, t, r: s.webhooks.deliveries(t, r["webhook"]["id"])),
    ("webhook deletion", lambda s, t, r: s.webhooks.delete(t, r["webhook"]["id"])),
]

#: lookups that answer "nothing" rather than NotFoundError
EMPTY = [
    ("blocks", lambda s, t, r: s.blocks.list(t)),
    ("block by content", lambda s, t, r: s.blocks.by_sha(t, "ab" * 32)),
    ("jobs", lambda s, t, r: s.jobs.list(t)),
    ("job count", lambda s, t, r: s.jobs.count(t)),
    ("orchard blocks", lambda s, t, r: s.orchard_blocks.list(t)),
    ("capture of a job", lambda s, t, r: s.orchard_blocks.capture_of_job(t, r["capture"]["job_id"])),
    ("latest done capture", lambda s, t, r: s.orchard_blocks.latest_done_capture(t, r["ob"]["id"])),
    ("schedules", lambda s, t, r: s.schedules.list(t)),
    ("webhooks", lambda s, t, r: s.webhooks.list(t)),
    ("tokens", lambda s, t, r: s.accounts.list_tokens(t)),
]


@pytest.mark.parametrize(("what", "call"), SCOPED, ids=[w for w, _ in SCOPED])
def test_another_farm_cannot_reach_a_record_through_a_scoped_lookup(two_farms, what, call):
    store, a, b, recs = two_farms
    with pytest.raises(NotFoundError):
        call(store, b["id"], recs)
    call(store, a["id"], recs)  # the owner can: the lookup itself works


@pytest.mark.parametrize(("what", "call"), EMPTY, ids=[w for w, _ in EMPTY])
def test_another_farm_lists_nothing_of_a_farms(two_farms, what, call):
    store, a, b, recs = two_farms
    assert not call(store, b["id"], recs)
    assert call(store, a["id"], recs) or what == "tokens"  # the owner's own (farm A made no token)


def test_no_lookup_takes_no_tenant_for_any_tenant(two_farms):
    # `tenant_id=None` meant "any tenant": one forgotten argument from a cross-tenant read
    store = two_farms[0]
    parts = [type(part) for part in vars(store).values() if getattr(part, "db", None) is store.db]
    assert len(parts) == 7
    checked = 0
    for cls in parts:
        for name, fn in inspect.getmembers(cls, inspect.isfunction):
            param = inspect.signature(fn).parameters.get("tenant_id")
            if param is None or name.startswith("_"):
                continue
            checked += 1
            assert param.default is inspect.Parameter.empty, f"{cls.__name__}.{name}: the tenant has a default"
            assert param.annotation in ("str", str), f"{cls.__name__}.{name}: tenant_id: {param.annotation}"
            assert not name.endswith("_any_tenant"), f"{cls.__name__}.{name} takes a tenant"
    assert checked >= 25


def test_the_unscoped_lookups_are_named_so(two_farms):
    store, a, _, recs = two_farms
    assert store.jobs.get_any_tenant(recs["job"]["id"])["tenant_id"] == a["id"]
    assert store.schedules.get_any_tenant(recs["schedule"]["id"])["tenant_id"] == a["id"]
    assert [s["id"] for s in store.schedules.list_any_tenant()] == [recs["schedule"]["id"]]
    assert [o["id"] for o in store.orchard_blocks.list_any_tenant()] == [recs["ob"]["id"]]


# -- at the API: another farm's ids are 404, also for a finished job's report and map ------------


@pytest.fixture()
def farms(api, api_data):
    """Clients of two farms of their own in the shared app (other tests count farm-a's webhooks)."""
    a, b = (client_of(api, token=make_token(api_data, name)) for name in ("tenancy-a", "tenancy-b"))
    yield a, b
    a.close()
    b.close()


def test_another_farms_finished_job_orchard_block_and_webhook_are_404(api, farms, tmp_path):
    client_a, client_b = farms
    las = write_las(tmp_path / "a.laz", 500, seed=11)
    block = client_a.post("/v1/blocks", files={"file": ("a.laz", las.read_bytes())}).json()
    job = client_a.post("/v1/jobs", json={"block_id": block["id"]}).json()
    with api.app.state.store.db.transaction() as con:  # done: the report and the map would be drawn
        con.execute("UPDATE jobs SET state = 'done', finished_at = 1 WHERE id = ?", (job["id"],))
    ob = client_a.post("/v1/orchard-blocks", json={"name": f"tenancy-{job['id'][:8]}"}).json()
    cap = client_a.post(f"/v1/orchard-blocks/{ob['id']}/captures", json={"block_id": block["id"]}).json()
    hook = client_a.post("/v1/webhooks", json={"url": "https://example.org/hook", "secret": "s" * 32}).json()
    for path in (f"/v1/jobs/{job['id']}", f"/v1/jobs/{job['id']}/report", f"/v1/jobs/{job['id']}/trees",
                 f"/web/jobs/{job['id']}/map.json", f"/v1/orchard-blocks/{ob['id']}",
                 f"/v1/orchard-blocks/{ob['id']}/captures", f"/v1/orchard-blocks/{ob['id']}/captures/{cap['id']}",
                 f"/v1/orchard-blocks/{ob['id']}/trees/1/history", f"/v1/webhooks/{hook['id']}",
                 f"/v1/webhooks/{hook['id']}/deliveries"):
        r = client_b.get(path)
        assert r.status_code == 404, (path, r.status_code, r.text)
    assert client_b.post(f"/v1/orchard-blocks/{ob['id']}/captures", json={"block_id": block["id"]}).status_code == 404
    assert client_b.delete(f"/v1/webhooks/{hook['id']}").status_code == 404
    assert client_a.get(f"/v1/webhooks/{hook['id']}").status_code == 200  # still there
    assert client_a.get(f"/v1/orchard-blocks/{ob['id']}/captures/{cap['id']}").status_code == 200
