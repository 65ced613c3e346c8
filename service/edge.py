"""The HTTP server's edge: limits on connections and on the time a request takes to arrive.

uvicorn times out an idle keep-alive connection, but not a request's line and headers
while they arrive (uvicorn issue #157, "--timeout-request-start", is open), nor a
request body, and it caps connections only by answering 503 to the requests of the
connections past ``limit_concurrency``: it holds every connection it accepts. 20,000
connections that sent nothing used every file handle of the process; asyncio then
logged each failed ``accept()`` and paused accepting, and ``/healthz`` went unanswered.

`edge_protocol` makes uvicorn's h11 protocol class with these limits (`EdgeLimits`),
and `EdgeSocket` the listening socket that sorts connections as they are accepted:

- a connection past ``max_connections`` open in all, or past ``max_per_client`` from
  one address, is answered ``503`` (``Retry-After``) and closed; while more than
  ``max_refusing`` such answers are pending, further ones are closed unanswered, by
  `EdgeSocket` as they are accepted (no transport, no protocol, no task made for them:
  a burst of them is drained from the kernel's listen queue fast enough that a
  connection which is served, ``/healthz``'s, is not dropped from it);
- a connection that sends nothing stays with the kernel (``TCP_DEFER_ACCEPT``, Linux)
  up to ``header_timeout_s``: it holds no file handle and no protocol of the service
  until its first byte arrives or that time is up;
- a request whose line and headers have not all arrived ``header_timeout_s`` after
  the connection opened (or after the first byte of a later request on it) is
  answered ``408`` and closed;
- a request body other than an upload's that has not all arrived ``body_timeout_s``
  after its headers is cut off (an upload has its own deadline and minimum rate, in
  `service.api.uploads`).

Each of these is logged through `service.logs`, which rate-limits repeated warnings.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import math
import os
import socket
import time

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger("orchard.edge")

_PHRASES = {408: b"Request Timeout", 503: b"Service Unavailable"}


@dataclasses.dataclass(frozen=True)
class EdgeLimits:
    """Limits of `edge_protocol` (see the module's docstring); times in seconds."""

    max_connections: int = 1000
    max_per_client: int = 64
    header_timeout_s: float = 10.0
    body_timeout_s: float = 120.0
    max_refusing: int = 256
    refuse_linger_s: float = 1.0
    upload_path: str = "/v1/blocks"


def _raw_response(status: int, detail: str, *, retry_after: int | None = None) -> bytes:
    body = json.dumps({"detail": detail}).encode()
    head = [b"HTTP/1.1 %d %s" % (status, _PHRASES[status]), b"content-type: application/json",
            b"content-length: %d" % len(body), b"connection: close"]
    if retry_after is not None:
        head.append(b"retry-after: %d" % retry_after)
    return b"\r\n".join(head) + b"\r\n\r\n" + body


_ADMIT, _REFUSE, _DROP = "admit", "refuse", "drop"


class _Counts:
    """Open connections of one server, in all and per client address, and its pending refusals."""

    def __init__(self, limits: EdgeLimits) -> None:
        self.limits = limits
        self.per_client: collections.Counter[str] = collections.Counter()
        self.open = self.refusing = 0
        self.sorted: dict[tuple, str] = {}  # peer name -> verdict, from accept to connection_made

    def full(self, peer: str) -> bool:
        return self.open >= self.limits.max_connections or self.per_client[peer] >= self.limits.max_per_client

    def admit(self, peer: str) -> str:
        """The verdict on a new connection from ``peer``, counted: admit, refuse (a 503) or drop (closed unanswered)."""
        if not self.full(peer):
            self.open += 1
            self.per_client[peer] += 1
            return _ADMIT
        if self.refusing >= self.limits.max_refusing:
            return _DROP
        self.refusing += 1
        return _REFUSE

    def release(self, peer: str, verdict: str) -> None:
        if verdict == _ADMIT:
            self.open -= 1
            self.per_client[peer] -= 1
            if self.per_client[peer] <= 0:
                del self.per_client[peer]
        elif verdict == _REFUSE:
            self.refusing -= 1


class EdgeSocket(socket.socket):
    """A listening socket whose ``accept()`` sorts each connection by the counts of an
    `edge_protocol` class (``EdgeSocket.wrap(sock, protocol)``), and closes those to drop
    there and then, before asyncio makes a transport, a protocol and a task for each."""

    #: connections closed in one ``accept()`` call at most before the event loop runs again
    DROP_BATCH = 1024
    #: seconds between two log lines about dropped connections
    LOG_EVERY_S = 1.0

    @classmethod
    def wrap(cls, sock: socket.socket, protocol: type[H11Protocol]) -> "EdgeSocket":
        """An `EdgeSocket` on ``sock``'s file descriptor (``sock`` is detached: use the result)."""
        edge = cls(sock.family, sock.type, sock.proto, fileno=sock.detach())
        edge._counts = protocol.edge_counts
        if hasattr(socket, "TCP_DEFER_ACCEPT"):
            edge.setsockopt(socket.IPPROTO_TCP, socket.TCP_DEFER_ACCEPT,
                            max(1, math.ceil(protocol.edge_counts.limits.header_timeout_s)))
        edge._dropped = 0
        edge._logged_at = 0.0
        return edge

    def accept(self):
        dropped = 0
        while True:
            fd, addr = self._accept()  # BlockingIOError once the queue is empty: asyncio waits for more
            peer = addr[0]
            verdict = self._counts.admit(peer)
            if verdict != _DROP:
                self._counts.sorted[addr] = verdict
                conn = socket.socket(self.family, self.type, self.proto, fileno=fd)
                if socket.getdefaulttimeout() is None and self.gettimeout():
                    conn.setblocking(True)  # as socket.accept does
                return conn, addr
            os.close(fd)
            dropped += 1
            self._note_dropped(peer)
            if dropped >= self.DROP_BATCH:  # the loop's other work (/healthz's answer) goes first
                raise BlockingIOError

    def _note_dropped(self, peer: str) -> None:
        self._dropped += 1
        now = time.monotonic()
        if now - self._logged_at >= self.LOG_EVERY_S:
            counts = self._counts
            log.warning("connections closed unanswered: too many open connections and refusals pending "
                        "(%d closed since the last such line, %d open in all, %d from %s, %d refusals pending)",
                        self._dropped, counts.open, counts.per_client[peer], peer, counts.refusing)
            self._dropped = 0
            self._logged_at = now


def edge_protocol(limits: EdgeLimits) -> type[H11Protocol]:
    """uvicorn's h11 protocol with ``limits`` (pass it as ``uvicorn.Config(http=...)``;
    listen with ``EdgeSocket.wrap(sock, protocol)`` to close a flood at accept time).

    The counts are those of one server: each call makes a class with counts of its own.
    """

    class EdgeProtocol(_EdgeProtocol):
        edge_counts = _Counts(limits)
        edge_busy = _raw_response(503, f"too many open connections (at most {limits.max_connections} in all, "
                                       f"{limits.max_per_client} from one address); try again shortly", retry_after=5)
        edge_slow = _raw_response(408, f"the request's line and headers did not arrive within {limits.header_timeout_s:g} s")

    return EdgeProtocol


class _EdgeProtocol(H11Protocol):
    """uvicorn's h11 protocol with the limits of `EdgeLimits`; `edge_protocol` makes a
    subclass per server, with that server's counts and its two ready-made answers."""

    edge_counts: _Counts
    edge_busy: bytes  # the 503 of a refused connection
    edge_slow: bytes  # the 408 of a request whose line and headers came late

    @property
    def edge_limits(self) -> EdgeLimits:
        return self.edge_counts.limits

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        counts = self.edge_counts
        self._peer = self.client[0] if self.client else ""
        self._verdict = None
        self._refused = False
        self._head_timer = self._body_timer = None
        verdict = counts.sorted.pop(transport.get_extra_info("peername"), None)
        if verdict is None:  # not accepted by an EdgeSocket: sorted here
            verdict = counts.admit(self._peer)
        if verdict == _DROP:  # a flood: no file handle held for it
            log.warning("connection refused: too many open connections (%d in all, %d from %s)",
                        counts.open, counts.per_client[self._peer], self._peer)
            self._refused = True
            self.transport.abort()
            return
        self._verdict = verdict
        if verdict == _REFUSE:
            self._refuse()
            return
        self._arm_head()

    # -- refused connections ---------------------------------------------------

    def _refuse(self) -> None:
        self._refused = True
        counts = self.edge_counts
        log.warning("connection refused: too many open connections (%d in all, %d from %s)",
                    counts.open, counts.per_client[self._peer], self._peer)
        # answered once its request arrives (closing with an unread request would reset
        # the connection, and the client would never read the 503), or after a moment
        self._head_timer = self.loop.call_later(self.edge_limits.refuse_linger_s, self._answer_refused)

    def _answer_refused(self) -> None:
        if not self.transport.is_closing():
            self.transport.write(self.edge_busy)
            self.transport.close()

    # -- deadlines ----------------------------------------------------------------

    def _arm_head(self) -> None:
        self._head_timer = self.loop.call_later(self.edge_limits.header_timeout_s, self._head_late)

    def _disarm(self, name: str) -> None:
        timer = getattr(self, name)
        if timer is not None:
            timer.cancel()
            setattr(self, name, None)

    def _head_late(self) -> None:
        self._head_timer = None
        if self.transport.is_closing() or self.conn.their_state is not h11.IDLE:
            return
        log.warning("request from %s: its line and headers did not arrive within %g s; closed",
                    self._peer, self.edge_limits.header_timeout_s)
        self.transport.write(self.edge_slow)
        self.transport.close()

    def _body_late(self) -> None:
        self._body_timer = None
        if self.transport.is_closing() or self.conn.their_state is not h11.SEND_BODY:
            return
        log.warning("request from %s: its body did not arrive within %g s; closed", self._peer, self.edge_limits.body_timeout_s)
        self.transport.close()  # the app sees a disconnect (the response may have begun: no 408 here)

    def data_received(self, data: bytes) -> None:
        if self._refused:
            self._disarm("_head_timer")
            self._answer_refused()
            return
        if self._head_timer is None and self.conn.their_state is h11.IDLE:
            self._arm_head()  # the first byte of a later request on a kept-alive connection
        super().data_received(data)
        self._after_events()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._after_events()

    def _after_events(self) -> None:
        """Disarm or arm the deadlines as the request moved on: its headers in, its body in."""
        theirs = self.conn.their_state
        if theirs is not h11.IDLE:
            self._disarm("_head_timer")
        if theirs is h11.SEND_BODY and self._body_timer is None and self.scope is not None \
                and self.scope.get("path", "").rstrip("/") != self.edge_limits.upload_path:
            self._body_timer = self.loop.call_later(self.edge_limits.body_timeout_s, self._body_late)
        elif theirs is not h11.SEND_BODY:
            self._disarm("_body_timer")

    def connection_lost(self, exc) -> None:
        self._disarm("_head_timer")
        self._disarm("_body_timer")
        if self._verdict is not None:
            self.edge_counts.release(self._peer, self._verdict)
            self._verdict = None
        super().connection_lost(exc)
