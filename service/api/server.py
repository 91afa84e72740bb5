"""The HTTP server: uvicorn with a request-head timeout and a connection cap.

uvicorn (its h11 and its httptools protocol alike) arms a timer on a connection only once a
response has ended (the keep-alive timeout): a connection that opens and never completes its
request head stays open for ever, and nothing caps the connections.  Its own
``limit_concurrency`` does not help: past it every request, the probes' too, is answered 503,
and the connections stay open.  :class:`GuardedH11Protocol` adds both to uvicorn's h11
protocol (the one this service installs: its ``uvicorn`` has no ``httptools``):

* **request-head timeout**: a connection must deliver a whole request head within
  ``header_timeout_s`` of being opened, and of its previous response ending, or it is closed
  (slow-header and trickle connections included: bytes arriving do not restart the clock);
* **connection cap**: at ``max_connections`` a new connection closes the connection that has
  waited longest for a request head (one that has sent nothing yet, or is idle between two
  requests) and takes its place; when every connection is in the middle of a request it is
  refused with a 503.  The requests in progress are bounded (``max_requests`` and the
  picture's ``picture_max_clients``, service/api/limits.py), so some connections are always
  waiting, and a health probe always gets in however many idle connections a flood opens
  (docs/operations/http.md says why this, rather than a second port for probes).

It also gives each request, in ``scope["extensions"][CONNECTION_EXTENSION]``: ``abort``, which
resets its connection at once (the picture's feed drops a client that does not read with it,
without the error uvicorn logs for a response left unfinished); ``bound_output(n)``, which
bounds what the connection holds unsent (the feed's streams); and ``closing``, an event set
when the server shuts down (the feed's streams end then rather than being cancelled).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import resource
import socket
import struct
import time
from dataclasses import replace
from typing import Any, ClassVar, cast

import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.api.limits import PROBE_ROOM, HttpLimits

log = logging.getLogger("topofusion.http")

#: Largest request head (bytes) a connection may send; a longer one is answered 400 and closed.
MAX_HEAD_BYTES = 16 * 1024
#: File descriptors kept for everything but HTTP connections (Zenoh, the correlation
#: process's pipes, the state file, logs, the listening socket).
FD_RESERVE = 128
#: Accept batches (``backlog`` connections each) that can be open before the first is looked
#: at: asyncio accepts a batch per pass of its loop and the protocols see it two passes later.
ACCEPT_BATCHES = 4
#: Seconds between two log lines about connections closed by the cap or the head timeout.
LOG_EVERY_S = 10.0
#: ``scope["extensions"]`` key of the request's ``{"abort", "closing", "bound_output"}``.
CONNECTION_EXTENSION = "topofusion.connection"
#: A connection refused at the cap is told so (and the client may try again in a second).
REFUSED = (
    b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain; charset=utf-8\r\n"
    b"content-length: 20\r\nretry-after: 1\r\nconnection: close\r\n\r\ntoo many connections"
)


#: A request head over ``MAX_HEAD_BYTES`` is answered so, and its connection closed.
_TOO_LARGE_BODY = b'{"detail":"request head larger than %d bytes"}' % MAX_HEAD_BYTES
HEAD_TOO_LARGE = (
    b"HTTP/1.1 400 Bad Request\r\ncontent-type: application/json\r\n"
    + b"content-length: %d\r\nconnection: close\r\n\r\n" % len(_TOO_LARGE_BODY)
    + _TOO_LARGE_BODY
)


def head_bytes(scope: dict[str, Any]) -> int:
    """The size of a request head as it came: request line and headers, each line's CRLF."""
    query = scope.get("query_string", b"")
    target = len(scope.get("raw_path", b"")) + (len(query) + 1 if query else 0)
    line = len(scope.get("method", "")) + target + len("  HTTP/1.1\r\n")
    return line + sum(len(name) + len(value) + 4 for name, value in scope.get("headers", ())) + 2


class ConnectionGuard:
    """The open connections of one server, and those waiting for a request head."""

    def __init__(self, limits: HttpLimits) -> None:
        self.limits = limits
        self.open = 0
        #: Waiting for a request head, the longest waiting first (a dict keeps insertion order).
        self.waiting: dict[GuardedH11Protocol, float] = {}
        #: Connections closed for the cap, refused at it, and closed by the head timeout.
        self.evicted = 0
        self.refused = 0
        self.timed_out = 0
        self._logged = (0, 0, 0)
        self._logged_at = -LOG_EVERY_S

    def admit(self) -> bool:
        """Room for one more connection: under the cap, or by closing the longest waiting."""
        if self.open >= self.limits.max_connections:
            oldest = next(iter(self.waiting), None)
            if oldest is None:
                self.refused += 1
                self.report()
                return False
            self.evicted += 1
            oldest.close_now()
            self.report()
        self.open += 1
        return True

    def report(self) -> None:
        """One log line per ``LOG_EVERY_S`` at most, with what happened since the last."""
        now = time.monotonic()
        counts = (self.evicted, self.refused, self.timed_out)
        if now - self._logged_at < LOG_EVERY_S or counts == self._logged:
            return
        evicted, refused, timed_out = (a - b for a, b in zip(counts, self._logged, strict=True))
        if evicted or refused:
            log.warning(
                "HTTP connections at the cap of %d (TOPOFUSION_HTTP_MAX_CONNECTIONS): since the last "
                "report %d waiting for a request head closed for newer ones, %d refused; %d closed "
                "by the request-head timeout",
                self.limits.max_connections,
                evicted,
                refused,
                timed_out,
            )
        else:  # (not at the cap: an idle connection, a browser's spare one, is no alarm)
            log.info(
                "HTTP connections closed by the request-head timeout (TOPOFUSION_HTTP_HEADER_TIMEOUT_S) "
                "since the last report: %d",
                timed_out,
            )
        self._logged, self._logged_at = counts, now


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with the request-head timeout and the connection cap of
    :class:`ConnectionGuard` (one per server: :func:`guarded_protocol`)."""

    guard: ClassVar[ConnectionGuard]

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._head_timer: asyncio.TimerHandle | None = None
        self._admitted = False
        self._seen_cycle: object = None
        #: Set when the server shuts down during the current request (a stream ends then).
        self._closing: asyncio.Event | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if not self.guard.admit():
            transport.write(REFUSED)
            transport.close()
            return
        self._admitted = True
        self._wait_for_head()

    def connection_lost(self, exc: Exception | None) -> None:
        self._leave()
        super().connection_lost(exc)

    def handle_events(self) -> None:
        super().handle_events()
        cycle = self.cycle
        if cycle is not None and cycle is not self._seen_cycle:  # a request head came in whole
            self._seen_cycle = cycle
            self._stop_waiting()
            if head_bytes(cast(dict[str, Any], self.scope)) > MAX_HEAD_BYTES:
                # (h11's own bound holds only while a head is incomplete: one that came in
                # whole in one read is measured here; the request is never answered)
                cycle.disconnected = True
                self.transport.write(HEAD_TOO_LARGE)
                self.close_now()
                return
            self._closing = asyncio.Event()
            scope = cast(dict[str, Any], self.scope)
            scope.setdefault("extensions", {})[CONNECTION_EXTENSION] = {
                "abort": self.abort_now,
                "closing": self._closing,
                "bound_output": self.bound_output,
            }

    def on_response_complete(self) -> None:
        if self._admitted and not self.transport.is_closing():
            self._wait_for_head()  # (the next request, pipelined, stops it at once)
        super().on_response_complete()

    def shutdown(self) -> None:
        # A long response (the picture's feed) ends itself when told, well within uvicorn's
        # graceful-shutdown time, instead of being cancelled at its end.
        if self._closing is not None:
            self._closing.set()
        super().shutdown()

    def close_now(self) -> None:
        """Close the connection (what was written still goes out); it no longer counts."""
        self._leave()
        if not self.transport.is_closing():
            self.transport.close()

    def abort_now(self) -> None:
        """Close the connection and drop what it has not sent yet (a client that does not
        read), the kernel's buffer included: the client is reset."""
        self._leave()
        if self.cycle is not None:
            # at once, not when the loop reports the connection lost: the request's sends
            # return from now on, and its end is no unfinished response
            self.cycle.disconnected = True
        sock = self.transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        self.transport.abort()

    def bound_output(self, send_buffer: int) -> None:
        """Hold at most ``send_buffer`` bytes in the kernel for this connection (Linux doubles
        it for its bookkeeping) and nothing in the server once a write is under way: a send
        returns only when what came before has gone to the kernel."""
        sock = self.transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, send_buffer)
        self.transport.set_write_buffer_limits(high=0)

    # -- the guard's bookkeeping ---------------------------------------------------------------
    def _wait_for_head(self) -> None:
        self._stop_waiting()
        self.guard.waiting[self] = time.monotonic()
        self._head_timer = self.loop.call_later(self.guard.limits.header_timeout_s, self._head_late)

    def _stop_waiting(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None
        self.guard.waiting.pop(self, None)

    def _head_late(self) -> None:
        self._head_timer = None
        self.guard.timed_out += 1
        self.guard.report()
        self.close_now()

    def _leave(self) -> None:
        self._stop_waiting()
        if self._admitted:
            self._admitted = False
            self.guard.open -= 1


def guarded_protocol(limits: HttpLimits) -> type[GuardedH11Protocol]:
    """A protocol class for one server, with a guard of its own."""
    return type("GuardedH11Protocol", (GuardedH11Protocol,), {"guard": ConnectionGuard(limits)})


def fit_file_limit(limits: HttpLimits) -> HttpLimits:
    """``limits`` within the process's open-file limit: the soft limit is raised (up to the
    hard one) to ``max_connections + ACCEPT_BATCHES * backlog + FD_RESERVE``; where it cannot
    be, the cap is lowered to fit, with a warning.  An accept that finds no descriptor left
    stops the server from accepting anything, probes included, for a second at a time."""
    need = limits.max_connections + ACCEPT_BATCHES * limits.backlog + FD_RESERVE
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < need:
        target = need if hard == resource.RLIM_INFINITY else min(need, hard)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    if soft == resource.RLIM_INFINITY or soft >= need:
        return limits
    room = soft - ACCEPT_BATCHES * limits.backlog - FD_RESERVE
    if room < limits.busy_at_most + PROBE_ROOM:
        raise RuntimeError(
            f"the open-file limit ({soft}, hard {hard}) leaves room for {max(room, 0)} HTTP connections, "
            f"fewer than the {limits.busy_at_most + PROBE_ROOM} the other TOPOFUSION_HTTP_* "
            "limits need: raise it (ulimit -n) or lower TOPOFUSION_HTTP_MAX_REQUESTS, "
            "TOPOFUSION_HTTP_PICTURE_MAX_CLIENTS or TOPOFUSION_HTTP_BACKLOG"
        )
    log.warning(
        "the open-file limit (%d, hard %d) leaves room for %d HTTP connections: "
        "TOPOFUSION_HTTP_MAX_CONNECTIONS lowered from %d",
        soft,
        hard,
        room,
        limits.max_connections,
    )
    return replace(limits, max_connections=room)


def server_config(
    app: Any, limits: HttpLimits, host: str = "127.0.0.1", port: int = 8000, **kw: Any
) -> uvicorn.Config:
    """uvicorn's configuration for ``app`` under ``limits`` (``kw``: more of its options)."""
    return uvicorn.Config(
        app,
        host=host,
        port=port,
        http=guarded_protocol(limits),
        ws="none",  # no WebSocket endpoint: an upgrade would leave the guard's protocol
        timeout_keep_alive=limits.keep_alive_s,  # type: ignore[arg-type]
        backlog=limits.backlog,
        h11_max_incomplete_event_size=MAX_HEAD_BYTES,
        **kw,
    )
