"""Browser sign-in over HTTP, on the app in this process: the cookie's flags, CSRF,
sign-out, other farms' jobs, and the offline API docs (the browser itself:
test_web_browser.py). That no token reaches the server's log is checked on a real server."""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator

import httpx
import pytest
from fastapi.testclient import TestClient
from service_fixtures import client_of, make_token


@pytest.fixture(scope="module")
def tokens(api_data):
    """Farms of their own: the jobs these tests make are in no other test's listings."""
    return {"a": make_token(api_data, "web-a"), "b": make_token(api_data, "web-b")}


@pytest.fixture(scope="module")
def queued_jobs(api, tokens, small_las):
    """A queued job of each farm (the app's runner is off)."""
    out = {}
    for farm in ("a", "b"):
        with _browser(api, token=tokens[farm]) as c:
            block = c.post("/v1/blocks", files={"file": ("small.laz", small_las.read_bytes())}).json()
            out[farm] = c.post("/v1/jobs", json={"block_id": block["id"]}).json()
    return out


@contextlib.contextmanager
def _browser(api: TestClient, token: str | None = None) -> Iterator[TestClient]:
    """A client with a cookie jar of its own that shows the redirects it gets."""
    c = client_of(api, token=token, follow_redirects=False)
    try:
        yield c
    finally:
        c.close()


def _sign_in(c: httpx.Client, token: str, **headers) -> httpx.Response:
    return c.post("/signin", data={"token": token, "next": "/blocks"}, headers=headers)


def _csrf(c: httpx.Client) -> str:
    page = c.get("/blocks")
    assert page.status_code == 200
    return re.search(r'<meta name="csrf-token" content="([^"]+)">', page.text).group(1)


def test_sign_in_sets_a_strict_httponly_expiring_cookie(api, tokens):
    with _browser(api) as c:
        assert c.get("/").headers["location"] == "/blocks"
        to_signin = c.get("/blocks")
        assert to_signin.status_code == 303 and to_signin.headers["location"].startswith("/signin")
        form = c.get("/signin")
        assert form.status_code == 200 and 'method="post"' in form.text and form.headers["cache-control"] == "no-store"
        assert form.headers["x-frame-options"] == "DENY"  # no other site frames the form
        resp = _sign_in(c, tokens["a"])
        assert resp.status_code == 303 and resp.headers["location"] == "/blocks"
        cookie = resp.headers["set-cookie"].lower()
        assert "httponly" in cookie and "samesite=strict" in cookie and "max-age=43200" in cookie and "path=/" in cookie
        assert tokens["a"] not in resp.headers["set-cookie"] and tokens["a"] not in resp.headers["location"]
        assert c.get("/v1/jobs").status_code == 200  # the API with the cookie alone


def test_a_signed_in_token_is_not_in_the_servers_log(api_server):
    token = make_token(api_server.data_dir, "web-log")
    with httpx.Client(base_url=api_server.url, timeout=30, follow_redirects=False) as c:
        assert _sign_in(c, token).status_code == 303
        assert c.get("/v1/jobs").status_code == 200
    assert token not in api_server.log()


def test_a_wrong_token_is_refused_and_no_cookie_is_set(api, tokens):
    with _browser(api) as c:
        resp = _sign_in(c, tokens["a"] + "x")
        assert resp.status_code == 401 and "set-cookie" not in resp.headers and "not known" in resp.text
        assert c.get("/v1/jobs").status_code == 401


def test_sign_in_from_another_site_is_refused(api, tokens):
    with _browser(api) as c:
        resp = _sign_in(c, tokens["a"], Origin="https://evil.example")
        assert resp.status_code == 403 and "set-cookie" not in resp.headers


def test_sign_in_from_this_host_with_another_scheme_or_port_is_refused(api, tokens):
    own = str(api.base_url).rstrip("/")  # http://testserver
    host = own.split("://", 1)[1]
    for origin in (f"https://{host}", f"http://{host}:8443", f"https://{host}:80"):
        with _browser(api) as c:
            resp = _sign_in(c, tokens["a"], Origin=origin)
            assert resp.status_code == 403 and "set-cookie" not in resp.headers, origin
    with _browser(api) as c:  # the same origin, its default port written out
        assert _sign_in(c, tokens["a"], Origin=f"http://{host}:80").status_code == 303


def test_next_stays_on_this_server(api, tokens):
    with _browser(api) as c:
        resp = c.post("/signin", data={"token": tokens["a"], "next": "//evil.example/x"})
        assert resp.headers["location"] == "/blocks"


def test_changes_with_the_cookie_need_the_csrf_token(api, tokens, queued_jobs):
    job_id = queued_jobs["a"]["id"]
    with _browser(api) as c:
        _sign_in(c, tokens["a"])
        csrf = _csrf(c)
        assert c.delete(f"/v1/jobs/{job_id}").status_code == 403  # a forged form or script
        assert c.delete(f"/v1/jobs/{job_id}", headers={"X-CSRF-Token": "wrong"}).status_code == 403
        foreign = {"X-CSRF-Token": csrf, "Origin": "https://evil.example"}
        assert c.delete(f"/v1/jobs/{job_id}", headers=foreign).status_code == 403
        assert c.get(f"/v1/jobs/{job_id}").json()["state"] == "queued"  # nothing changed
        ok = c.delete(f"/v1/jobs/{job_id}", headers={"X-CSRF-Token": csrf, "Origin": str(c.base_url).rstrip("/")})
        assert ok.status_code == 202 and ok.json()["cancel_requested"]


def test_bearer_requests_need_no_csrf_token(api, tokens, queued_jobs):
    with _browser(api, token=tokens["a"]) as c:
        resp = c.post("/v1/jobs", json={"block_id": queued_jobs["a"]["block_id"]})
    assert resp.status_code == 201
    assert set(resp.json()["links"]) == {"self", "page"} and resp.json()["links"]["page"] == f"/jobs/{resp.json()['id']}"


def test_sign_out_ends_the_session_on_the_server(api, tokens):
    with _browser(api) as c:
        _sign_in(c, tokens["a"])
        csrf = _csrf(c)
        cookie = c.cookies.get("orchard_session")
        assert c.post("/signout", data={"csrf": "wrong"}).status_code == 403
        out = c.post("/signout", data={"csrf": csrf})
        assert out.status_code == 303 and out.headers["location"] == "/signin"
        assert 'orchard_session=""' in out.headers["set-cookie"] or "max-age=0" in out.headers["set-cookie"].lower()
    with _browser(api) as replay:  # the old cookie, kept by someone: no longer valid
        replay.cookies.set("orchard_session", cookie)
        assert replay.get("/v1/jobs").status_code == 401
        assert replay.get("/blocks").status_code == 303


def test_another_farms_job_page_is_404(api, tokens, queued_jobs):
    with _browser(api) as c:
        _sign_in(c, tokens["a"])
        assert c.get(f"/jobs/{queued_jobs['a']['id']}").status_code == 200
        other = c.get(f"/jobs/{queued_jobs['b']['id']}")
        assert other.status_code == 404 and "No such job" in other.text
        assert c.get(f"/web/jobs/{queued_jobs['b']['id']}/map.json").status_code == 404
        assert c.get(f"/web/jobs/{queued_jobs['a']['id']}/map.json").status_code == 409  # not done yet


@pytest.mark.parametrize("path", ["/docs", "/redoc"])
def test_api_docs_load_only_files_of_this_server(api, path):
    page = api.get(path)
    assert page.status_code == 200
    urls = re.findall(r'(?:src|href)\s*=\s*["\']([^"\']+)', page.text) + re.findall(r"url:\s*'([^']+)'", page.text)
    assert urls and all(u.startswith("/") and not u.startswith("//") for u in urls), urls
    for url in urls:
        assert api.get(url).status_code == 200, url
    if path == "/redoc":
        script = api.get("/redoc/redoc.standalone.js").text
        assert "cdn.redoc.ly" not in script


def test_every_kind_of_response_carries_the_security_headers(api, tokens, queued_jobs):
    with _browser(api) as c:
        seen = {
            "signin": c.get("/signin"),
            "docs": c.get("/docs"),
            "redoc": c.get("/redoc"),
            "openapi": c.get("/openapi.json"),
            "static": c.get("/static/orchard.js"),
            "health": c.get("/healthz"),
            "unauthorized": c.get("/v1/jobs"),
            "not found": c.get("/nowhere"),
            "too large": c.post("/v1/jobs", content=b"{}", headers={"Content-Length": str(1 << 30)}),
        }
        _sign_in(c, tokens["a"])
        seen["blocks"] = c.get("/blocks")
        seen["job"] = c.get(f"/jobs/{queued_jobs['a']['id']}")
        seen["json"] = c.get("/v1/jobs")
    for name, resp in seen.items():
        h = resp.headers
        csp = h.get("content-security-policy", "")
        assert "frame-ancestors 'none'" in csp and "script-src 'self';" in csp and "unsafe-inline" not in csp.split(";")[0], name
        assert "'unsafe-eval'" not in csp, name
        assert h.get("x-frame-options") == "DENY" and h.get("x-content-type-options") == "nosniff", name
        assert h.get("referrer-policy") == "same-origin", name
    for name in ("signin", "docs", "redoc", "blocks", "job"):  # pages start their scripts from files
        assert re.search(r"<script>(?!\s*</script>)", seen[name].text) is None, name
    assert 'data-page="job"' in seen["job"].text and 'data-page="blocks"' in seen["blocks"].text


def test_the_served_report_names_its_inline_scripts_by_hash():
    from service.headers import report_policy

    policy = report_policy('<script>a()</script><script type="application/json">{"x": 1}</script><script>b()</script>')
    script_src = policy.split(";")[0]
    # sha256 of "a()" and "b()": the data element is not a script and is not named
    assert script_src.count("'sha256-") == 2 and "unsafe-inline" not in script_src and "frame-ancestors 'none'" in policy
    assert report_policy("<p>no scripts</p>").startswith("script-src 'none';")
