"""Browser sessions: a tenant's token given once on the sign-in page, then a cookie.

The cookie holds a random session id (only its sha256 is stored, in
``<data dir>/sessions.sqlite``, beside the job store); it is HttpOnly (no script reads
it), SameSite=Strict (no other site's page sends it) and expires after
`SESSION_SECONDS`. A session remembers the hash of the token it was opened with, so
revoking the token ends its sessions too. Requests that change something with the
cookie (anything but GET/HEAD/OPTIONS) must also carry the session's CSRF token in the
``X-CSRF-Token`` header (or the ``csrf`` form field) and, when the browser says where
they come from, come from this server's own origin.

The API keeps bearer tokens: a request with an ``Authorization`` header is judged by it
alone, and never needs a CSRF token (a browser never adds that header by itself).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from fastapi import Request
from starlette.exceptions import HTTPException

from service.auth import UnauthorizedError, authenticate, hash_token
from service.db.jobstore import Store

COOKIE = "orchard_session"
CSRF_HEADER = "x-csrf-token"
SESSION_SECONDS = 12 * 3600  # a working day in the field; sign in again the next morning
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


@dataclass(frozen=True)
class Session:
    """One signed-in browser: its tenant's token (hashed), CSRF token and expiry (unix seconds)."""

    token_hash: str
    csrf: str
    expires_at: float


def _hash(session_id: str) -> str:
    return hashlib.sha256(session_id.encode("utf-8")).hexdigest()


class SessionStore:
    """Sessions in their own SQLite file (one connection, serialised by a lock)."""

    def __init__(self, path: str | Path) -> None:
        self._lock = threading.Lock()
        self._con = sqlite3.connect(str(path), timeout=30.0, isolation_level=None, check_same_thread=False)
        self._con.execute("PRAGMA journal_mode=WAL")
        self._con.execute("PRAGMA busy_timeout=30000")
        self._con.execute(
            "CREATE TABLE IF NOT EXISTS sessions (id_hash TEXT PRIMARY KEY, token_hash TEXT NOT NULL, "
            "csrf TEXT NOT NULL, created_at REAL NOT NULL, expires_at REAL NOT NULL)"
        )

    def open(self, token_hash: str, *, now: float | None = None) -> tuple[str, Session]:
        """A new session for a (checked) token: its id, for the cookie, and the session."""
        now = time.time() if now is None else now
        sid = secrets.token_urlsafe(32)
        sess = Session(token_hash=token_hash, csrf=secrets.token_urlsafe(24), expires_at=now + SESSION_SECONDS)
        with self._lock:
            self._con.execute("DELETE FROM sessions WHERE expires_at <= ?", (now,))
            self._con.execute(
                "INSERT INTO sessions (id_hash, token_hash, csrf, created_at, expires_at) VALUES (?, ?, ?, ?, ?)",
                (_hash(sid), sess.token_hash, sess.csrf, now, sess.expires_at),
            )
        return sid, sess

    def get(self, session_id: str, *, now: float | None = None) -> Session | None:
        """The live session of a cookie value, or None (unknown or expired)."""
        now = time.time() if now is None else now
        with self._lock:
            row = self._con.execute(
                "SELECT token_hash, csrf, expires_at FROM sessions WHERE id_hash = ?", (_hash(session_id),)
            ).fetchone()
        if row is None or row[2] <= now:
            return None
        return Session(token_hash=row[0], csrf=row[1], expires_at=row[2])

    def close_session(self, session_id: str) -> None:
        with self._lock:
            self._con.execute("DELETE FROM sessions WHERE id_hash = ?", (_hash(session_id),))

    def close(self) -> None:
        with self._lock:
            self._con.close()


_stores_lock = threading.Lock()


def sessions_of(request: Request) -> SessionStore:
    """The app's session store, opened on first use."""
    state = request.app.state
    with _stores_lock:
        if getattr(state, "sessions", None) is None:
            state.sessions = SessionStore(Path(state.settings.data_dir) / "sessions.sqlite")
        return state.sessions


def current_session(request: Request, store: Store) -> tuple[Session, dict[str, Any]] | None:
    """The request's live session and its tenant, or None (no cookie, expired, signed
    out, or its token revoked since)."""
    sid = request.cookies.get(COOKIE)
    if not sid:
        return None
    now = time.time()
    sess = sessions_of(request).get(sid, now=now)
    if sess is None:
        return None
    rec = store.accounts.token_by_hash(sess.token_hash)  # revoked or expired since: the session ends with it
    if rec is None or rec["tenant"] is None or (rec.get("expires_at") is not None and rec["expires_at"] <= now):
        return None
    return sess, rec["tenant"]


_DEFAULT_PORTS = {"http": 80, "https": 443}


def _origin(scheme: str, netloc: str) -> tuple[str, str, int | None] | None:
    """(scheme, host, port) of an origin, the port filled in from the scheme; None if malformed."""
    try:
        parts = urlsplit(f"{scheme}://{netloc}")
        port = parts.port
    except ValueError:
        return None
    if not parts.hostname:
        return None
    return scheme.lower(), parts.hostname.lower(), port if port is not None else _DEFAULT_PORTS.get(scheme.lower())


def same_origin(request: Request) -> bool:
    """False when the browser says the request comes from another origin (Origin, or
    Referer without it): scheme, host and port must all be this server's (the scheme as
    the server sees it: https behind a proxy that says so, see docs/operations.md); True
    when it says nothing (non-browser clients)."""
    source = request.headers.get("origin") or request.headers.get("referer")
    if not source or source == "null":
        return source is None
    parts = urlsplit(source)
    if parts.scheme not in ("http", "https"):
        return False
    theirs = _origin(parts.scheme, parts.netloc)
    ours = _origin(request.url.scheme, request.headers.get("host", ""))
    return theirs is not None and theirs == ours


def check_csrf(request: Request, sess: Session, form_token: str | None = None) -> None:
    """403 unless a state-changing cookie request carries the session's CSRF token and
    comes from this origin (SameSite=Strict already keeps other sites' cookies out; this
    holds for browsers that ignore it)."""
    given = request.headers.get(CSRF_HEADER) or form_token or ""
    if not same_origin(request) or not hmac.compare_digest(given.encode(), sess.csrf.encode()):
        raise HTTPException(status_code=403, detail="this request changes something and needs the page's CSRF token "
                                                    "(reload the page and try again)")


def request_tenant(request: Request, store: Store) -> dict[str, Any]:
    """The tenant of a request: its bearer token if it has an ``Authorization`` header,
    else its session cookie (with the CSRF check for anything but reading). 401 otherwise."""
    authorization = request.headers.get("authorization")
    if authorization:
        return authenticate(store, authorization)
    found = current_session(request, store)
    if found is None:
        if request.cookies.get(COOKIE):
            raise UnauthorizedError("the session has expired or was signed out: sign in again at /signin")
        return authenticate(store, None)
    sess, tenant = found
    if request.method not in SAFE_METHODS:
        check_csrf(request, sess)
    return tenant


def sign_in(request: Request, store: Store, token: str) -> tuple[str, Session, dict[str, Any]]:
    """Open a session for a token given on the sign-in page; `UnauthorizedError` if unknown."""
    token = token.strip()
    tenant = authenticate(store, f"Bearer {token}") if token else None
    if tenant is None:
        raise UnauthorizedError("paste a token from `orchard tokens create --tenant NAME`")
    sid, sess = sessions_of(request).open(hash_token(token))
    return sid, sess, tenant
