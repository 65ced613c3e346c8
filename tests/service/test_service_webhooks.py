"""Webhooks: signed calls to a receiver on loopback for finished and failed jobs and
rejected captures, retried with backoff after a 500, the deliveries shown by the API."""

from __future__ import annotations

import http.server
import json
import threading
import time

import pytest
from service_fixtures import tenant_inbox

from pipeline.errors import InputError, ParameterError
from service.db.jobstore import Store
from service.runner import Runner
from service.schedules import run_schedule
from service.settings import Settings
from service.webhooks import WebhookSender, backoff_s, check_url, job_event, sign, verify

import workers.job as workers_job
import workers.jobspec as workers_jobspec

SECRET = "s3cret-of-the-farm-0123"


class Receiver:
    """An HTTP server on a loopback port of its own choosing (port 0) that keeps every
    call and answers each with the next of ``answers`` (then 200)."""

    def __init__(self, answers=()):
        self.calls: list[dict] = []
        self.answers = list(answers)
        self.got = threading.Condition()
        outer = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                with outer.got:
                    status = outer.answers.pop(0) if outer.answers else 200
                    outer.calls.append({"headers": dict(self.headers), "body": body, "status": status})
                    outer.got.notify_all()
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def wait_for(self, n: int, timeout: float = 30.0) -> list[dict]:
        with self.got:
            self.got.wait_for(lambda: len(self.calls) >= n, timeout)
        return list(self.calls)

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture()
def receiver():
    r = Receiver()
    yield r
    r.close()


@pytest.fixture()
def env(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", runner_poll_s=0.05, job_retries=0, webhook_backoff_s=0.05,
                        webhook_attempts=3, webhook_poll_s=0.05, capture_settle_s=0)
    store = Store(settings.store_path)
    tenant = store.accounts.ensure_tenant("farm")
    block, _ = store.blocks.insert(tenant_id=tenant["id"], sha256="ab" * 32, path=str(tmp_path / "b.laz"),
                                  filename="b.laz", size_bytes=1, info={})
    yield settings, store, tenant, block
    store.close()


def _checked(call) -> dict:
    h = call["headers"]
    assert verify(SECRET, h["X-Orchard-Timestamp"], call["body"], h["X-Orchard-Signature"])
    assert not verify("another secret of 16+", h["X-Orchard-Timestamp"], call["body"], h["X-Orchard-Signature"])
    assert not verify(SECRET, h["X-Orchard-Timestamp"], call["body"] + b" ", h["X-Orchard-Signature"])
    body = json.loads(call["body"])
    assert body["event"] == h["X-Orchard-Event"] and body["id"] == h["X-Orchard-Delivery"]
    return body


def test_signature_and_backoff_by_hand():
    body = b'{"event":"job.done"}'
    # HMAC-SHA256 of "<timestamp>.<body>", as a receiver computes it with hmac and hashlib
    assert sign("key-key-key-key-key", 1700000000, body) == (
        "sha256=" + __import__("hmac").new(b"key-key-key-key-key", b"1700000000." + body, "sha256").hexdigest())
    assert verify("key-key-key-key-key", "1700000000", body, sign("key-key-key-key-key", 1700000000, body), now=1700000100)
    assert not verify("key-key-key-key-key", "1700000000", body, sign("key-key-key-key-key", 1700000000, body), now=1700001000)
    s = Settings(webhook_backoff_s=30, webhook_attempts=4)
    assert [backoff_s(n, s) for n in (1, 2, 3, 4)] == [30, 60, 120, None]


@pytest.mark.parametrize("url, words", [
    ("ftp://example.org/x", "http:// or https://"),
    ("file:///etc/passwd", "http:// or https://"),
    ("http:///nohost", "with a host"),
    ("http://example.org:99999/", "not a valid URL"),
    ("http://intranet.local/", "not one this server calls"),
])
def test_only_http_urls_of_allowed_hosts(url, words):
    with pytest.raises(ParameterError, match=words):
        check_url(url, Settings(webhook_hosts="example.org, 127.0.0.1"))
    assert check_url("https://example.org/h", Settings(webhook_hosts="example.org")) == "https://example.org/h"


def test_a_signed_call_per_finished_job_and_a_retry_after_a_500(env, receiver, monkeypatch):
    settings, store, tenant, block = env
    receiver.answers = [500]
    hook = store.webhooks.create(tenant_id=tenant["id"], url=receiver.url, secret=SECRET, schedule_id=None,
                                events=["job.done", "job.failed"])
    outcomes = iter([workers_jobspec.JobOutcome(100, 3, 1, [], False, {}, {"trees": "t"}), InputError("b.laz: truncated")])

    def fake(spec, *, client, progress, cancel):
        out = next(outcomes)
        if isinstance(out, Exception):
            raise out
        return out

    monkeypatch.setattr(workers_job, "run_job", fake)
    sender = WebhookSender(store, settings)

    def notify(job):
        if job_event(store, job):
            sender.wake()

    runner = Runner(store, settings, client_factory=lambda: None, on_final=notify)
    done_job = store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
    sender.start()
    runner.start()
    try:
        calls = receiver.wait_for(2)  # the done job's call, answered 500, and its retry
        store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
        calls = receiver.wait_for(3)
    finally:
        runner.stop()
        sender.stop()
    assert [c["status"] for c in calls] == [500, 200, 200]
    first, retry, failed = (_checked(c) for c in calls)
    assert first == retry and first["event"] == "job.done" and first["job"]["id"] == done_job["id"]
    assert first["job"]["n_trees"] == 3 and first["job"]["links"]["page"] == f"/jobs/{done_job['id']}"
    assert failed["event"] == "job.failed" and failed["job"]["error"] == "b.laz: truncated"
    deliveries = {d["event"]: d for d in store.webhooks.deliveries(tenant["id"], hook["id"])}
    assert deliveries["job.done"]["state"] == "delivered" and deliveries["job.done"]["attempts"] == 2
    assert [t["status_code"] for t in deliveries["job.done"]["tries"]] == [500, 200]
    assert deliveries["job.failed"]["attempts"] == 1


def test_a_receiver_that_keeps_failing_is_given_up_after_the_attempts(env, receiver):
    settings, store, tenant, block = env
    receiver.answers = [503, 503, 503, 503]
    hook = store.webhooks.create(tenant_id=tenant["id"], url=receiver.url, secret=SECRET, schedule_id=None, events=["job.failed"])
    job = store.jobs.create(tenant_id=tenant["id"], block_id=block["id"], job={})
    store.jobs.claim_next()
    assert job_event(store, store.jobs.finish(job["id"], "failed", error="no trees found")) == 1
    # a cancelled job, or one of another event, calls nobody
    assert job_event(store, {**job, "state": "cancelled"}) == 0
    sender = WebhookSender(store, settings)
    for _ in range(3):
        time.sleep(settings.webhook_backoff_s * 4)  # (lets the backoff pass; nothing is timed)
        sender.deliver_due()
    (d,) = store.webhooks.deliveries(tenant["id"], hook["id"])
    assert d["state"] == "failed" and d["attempts"] == 3 and d["status_code"] == 503
    assert len(receiver.calls) == 3 and sender.deliver_due() == 0
    assert store.webhooks.prune_deliveries_any_tenant(d["finished_at"]) == 0  # ended at, not before
    assert store.webhooks.prune_deliveries_any_tenant(d["finished_at"] + 1) == 1
    assert store.webhooks.deliveries(tenant["id"], hook["id"]) == []


def test_a_receiver_that_is_not_there_is_recorded_as_no_answer(env):
    settings, store, tenant, block = env
    gone = Receiver()
    url = gone.url
    gone.close()
    hook = store.webhooks.create(tenant_id=tenant["id"], url=url, secret=SECRET, schedule_id=None, events=["job.done"])
    store.webhooks.queue_event(tenant_id=tenant["id"], schedule_id=None, event="job.done", body={"job": {}})
    WebhookSender(store, settings).deliver_due()
    (d,) = store.webhooks.deliveries(tenant["id"], hook["id"])
    assert d["state"] == "pending" and d["status_code"] is None and d["error"].startswith("no answer")


def test_a_rejected_capture_calls_the_schedules_webhook_only(env, receiver, tmp_path):
    settings, store, tenant, _ = env
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    (inbox / "bad.laz").write_text("not points")
    sched = store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron="0 1 * * *", job={},
                                  next_run_at=None)
    other = tmp_path / "other"
    other.mkdir()
    sched2 = store.schedules.create(tenant_id=tenant["id"], inbox=str(other), cron="0 1 * * *", job={},
                                   next_run_at=None)
    mine = store.webhooks.create(tenant_id=tenant["id"], url=receiver.url, secret=SECRET, schedule_id=sched["id"],
                                events=["capture.rejected"])
    theirs = store.webhooks.create(tenant_id=tenant["id"], url=receiver.url, secret=SECRET, schedule_id=sched2["id"],
                                  events=["capture.rejected"])
    assert len(run_schedule(store, settings, sched)["rejected"]) == 1
    WebhookSender(store, settings).deliver_due()
    (call,) = receiver.calls
    body = _checked(call)
    assert body["event"] == "capture.rejected" and body["capture"]["file"] == "bad.laz"
    assert "LASF" in body["capture"]["reason"] and body["schedule_id"] == sched["id"]
    assert len(store.webhooks.deliveries(tenant["id"], mine["id"])) == 1
    assert store.webhooks.deliveries(tenant["id"], theirs["id"]) == []


def test_api_webhooks(client_a, client_b, api, api_data, receiver):
    r = client_a.post("/v1/webhooks", json={"url": "ftp://x.org/", "secret": SECRET})
    assert r.status_code == 422 and "http:// or https://" in r.json()["detail"]
    assert client_a.post("/v1/webhooks", json={"url": receiver.url, "secret": "short"}).status_code == 422
    assert client_a.post("/v1/webhooks", json={"url": receiver.url, "secret": SECRET, "events": ["job.lost"]}).status_code == 422
    assert client_a.post("/v1/webhooks", json={"url": receiver.url, "secret": SECRET, "schedule_id": "nope"}).status_code == 404
    r = client_a.post("/v1/webhooks", json={"url": receiver.url, "secret": SECRET})
    assert r.status_code == 201, r.text
    hook = r.json()
    assert "secret" not in hook and hook["events"] == ["job.done", "job.failed", "capture.rejected"]
    assert r.headers["location"] == f"/v1/webhooks/{hook['id']}"
    assert [h["id"] for h in client_a.get("/v1/webhooks").json()] == [hook["id"]]
    assert client_b.get(f"/v1/webhooks/{hook['id']}").status_code == 404
    assert client_b.get(f"/v1/webhooks/{hook['id']}/deliveries").status_code == 404
    # a scan that rejects a capture calls it (this server's sender is off: delivered here)
    inbox = tenant_inbox(api_data, "farm-a", "hooked")
    (inbox / "bad.laz").write_text("not points")
    sid = client_a.post("/v1/schedules", json={"inbox": str(inbox)}).json()["id"]
    try:
        client_a.post(f"/v1/schedules/{sid}/run")
        store, settings = api.app.state.store, api.app.state.settings
        WebhookSender(store, settings).deliver_due()
        (d,) = client_a.get(hook["links"]["deliveries"]).json()
        assert d["state"] == "delivered" and d["attempts"] == 1 and d["tries"][0]["status_code"] == 200
        assert d["body"]["capture"]["file"] == "bad.laz" and d["event"] == "capture.rejected"
        assert _checked(receiver.calls[0])["id"] == d["id"]
    finally:
        client_a.delete(f"/v1/schedules/{sid}")
        assert client_a.delete(f"/v1/webhooks/{hook['id']}").status_code == 204
    assert client_a.get(f"/v1/webhooks/{hook['id']}").status_code == 404


def test_a_deleted_schedules_webhooks_go_with_it_and_a_farm_has_at_most_20(env, tmp_path):
    _, store, tenant, _ = env
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    sched = store.schedules.create(tenant_id=tenant["id"], inbox=str(inbox), cron="0 1 * * *", job={},
                                  next_run_at=None)
    farm = store.webhooks.create(tenant_id=tenant["id"], url="http://127.0.0.1:9/", secret=SECRET, schedule_id=None, events=["job.done"])
    store.webhooks.create(tenant_id=tenant["id"], url="http://127.0.0.1:9/", secret=SECRET, schedule_id=sched["id"], events=["job.done"])
    store.schedules.delete(tenant["id"], sched["id"])
    assert [w["id"] for w in store.webhooks.list(tenant["id"])] == [farm["id"]]

    from service.db.webhooks import MAX_WEBHOOKS

    for _ in range(MAX_WEBHOOKS - 1):
        store.webhooks.create(tenant_id=tenant["id"], url="http://127.0.0.1:9/", secret=SECRET, schedule_id=None, events=["job.done"])
    with pytest.raises(ParameterError, match="the most it may have"):
        store.webhooks.create(tenant_id=tenant["id"], url="http://127.0.0.1:9/", secret=SECRET, schedule_id=None, events=["job.done"])


@pytest.mark.slow
def test_a_real_server_calls_the_webhook_when_its_jobs_finish_or_fail(tmp_path, receiver):
    """`orchard serve` with its runner: a job on a generated block (done) and one on a
    block of random points (no trees: failed) each give one signed call."""
    import httpx
    from service_fixtures import ServerProcess, make_token, simulated_block, wait_for_job, write_las

    receiver.answers = [500]  # the first call is answered 500: tried again
    srv = ServerProcess(tmp_path / "data", ORCHARD_SCHEDULING="false", ORCHARD_WEBHOOK_HOSTS="127.0.0.1",
                        ORCHARD_WEBHOOK_BACKOFF_S="0.2")
    srv.start()
    try:
        token = make_token(srv.data_dir, "farm-a")
        block = simulated_block(tmp_path / "orchard.laz", rows=2, trees_per_row=3, density=0.4, seed=3)
        noise = write_las(tmp_path / "noise.laz", 2000, seed=5)
        with httpx.Client(base_url=srv.url, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
            hook = c.post("/v1/webhooks", json={"url": receiver.url, "secret": SECRET}).json()
            assert c.post("/v1/webhooks", json={"url": "http://intranet.example/", "secret": SECRET}).status_code == 422
            jobs = []
            for path in (block, noise):
                b = c.post("/v1/blocks", files={"file": (path.name, path.read_bytes())}).json()
                jobs.append(wait_for_job(c, c.post("/v1/jobs", json={"block_id": b["id"]}).json()["id"], timeout=240))
            assert [j["state"] for j in jobs] == ["done", "failed"]
            calls = receiver.wait_for(3, timeout=60)
            per_job: dict = {}
            for call in calls:  # (the failed job's call may come before the done job's retry)
                body = _checked(call)
                per_job.setdefault((body["event"], body["job"]["id"]), []).append((call["status"], body))
            assert sorted(per_job) == sorted([("job.done", jobs[0]["id"]), ("job.failed", jobs[1]["id"])])
            done, failed = per_job[("job.done", jobs[0]["id"])], per_job[("job.failed", jobs[1]["id"])]
            assert [st for st, _ in done] == [500, 200] and done[0][1] == done[1][1]  # the same delivery again
            assert [st for st, _ in failed] == [200]
            assert done[0][1]["job"]["n_trees"] == jobs[0]["n_trees"] and failed[0][1]["job"]["error"] == jobs[1]["error"]
            shown = {d["event"]: d for d in c.get(hook["links"]["deliveries"]).json()}
            assert [t["status_code"] for t in shown["job.done"]["tries"]] == [500, 200]
            assert shown["job.failed"]["state"] == "delivered"
    finally:
        srv.stop()
