"""Helpers the tests import: free ports, polling, Zenoh puts, and the real service in-process.

The pytest fixtures built on them stay in conftest.py (tests never import conftest).  Everything
stays on 127.0.0.1 with ports picked at run time.
"""

from __future__ import annotations

import contextlib
import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import uvicorn
import zenoh

from service.api.app import create_app
from service.engine import Engine, EngineConfig
from service.settings import Settings
from service.tracking.base import TrackTable
from service.transport.node import ServiceNode
from service.transport.session import ZenohOptions, open_session
from service.wire.outgoing import Outgoing

_HANDED_OUT: set[int] = set()


def free_port() -> int:
    """A loopback port free now and never handed out before in this process: the kernel may
    give a just-released port again, and two settings of one test (a Zenoh endpoint and an
    HTTP port) must never meet on one."""
    for _ in range(1000):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port not in _HANDED_OUT:
            _HANDED_OUT.add(port)
            return port
    raise RuntimeError("no loopback port left that this process has not handed out")


@contextlib.contextmanager
def zenoh_router() -> Iterator[str]:
    """A router-mode Zenoh session on a free loopback port (multicast scouting off, as every
    session opened through ``open_session``); yields its endpoint, closes it after."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
    try:
        yield endpoint
    finally:
        session.close()


def wait_for(predicate: Callable[[], Any], timeout: float = 10.0, interval: float = 0.05) -> Any:
    """Poll until ``predicate()`` is truthy; fail the test with a clear message otherwise."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"condition not met within {timeout} s (last value: {last!r})")


def wait_subscribed(session: zenoh.Session, key: str, timeout: float = 10.0) -> None:
    """Wait until a subscriber matching ``key`` is known to ``session`` (a put before that is lost)."""
    publisher = session.declare_publisher(key)
    try:
        wait_for(lambda: publisher.matching_status.matching, timeout=timeout)
    finally:
        publisher.undeclare()


def put_json(session: zenoh.Session, key: str, body: Any) -> None:
    """Put as a radar publisher should: blocking, so that a busy machine slows the
    test down instead of dropping samples (Zenoh's default for ``put`` drops under congestion)."""
    payload = body if isinstance(body, bytes) else json.dumps(body).encode()
    session.put(
        key,
        payload,
        encoding=zenoh.Encoding.APPLICATION_JSON,
        congestion_control=zenoh.CongestionControl.BLOCK,
    )


def _time_s(payload: bytes) -> float | None:
    try:
        value = json.loads(payload).get("time_s")
    except (ValueError, AttributeError):
        return None
    return float(value) if isinstance(value, (int, float)) else None


@contextlib.contextmanager
def paced_stream(
    client: zenoh.Session, stream: list[tuple[str, bytes]], opening_s: float, speed: float
) -> Iterator[threading.Event]:
    """Publish ``stream`` on a thread of its own: its first ``opening_s`` data seconds at once,
    the rest at ``speed`` times real time.  Yields an event set once the whole stream is out;
    the thread is stopped at the exit."""
    published, stop = threading.Event(), threading.Event()

    def publish() -> None:
        start = next(t for k, p in stream if k.endswith("/plots") and (t := _time_s(p)))
        wall = time.monotonic()
        for key, payload in stream:
            if stop.is_set():
                return
            t = _time_s(payload) if key.endswith("/plots") else None
            if t is not None and t - start > opening_s:
                ahead = (t - start - opening_s) / speed - (time.monotonic() - wall)
                if ahead > 0 and stop.wait(ahead):
                    return
            elif t is not None:
                wall = time.monotonic()
            put_json(client, key, payload)
        published.set()

    thread = threading.Thread(target=publish, name="stream", daemon=True)
    thread.start()
    try:
        yield published
    finally:
        stop.set()
        thread.join(timeout=30)
        assert not thread.is_alive(), "publisher did not stop"


@dataclass
class RunningService:
    node: ServiceNode
    http: httpx.Client
    base_url: str


@contextlib.contextmanager
def running_service(
    router: str,
    config: EngineConfig | None = None,
    radars: tuple[str, ...] = (),
    correlation_process: bool = True,
    wait_ready: bool = True,
    settings: Settings | None = None,
    **node_kw: Any,
) -> Iterator[RunningService]:
    """The real service in-process: a client session to ``router``, the worker, uvicorn on a free
    port (``node_kw``: more of :class:`ServiceNode`'s options).  ``settings``: the node is the
    command's, built from them (``ServiceNode.from_settings``; their Zenoh settings are its)."""
    holder: dict[str, ServiceNode] = {}

    def factory() -> ServiceNode:
        if settings is not None:
            holder["node"] = ServiceNode.from_settings(settings)
            return holder["node"]
        options = ZenohOptions(mode="client", connect=(router,))
        holder["node"] = ServiceNode(
            config or EngineConfig(),
            options,
            radars=radars,
            correlation_process=correlation_process,
            **node_kw,
        )
        return holder["node"]

    app = create_app(factory)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=base, timeout=10.0) as http:
            wait_for(lambda: server.started, timeout=15)
            if wait_ready:
                wait_for(lambda: http.get("/readyz").status_code == 200, timeout=15)
            yield RunningService(holder["node"], http, base)
    finally:
        server.should_exit = True
        thread.join(timeout=10)
        sock.close()
        assert not thread.is_alive(), "uvicorn did not stop"


def run_engine(
    messages: list[tuple[str, bytes]], config: EngineConfig | None = None
) -> tuple[Engine, list[Outgoing]]:
    """Every message through a fresh engine (receipt time 0), then a flush: the engine and what
    it published."""
    engine = Engine(config or EngineConfig())
    out = []
    for key, payload in messages:
        out.extend(engine.ingest(key, payload, receive_time_s=0.0))
    out.extend(engine.flush())
    return engine, out


def random_track_table(rng: np.random.Generator, ids: list[str]) -> TrackTable:
    """A table of ``ids`` with random states, labels and qualities, in id order."""
    n = len(ids)
    truth = np.array([f"t{i}" if i % 3 else None for i in range(n)], dtype=object)
    return TrackTable(
        np.asarray(ids, dtype=str),
        rng.random(n) > 0.5,
        rng.random(n) * 100,
        rng.normal(size=(n, 3)) * 1e6,
        rng.normal(size=(n, 3)) * 100,
        rng.normal(size=(n, 6, 6)),
        rng.integers(0, 50, n),
        truth,
        quality=np.where(rng.random(n) < 0.2, np.nan, rng.random(n)),
    ).by_id()
