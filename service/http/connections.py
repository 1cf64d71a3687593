"""Connection-level defences of ``maxfs serve``, in uvicorn's own HTTP/1.1 protocol (h11),
before the app sees a request.

uvicorn has no deadline for reading a request head (``timeout_keep_alive`` starts only after
an answer), and its ``limit_concurrency`` counts every open connection, so a few hundred
connections that send a head slowly, or nothing, hold every slot and everyone else gets 503.
:func:`guarded_protocol` adds, per connection:

- a head deadline (``MAXFS_HEADER_TIMEOUT``): a request head must have arrived whole within
  that many seconds of the connection opening or of the previous answer, else the connection
  is closed (a body the app reads has its own timeouts, :func:`service.guards.body_chunks`);
  the same deadline holds for the rest of a body nobody reads: when the answer went out before
  the body was read (401, 404, a health check with a body), the client has that long to finish
  sending it, else the connection is closed. Without it a client trickling a byte every few
  seconds into such a body kept the connection (uvicorn's keep-alive timer restarts on every
  byte), and a thousand of them, from a few addresses, held every slot of the server;
- a cap on open connections per client address (``MAXFS_MAX_CONNECTIONS_PER_CLIENT``):
  beyond it a new connection gets a 503 and is closed before anything is read;
- room for newcomers: when every slot (``MAXFS_MAX_CONNECTIONS``) is taken, a new connection
  closes one that is doing nothing for anyone instead of getting the 503, in this order: one
  answered and still sending a body nobody reads; one whose reader has taken nothing of its
  answer for :data:`STALLED` seconds; one without a whole request head after :data:`GRACE`
  seconds; one idle between requests for :data:`GRACE` seconds (oldest first within each). A
  connection younger than that (a client that has just connected and is sending its head) and
  a request being served are never closed for it. Without this, clients on many addresses
  reopening such connections as fast as they were closed kept every slot (the deadlines above
  close each within seconds, not before the next one arrives);
- request smuggling refused (RFC 9112 section 6.1): a request with both ``Content-Length`` and
  ``Transfer-Encoding`` gets 400 and the connection is closed, so nothing pipelined behind it
  (or hidden in its body) is answered.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger("maxfs.connections")

#: Seconds a connection may wait for its head, or between requests, before it can be closed to
#: make room at the connection cap (a client sends its head within milliseconds of connecting).
GRACE = 1.0
#: Seconds without its reader taking anything of the answer before a connection can be closed
#: to make room (a slow link drains its buffer many times a second).
STALLED = 5.0


def _raw_answer(status: int, reason: str, detail: str, error: str) -> bytes:
    """A whole HTTP/1.1 answer with the JSON error body, for writing straight to a socket."""
    body = json.dumps({"error": error, "detail": detail}).encode()
    head = (
        f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/json\r\n"
        f"content-length: {len(body)}\r\nconnection: close\r\nx-content-type-options: nosniff\r\n\r\n"
    )
    return head.encode() + body


def is_smuggling(headers: list[tuple[bytes, bytes]]) -> bool:
    """Whether a request head has both ``Content-Length`` and ``Transfer-Encoding``: two
    framings that a proxy and this server could read differently (RFC 9112 section 6.1)."""
    names = {name.lower() for name, _ in headers}
    return b"content-length" in names and b"transfer-encoding" in names


SMUGGLING = (
    "the request has both Content-Length and Transfer-Encoding, so its length is ambiguous "
    "(RFC 9112 section 6.1); send one of them. The connection is closed"
)


def guarded_protocol(header_timeout: float, per_client: int) -> type[H11Protocol]:
    """An :class:`H11Protocol` with the defences of this module (pass it as uvicorn's ``http``).

    Parameters
    ----------
    header_timeout
        Seconds a request head may take to arrive (0 = no limit).
    per_client
        Open connections one client address may have (0 = no limit).
    """
    open_per_client: dict[str, int] = {}
    full = _raw_answer(
        503,
        "Service Unavailable",
        f"this address already has {per_client} connections open, the most allowed "
        "(MAXFS_MAX_CONNECTIONS_PER_CLIENT); close some or reuse them",
        "TooManyConnections",
    )

    class GuardedProtocol(H11Protocol):
        head_timer: asyncio.TimerHandle | None = None
        counted: str | None = None
        opened: float = 0.0
        quiet_since: float = 0.0  # when it last started waiting for a head (opened, or answered)
        stalled_since: float | None = None  # the reader stopped taking the answer (writes paused)

        def __init__(self, *args: Any, **kw: Any) -> None:
            super().__init__(*args, **kw)
            self.app = _refuse_smuggling(self.app)

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self.opened = self.quiet_since = self.loop.time()
            host = self.client[0] if self.client else ""
            if per_client and open_per_client.get(host, 0) >= per_client:
                transport.write(full)
                transport.close()
                return
            open_per_client[host] = open_per_client.get(host, 0) + 1
            self.counted = host
            self._arm_head_timer()
            self._make_room()

        def _make_room(self) -> None:
            """At the connection cap, close idle ones (:func:`_idle_rank`) so that this one is
            served: uvicorn answers 503 to a request that arrives while the cap is reached."""
            limit = self.limit_concurrency
            over = len(self.connections) - limit + 1 if limit else 0
            if over <= 0:
                return
            now = self.loop.time()
            ranked = sorted(
                (r, p.opened, id(p), p)
                for p in self.connections
                if p is not self and (r := _idle_rank(p, now)) is not None
            )
            for *_, p in ranked[:over]:
                log.info("closed an idle connection from %s to make room at the connection cap", p.counted)
                p.transport.close()

        def pause_writing(self) -> None:
            super().pause_writing()
            self.stalled_since = self.loop.time()

        def resume_writing(self) -> None:
            super().resume_writing()
            self.stalled_since = None

        def connection_lost(self, exc: Exception | None) -> None:
            if self.counted is not None:
                n = open_per_client.get(self.counted, 1) - 1
                if n > 0:
                    open_per_client[self.counted] = n
                else:
                    open_per_client.pop(self.counted, None)
                self.counted = None
            self._disarm_head_timer()
            super().connection_lost(exc)

        def on_response_complete(self) -> None:
            super().on_response_complete()
            self.quiet_since = self.loop.time()
            if not self.transport.is_closing():
                self._arm_head_timer()  # the next head has the same deadline

        def _arm_head_timer(self) -> None:
            self._disarm_head_timer()
            if header_timeout > 0:
                self.head_timer = self.loop.call_later(header_timeout, self._head_late)

        def _disarm_head_timer(self) -> None:
            if self.head_timer is not None:
                self.head_timer.cancel()
                self.head_timer = None

        def _head_late(self) -> None:
            self.head_timer = None
            if self.transport.is_closing():
                return
            # their_state leaves IDLE once a whole request head was parsed
            if self.conn.their_state is h11.IDLE:
                log.info(
                    "closed a connection from %s: no whole request head in %g s", self.counted, header_timeout
                )
                self.transport.close()
            elif self.conn.our_state is h11.DONE and self.conn.their_state is h11.SEND_BODY:
                # answered, and still sending a body that nothing reads
                log.info(
                    "closed a connection from %s: the rest of an unread body took over %g s",
                    self.counted,
                    header_timeout,
                )
                self.transport.close()

    return GuardedProtocol


def _idle_rank(p: Any, now: float) -> int | None:
    """How readily connection ``p`` may be closed to make room (lower first), None if never:
    0 answered and still sending a body nobody reads, 1 its reader has taken nothing of the
    answer for :data:`STALLED` s, 2 no whole request head after :data:`GRACE` s, 3 idle between
    requests for :data:`GRACE` s."""
    if not isinstance(p, H11Protocol) or p.transport is None or p.transport.is_closing():
        return None
    c = p.conn
    if c.our_state is h11.DONE and c.their_state is h11.SEND_BODY:
        return 0
    stalled = getattr(p, "stalled_since", None)
    if stalled is not None and now - stalled >= STALLED:
        return 1
    quiet = now - getattr(p, "quiet_since", now) >= GRACE
    if c.their_state is h11.IDLE and quiet and (p.cycle is None or p.cycle.response_complete):
        return 2 if p.cycle is None else 3
    return None


def _refuse_smuggling(app: Any) -> Any:
    async def guarded(scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] == "http" and is_smuggling(scope["headers"]):
            body = json.dumps({"error": "MaxfsError", "detail": SMUGGLING}).encode()
            await send(
                {
                    "type": "http.response.start",
                    "status": 400,
                    "headers": [
                        (b"content-type", b"application/json"),
                        (b"content-length", str(len(body)).encode()),
                        (b"connection", b"close"),  # uvicorn closes after this answer
                        (b"x-content-type-options", b"nosniff"),
                    ],
                }
            )
            await send({"type": "http.response.body", "body": body})
            return
        await app(scope, receive, send)

    return guarded
