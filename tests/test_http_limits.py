"""The HTTP side port's limits (``TOPOFUSION_HTTP_*``, docs/operations/http.md), through the
public interface: the service as ``python -m service run`` with those settings, a Zenoh client
of a router on a free loopback port, and raw connections and HTTP requests against it.

- Connections that never finish their request head, three times the cap: the service holds
  at most the cap of them, closes the rest within the request-head timeout, and ``/healthz``
  and ``/readyz`` answer at once all along.
- A kept-alive connection is closed after the keep-alive timeout; a request head sent a byte
  at a time is closed at the request-head timeout (bytes do not restart its clock).
- Requests beyond the concurrency limit are refused 503 with ``Retry-After``; probes never are.
- A flood past the process's open-file limit (1 024): the cap fits itself under the limit and
  the probes go on answering (before the cap, accept() failed and the probes timed out).
- The limits are settings, checked at start: a cap without room for the probes is refused.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator

import httpx
import pytest

from service.api.limits import PROBE_ROOM, HttpLimits, http_limits
from service.api.server import MAX_HEAD_BYTES
from service.settings import Settings
from tests.http_service import Served, closed_by_peer, ensure_open_files, open_idle, served
from tests.support import free_port, wait_for, zenoh_router

#: The limits the service runs with here (settings), small enough to be reached quickly.
CAP = 100
HEADER_TIMEOUT_S = 4.0
KEEP_ALIVE_S = 1.0
MAX_REQUESTS = 1
PICTURE_MAX_CLIENTS = 32
SETTINGS = {
    "TOPOFUSION_HTTP_MAX_CONNECTIONS": str(CAP),
    "TOPOFUSION_HTTP_HEADER_TIMEOUT_S": str(HEADER_TIMEOUT_S),
    "TOPOFUSION_HTTP_KEEP_ALIVE_S": str(KEEP_ALIVE_S),
    "TOPOFUSION_HTTP_MAX_REQUESTS": str(MAX_REQUESTS),
    "TOPOFUSION_HTTP_PICTURE_MAX_CLIENTS": str(PICTURE_MAX_CLIENTS),
}
#: Idle connections opened against the cap.
FLOOD = 3 * CAP
#: A probe must answer within this (s): the kubelet's default probe timeout (without the
#: limits a probe waited for minutes).
PROBE_MAX_S = 1.0
#: Probes in a row past PROBE_MAX_S that fail a pod (the kubelet's default failureThreshold):
#: one slow answer on a loaded two-core machine restarts nothing, three in a row would.
FAILURES_IN_A_ROW = 3
#: Probes asked while a flood holds its connections (each of /healthz and /readyz).
PROBES = 10
#: Slack (s) on a timeout being seen to act: the server's timer, then this test's polling.
SLACK_S = 1.5
#: An open-file limit as common as it is low, and a flood well past it.
OPEN_FILES = 1024
BIG_FLOOD = 1500
#: How long the big flood keeps reopening what the service closes (s).
BIG_FLOOD_S = 4.0


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    """One router for the module (tests/conftest.py's is per test)."""
    with zenoh_router() as endpoint:
        yield endpoint


@pytest.fixture(scope="module")
def service(router: str) -> Iterator[Served]:
    with served(router, SETTINGS) as svc:
        yield svc


def probe(base_url: str, path: str) -> float:
    """One probe as a kubelet sends it (a new connection); its latency (s)."""
    began = time.perf_counter()
    answer = httpx.get(base_url + path, timeout=5.0)
    took = time.perf_counter() - began
    assert answer.status_code == 200, (path, answer.status_code, answer.text)
    return took


def probe_while(base_url: str, rounds: int) -> list[float]:
    return [probe(base_url, path) for _ in range(rounds) for path in ("/healthz", "/readyz")]


def kubelet_content(latencies: list[float]) -> bool:
    """Whether a kubelet would keep the pod: neither probe of :func:`probe_while` (they
    alternate) ran past its timeout ``FAILURES_IN_A_ROW`` times in a row, and the typical
    probe answered well within it."""
    for path in (0, 1):
        late = 0
        for took in latencies[path::2]:
            late = late + 1 if took >= PROBE_MAX_S else 0
            if late >= FAILURES_IN_A_ROW:
                return False
    return statistics.median(latencies) < PROBE_MAX_S / 2


def test_kubelet_content_counts_failures_in_a_row_per_probe() -> None:
    quick, slow = 0.05, PROBE_MAX_S + 0.1
    assert kubelet_content([quick, quick, slow, quick] * 5)
    # one probe (every other answer) late three times in a row: restarted
    assert not kubelet_content([slow, quick] * 3 + [quick] * 20)
    # late answers spread over both probes are not in a row for either
    assert kubelet_content([slow, slow, quick, quick] * 2 + [quick] * 20)
    assert not kubelet_content([PROBE_MAX_S * 0.6] * 10)  # typical answer too slow


def test_idle_connections_past_the_cap_leave_the_probes_answering(service: Served) -> None:
    # half send nothing at all, half the start of a request head that never ends
    silent = open_idle(service.host, service.port, FLOOD // 2)
    partial = open_idle(
        service.host, service.port, FLOOD - FLOOD // 2, b"GET /status HTTP/1.1\r\nHost: x\r\n"
    )
    flood = silent + partial
    opened = time.monotonic()
    try:
        latencies = probe_while(service.base_url, PROBES)
        assert kubelet_content(latencies), latencies

        # the cap: the service holds at most CAP connections; the others were closed at once
        wait_for(lambda: sum(not closed_by_peer(s) for s in flood) <= CAP, timeout=SLACK_S)
        held = [s for s in flood if not closed_by_peer(s)]
        assert 0 < len(held) <= CAP
        assert time.monotonic() - opened < HEADER_TIMEOUT_S, "too slow to tell the cap from the timeout"

        # the request-head timeout: the rest go too, once it has run out (and not before)
        wait_for(lambda: all(closed_by_peer(s) for s in held), timeout=HEADER_TIMEOUT_S + SLACK_S)
        assert time.monotonic() - opened >= HEADER_TIMEOUT_S - 0.5

        # and the service goes on
        assert httpx.get(service.base_url + "/status", timeout=5).status_code == 200
        assert kubelet_content(probe_while(service.base_url, 3))
    finally:
        for s in flood:
            s.close()
    assert "HTTP connections at the cap of 100" in service.log()


def _seconds_until_closed(s: socket.socket, limit_s: float) -> float:
    began = time.monotonic()
    wait_for(lambda: closed_by_peer(s), timeout=limit_s, interval=0.02)
    return time.monotonic() - began


def test_keep_alive_and_trickled_request_heads_time_out(service: Served) -> None:
    kept = socket.create_connection((service.host, service.port))
    trickle: socket.socket | None = None
    try:
        kept.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        answer = b""
        while not answer.endswith(b'{"status":"ok"}'):
            answer += kept.recv(4096)
        kept.setblocking(False)
        idle = _seconds_until_closed(kept, KEEP_ALIVE_S + SLACK_S)
        assert idle >= KEEP_ALIVE_S - 0.3, idle

        # a header line every 0.4 s: the head never ends, and its bytes keep nothing open
        trickle = socket.create_connection((service.host, service.port))
        began = time.monotonic()
        trickle.setblocking(False)
        trickle.send(b"GET /healthz HTTP/1.1\r\n")
        while not closed_by_peer(trickle):
            assert time.monotonic() - began < HEADER_TIMEOUT_S + SLACK_S, "the trickle is still open"
            trickle.send(b"X-Slow: 1\r\n")
            time.sleep(0.4)
        assert time.monotonic() - began >= HEADER_TIMEOUT_S - 0.5
    finally:
        kept.close()
        if trickle is not None:
            trickle.close()


def _answer(service: Served, head: bytes, piece: int) -> bytes:
    """What the service answers ``head`` sent in writes of ``piece`` bytes (until it closes)."""
    with socket.create_connection((service.host, service.port)) as conn:
        conn.settimeout(10)
        with contextlib.suppress(OSError):  # (a peer that closed early resets the rest)
            for at in range(0, len(head), piece):
                conn.sendall(head[at : at + piece])
        answer = b""
        with contextlib.suppress(OSError):
            while chunk := conn.recv(65536):
                answer += chunk
    return answer


@pytest.mark.parametrize("piece", [1 << 20, 1024], ids=["in one write", "in pieces"])
def test_a_request_head_over_16_kib_is_refused_however_it_arrives(service: Served, piece: int) -> None:
    def head(size: int) -> bytes:
        start, end = b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: ", b"\r\nConnection: close\r\n\r\n"
        return start + b"a" * (size - len(start) - len(end)) + end

    assert _answer(service, head(MAX_HEAD_BYTES - 64), piece).startswith(b"HTTP/1.1 200")
    for size in (MAX_HEAD_BYTES + 64, 4 * MAX_HEAD_BYTES):
        answer = _answer(service, head(size), piece)
        assert answer.startswith(b"HTTP/1.1 400"), (size, answer[:200])


def test_requests_past_the_concurrency_limit_are_refused_but_probes_are_not(service: Served) -> None:
    codes: Counter[int] = Counter()
    retry_after: set[str | None] = set()
    probes: list[float] = []
    lock = threading.Lock()
    stop = threading.Event()

    def ask() -> None:
        # at least 25 requests each, and on until the watcher has its probes: every probe is
        # asked while the flood goes on (a handful asked in the flood's first second, when
        # the other tests' processes share the two cores too, made a median of noise)
        with httpx.Client(base_url=service.base_url, timeout=10) as http:
            done = 0
            while done < 25 or not stop.is_set():
                answer = http.get("/status")
                done += 1
                with lock:
                    codes[answer.status_code] += 1
                    if answer.status_code == 503:
                        retry_after.add(answer.headers.get("retry-after"))

    def watch() -> None:
        probes.extend(probe_while(service.base_url, PROBES))
        stop.set()

    askers = [threading.Thread(target=ask) for _ in range(8)]
    watcher = threading.Thread(target=watch)
    for t in askers:
        t.start()
    watcher.start()
    watcher.join(timeout=60)
    stop.set()
    for t in askers:
        t.join(timeout=60)
    assert set(codes) == {200, 503}, codes  # one at a time: some waited for none and got in
    assert retry_after == {"1"}
    assert len(probes) == 2 * PROBES and kubelet_content(probes), probes


@pytest.mark.slow
def test_a_flood_past_the_open_file_limit_leaves_the_probes_answering(router: str) -> None:
    """The service under a 1 024-file limit with the default limits: it fits its cap under the
    limit (saying so), and a flood of 1 500 connections kept open never exhausts it."""
    ensure_open_files(BIG_FLOOD + 64)
    with served(router, {}, open_files=OPEN_FILES) as svc:
        assert f"lowered from {HttpLimits().max_connections}" in svc.log()
        flood = open_idle(svc.host, svc.port, BIG_FLOOD)
        latencies: list[float] = []
        try:
            until = time.monotonic() + BIG_FLOOD_S
            while time.monotonic() < until:
                latencies += probe_while(svc.base_url, 1)
                # what the service closed is opened again: the flood keeps its size
                gone = [s for s in flood if closed_by_peer(s)]
                for s in gone:
                    flood.remove(s)
                    s.close()
                flood += open_idle(svc.host, svc.port, len(gone))
            assert kubelet_content(latencies), latencies
        finally:
            for s in flood:
                s.close()
        log = svc.log()
        assert "out of system resource" not in log and "Too many open files" not in log, log[-2000:]


def test_the_limits_are_settings_checked_at_start() -> None:
    assert http_limits(Settings()) == HttpLimits()  # one set of defaults
    least = HttpLimits().busy_at_most + PROBE_ROOM
    env = {"TOPOFUSION_HTTP_MAX_CONNECTIONS": str(least - 1), "PATH": "/usr/bin:/bin"}
    run = subprocess.run(
        [sys.executable, "-m", "service", "run", "--http-port", str(free_port())],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert run.returncode == 2, run.stderr
    assert "TOPOFUSION_HTTP_MAX_CONNECTIONS" in run.stderr and "probes" in run.stderr, run.stderr


def test_an_idle_connection_closed_by_the_head_timeout_is_no_alarm(caplog: pytest.LogCaptureFixture) -> None:
    """A connection closed by the request-head timeout alone (an idle one: a browser's spare
    connection) is said at INFO; only the cap reached is a warning (one idle connection was
    logged as 'at the cap of 512')."""
    from service.api.limits import HttpLimits
    from service.api.server import LOG_EVERY_S, ConnectionGuard

    guard = ConnectionGuard(HttpLimits())
    with caplog.at_level(logging.INFO, logger="topofusion.http"):
        guard.timed_out += 1
        guard.report()
        assert [r.levelno for r in caplog.records] == [logging.INFO]
        assert "at the cap" not in caplog.text and "request-head timeout" in caplog.text
        caplog.clear()
        guard._logged_at -= LOG_EVERY_S  # (the next report's turn)
        guard.refused += 1
        guard.report()
        assert [r.levelno for r in caplog.records] == [logging.WARNING]
        assert "at the cap of 512" in caplog.text
