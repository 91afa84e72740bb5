"""Operating the service (contract §4.6): the ingest queue's bounds, honest readiness through a
router outage and a stalled worker, a start before the router, and a stop under load.

Real parts only: Zenoh routers and clients on free loopback ports (multicast scouting off),
real HTTP, and `topofusion run` as a subprocess stopped by its own pid.
"""

from __future__ import annotations

import json
import re
import signal
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import httpx
import pytest
import zenoh

from service.engine import EngineConfig
from service.transport.ingest_queue import MAX_DROP_KEYS, OTHER_KEYS, BoundedQueue
from service.transport.node import ServiceNode
from service.transport.session import ZenohOptions, open_session
from tests.scenario_helpers import scenario_messages
from tests.support import free_port, put_json, running_service, wait_for, wait_subscribed
from tests.test_cli_process import process


def plot_batch(n: int, radar: str = "A", t0: float = 1_000.0) -> dict[str, Any]:
    """A valid one-plot batch (the radar's site: ``site``)."""
    return {
        "radar_id": radar,
        "seq": n,
        "time_s": t0 + 4.0 * n,
        "plots": {"time_s": [t0 + 4.0 * n], "range_m": [50_000.0], "azimuth_deg": [10.0]},
    }


def hold_the_worker(node: ServiceNode) -> threading.Event:
    """The worker waits before each message until the returned event is set (at most 30 s):
    a worker slower than its input, on purpose."""
    gate = threading.Event()
    real_ingest = node.engine.ingest

    def held_ingest(*args: Any, **kwargs: Any) -> Any:
        gate.wait(timeout=30)
        return real_ingest(*args, **kwargs)

    node.engine.ingest = held_ingest  # type: ignore[method-assign]
    return gate


def site(radar: str) -> dict[str, Any]:
    return {
        "radar_id": radar,
        "latitude_deg": 31.0,
        "longitude_deg": 118.0 + (radar == "B"),
        "altitude_m": 30.0,
        "range_sigma_m": 100.0,
        "azimuth_sigma_deg": 0.1,
        "elevation_sigma_deg": 0.1,
        "scan_period_s": 4.0,
    }


# -- the queue's bounds ------------------------------------------------------------------------


def test_bounded_queue_bounds_count_and_bytes_and_counts_drops_by_key() -> None:
    q = BoundedQueue(max_items=3, max_bytes=100)
    assert q.put("a", 60, "k/a") and not q.put("b", 60, "k/b")  # 120 bytes > 100
    assert q.put("c", 40, "k/c") and q.put("d", 0, "k/d") and not q.put("e", 0, "k/e")  # 3 items
    assert q.dropped == {"k/b": 1, "k/e": 1} and q.nbytes() == 100
    assert q.last_drop == "no room for 0.00 s"  # (the drop's log line says why)
    assert [q.get_nowait() for _ in range(3)] == ["a", "c", "d"] and q.nbytes() == 0
    assert q.put("big", 10_000, "k/big")  # one sample always fits an empty queue
    assert not q.put("x", 1, "k/x")
    # a waiting producer gets in as soon as the consumer makes room, not at its deadline
    threading.Timer(0.1, q.get_nowait).start()
    t0 = time.monotonic()
    assert q.put("y", 1, "k/y", timeout_s=5.0)
    assert time.monotonic() - t0 < 2.0
    # drops on made-up keys are bounded in number of keys
    flood = BoundedQueue(max_items=1, max_bytes=10)
    flood.put("first", 1, "k")
    for i in range(MAX_DROP_KEYS + 50):
        flood.put(i, 1, f"junk/{i}")
    counts = flood.dropped_counts()
    assert len(counts) == MAX_DROP_KEYS + 1 and counts[OTHER_KEYS] == 50
    assert flood.dropped_total == MAX_DROP_KEYS + 50


def test_fair_queue_takes_sources_in_turn_and_drops_a_flooders_excess_at_once() -> None:
    """A flooding source holds at most its share of the queue and its excess is dropped at once,
    counted under its key, while the others get in; the worker takes samples in arrival order,
    but never two of the flooder's while another source's sample waits.  When others press too
    (a replay as fast as it goes) a sample waits for room instead (push-back)."""
    q = BoundedQueue(max_items=128, max_bytes=10**6, fair_by=lambda key: key.split("/")[1])
    assert q.put("a0", 1, "fusion/A/plots") and q.put("b0", 1, "fusion/B/plots")  # A and B seen
    flood = [q.put(f"f{i}", 1, "fusion/F/plots", timeout_s=5.0) for i in range(500)]
    share = 128 // 2  # F alone holds more than a few samples; and room for one more
    assert sum(flood) == share and q.dropped == {"fusion/F/plots": 500 - share}
    assert all(flood[:share]) and not any(flood[share:])  # the excess dropped, each at once
    assert q.last_drop == "its source holds its fair share of the queue already (dropped at once)"
    assert q.put("a1", 1, "fusion/A/plots") and q.put("b1", 1, "fusion/B/plots")  # others lose nothing
    taken = [q.get_nowait() for _ in range(7)]
    # in arrival order, but after one of the flooder's the oldest of another source comes next
    assert taken == ["a0", "b0", "f0", "a1", "f1", "b1", "f2"]
    assert q.items() == [f"f{i}" for i in range(3, share)]
    assert q.classes() == {"F"}  # the sources with samples still queued (the feed's watch)
    # busy with everyone: a sample over its share waits for room (here: until one is taken)
    busy = BoundedQueue(max_items=64, max_bytes=10**6, fair_by=lambda key: key)
    for i in range(64):
        assert busy.put(i, 1, "ab"[i % 2])
    threading.Timer(0.1, busy.get_nowait).start()
    assert busy.put("late", 1, "a", timeout_s=5.0)


def test_a_full_queue_never_blocks_zenoh_beyond_the_bound(router: str, client: zenoh.Session) -> None:
    """The worker is held on purpose; Zenoh's callback waits at most `queue_wait_s` per sample,
    the drops are counted by key, and every sample is either processed or counted dropped."""
    bound = 0.2
    node = ServiceNode(
        EngineConfig(),
        ZenohOptions(mode="client", connect=(router,)),
        queue_size=2,
        queue_wait_s=bound,
        correlation_process=False,
    )
    gate = hold_the_worker(node)
    callback_s: list[float] = []
    real_callback = node._on_sample

    def timed_callback(sample: zenoh.Sample) -> None:  # Zenoh's network thread runs this
        t0 = time.monotonic()
        real_callback(sample)
        callback_s.append(time.monotonic() - t0)

    node._on_sample = timed_callback  # type: ignore[method-assign]
    node.start()
    try:
        wait_subscribed(client, "fusion/radar/A/plots")
        sent = Counter[str]()
        for radar in ("A", "B"):
            put_json(client, f"fusion/radar/{radar}/site", site(radar))
            sent[f"fusion/radar/{radar}/site"] += 1
        for n in range(1, 9):
            for radar in ("A", "B"):
                put_json(client, f"fusion/radar/{radar}/plots", plot_batch(n, radar))
                sent[f"fusion/radar/{radar}/plots"] += 1
        wait_for(lambda: len(callback_s) == sum(sent.values()), timeout=30)
        assert max(callback_s) < bound + 0.15, max(callback_s)
        dropped = node.status()["queue"]["dropped_by_key"]
        assert set(dropped) <= set(sent) and sum(dropped.values()) > 0
        assert {k for k in dropped if k.endswith("/plots")} == {k for k in sent if k.endswith("/plots")}
        gate.set()
        wait_for(
            lambda: node.queue.empty() and node.processed + node.queue.dropped_total == sum(sent.values())
        )
        status = node.status()
        assert status["rejected"] == {}  # every sample that got in was processed as valid input
        assert status["queue"]["dropped"] == sum(dropped.values())
        assert status["queue"]["capacity"] == 2 and status["queue"]["dropped_by_key"] == dropped
    finally:
        gate.set()
        node.stop()


# -- readiness ---------------------------------------------------------------------------------


def test_readyz_follows_a_router_outage_and_counts_are_exact() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    options = ZenohOptions(mode="router", listen=(endpoint,))
    router = open_session(options)
    publisher: zenoh.Session | None = None
    try:
        with running_service(endpoint, correlation_process=False) as svc:
            publisher = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
            stream = [(k, p) for k, p in scenario_messages("two-radar", duration_s=120.0) if "/A/" in k]
            site = next(p for k, p in stream if k.endswith("/site"))
            batches = [(k, p) for k, p in stream if k.endswith("/plots")][:24]
            wait_subscribed(publisher, "fusion/radar/A/plots")
            put_json(publisher, "fusion/radar/A/site", site)
            for key, payload in batches[:8]:
                put_json(publisher, key, payload)

            def row() -> dict[str, Any]:
                radars = svc.http.get("/status").json()["radars"]
                return radars[0] if radars else {"batches": 0, "lost_batches": 0}

            wait_for(lambda: row()["batches"] == 8)

            router.close()  # the router dies
            wait_for(lambda: svc.http.get("/readyz").status_code == 503, timeout=10)
            assert svc.http.get("/readyz").json()["reason"] == "no zenoh connection"
            assert svc.http.get("/healthz").status_code == 200
            for key, payload in batches[8:16]:  # published into the outage: lost on the way
                put_json(publisher, key, payload)

            router = open_session(options)  # back on the same endpoint
            wait_for(lambda: svc.http.get("/readyz").status_code == 200, timeout=20)
            wait_for(lambda: bool(publisher.info.routers_zid()), timeout=20)
            wait_subscribed(publisher, "fusion/radar/A/plots", timeout=20)
            for key, payload in batches[16:]:
                put_json(publisher, key, payload)

            wait_for(lambda: row()["batches"] == 16, timeout=20)
            last_seq = json.loads(batches[-1][1])["seq"]
            first_seq = json.loads(batches[0][1])["seq"]
            assert row()["batches"] + row()["lost_batches"] == last_seq - first_seq + 1 == 24
            assert row()["lost_batches"] == 8
            assert svc.http.get("/status").json()["rejected"] == {}
    finally:
        if publisher is not None:
            publisher.close()
        router.close()


def test_readyz_says_a_stalled_worker_and_recovers(router: str, client: zenoh.Session) -> None:
    with running_service(router, correlation_process=False, stall_s=0.5) as svc:
        gate = hold_the_worker(svc.node)
        try:
            wait_subscribed(client, "fusion/radar/A/plots")
            put_json(client, "fusion/radar/A/site", site("A"))
            for n in range(1, 4):
                put_json(client, "fusion/radar/A/plots", plot_batch(n))
            # (503 for that reason: under load another one, a link's watcher not seeing the
            # router for a moment, can come first, and pass)
            wait_for(lambda: svc.http.get("/readyz").json().get("reason") == "worker stalled", timeout=10)
            assert svc.http.get("/readyz").status_code == 503
        finally:
            gate.set()
        wait_for(lambda: svc.http.get("/readyz").status_code == 200, timeout=10)


# -- start before the router, stop under load ----------------------------------------------------


def _get(url: str) -> httpx.Response | None:
    try:
        return httpx.get(url, timeout=2)
    except httpx.HTTPError:
        return None


def test_a_service_started_before_its_router_waits_for_it() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hport = free_port()
    url = f"http://127.0.0.1:{hport}"
    args = ["run", "--mode", "client", "--connect", endpoint, "--http-port", str(hport)]
    with process(args) as proc:
        wait_for(lambda: _get(url + "/healthz") is not None or proc.poll() is not None, timeout=30)
        assert proc.poll() is None
        ready = _get(url + "/readyz")
        assert ready is not None and ready.status_code == 503
        assert ready.json()["reason"] == "connecting to zenoh"
        time.sleep(1.0)  # a few attempts with back-off
        router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
        try:
            wait_for(lambda: (r := _get(url + "/readyz")) is not None and r.status_code == 200, timeout=30)
            publisher = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
            try:
                stream = scenario_messages("two-radar", duration_s=20.0)
                wait_subscribed(publisher, "fusion/radar/A/plots")
                for key, payload in stream:
                    put_json(publisher, key, payload)
                n = sum(k.endswith("/plots") for k, _ in stream)
                wait_for(lambda: sum(r["batches"] for r in httpx.get(url + "/status").json()["radars"]) == n)
            finally:
                publisher.close()
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=30)
        finally:
            router.close()
    assert proc.returncode == 0, out
    assert "retrying with back-off" in out and "zenoh router reached" in out
    assert "Traceback" not in out, out


STOP_LINE = re.compile(
    r"stop: (?:processed all (\d+) queued samples|.* processed (\d+), (\d+) of (\d+) queued samples left "
    r"unprocessed).* (\d+) plot batches processed in all"
)


#: Outputs are put with congestion control DROP, which gives up on a sample after Zenoh's
#: ``wait_before_drop`` (1 ms) without room in the link's queue: a loaded machine may lose
#: one.  The stop tests count every TrackBatch, so their service waits up to 5 s instead.
PATIENT_ZENOH = (
    "{transport: {link: {tx: {queue: {congestion_control: {drop: {wait_before_drop: 5000000}}}}}}}"
)


def _stop_under_load(
    stream: list[tuple[str, bytes]], grace_s: float, tmp_path: Path
) -> tuple[str, Counter[str], Counter[str]]:
    """`topofusion run` takes ``stream`` faster than it can process it and gets SIGTERM with
    half of it queued: its output, the plot batches sent by radar and the `TrackBatch`es received by radar."""
    zport, hport = free_port(), free_port()
    listen = f"tcp/127.0.0.1:{zport}"
    url = f"http://127.0.0.1:{hport}"
    config = tmp_path / "zenoh.json5"
    config.write_text(PATIENT_ZENOH)
    args = [
        "run",
        "--mode",
        "peer",
        "--listen",
        listen,
        "--http-port",
        str(hport),
        "--zenoh-config",
        str(config),
    ]
    env = {"TOPOFUSION_STOP_GRACE_S": str(grace_s)}
    received = Counter[str]()
    sent = Counter(json.loads(p)["radar_id"] for k, p in stream if k.endswith("/plots"))
    with process(args, env) as proc:
        wait_for(lambda: (r := _get(url + "/readyz")) is not None and r.status_code == 200, timeout=30)
        session = open_session(ZenohOptions(mode="client", connect=(listen,)))
        try:

            def on_tracks(sample: zenoh.Sample) -> None:
                received[str(sample.key_expr).split("/")[2]] += 1

            tracks = session.declare_subscriber("fusion/radar/*/tracks", on_tracks)
            wait_subscribed(session, "fusion/radar/A/plots")
            for key, payload in stream:
                put_json(session, key, payload)

            # The signal once the service has taken (queued) at least half of the stream; what
            # is still on its way then is not taken at all.
            wait_for(lambda: httpx.get(url + "/status").json()["queue"]["depth"] >= len(stream) // 2)
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=grace_s + 30)
            # the last puts on their way: until every batch the service says it processed has
            # come (at most 5 s; the callers' assertions judge what came)
            stop = STOP_LINE.search(out)
            processed = int(stop.group(5)) if stop is not None else 0
            deadline = time.monotonic() + 5.0
            while sum(received.values()) < processed and time.monotonic() < deadline:
                time.sleep(0.05)
            tracks.undeclare()
        finally:
            session.close()
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out
    return out, sent, received


@pytest.fixture(scope="module")
def heavy_stream() -> list[tuple[str, bytes]]:
    """A stream the worker needs seconds for, published in a fraction of that."""
    return scenario_messages("two-radar", duration_s=400.0)


@pytest.mark.slow
def test_sigterm_under_load_drains_the_queue_and_publishes_the_final_outputs(
    heavy_stream: list[tuple[str, bytes]], tmp_path: Path
) -> None:
    out, sent, received = _stop_under_load(heavy_stream, grace_s=60.0, tmp_path=tmp_path)
    line = STOP_LINE.search(out)
    assert line is not None and line.group(1) is not None, out
    assert int(line.group(1)) > 0, "nothing was queued at SIGTERM: the test did not load the service"
    # One TrackBatch per plot batch processed: the queue's outputs were all published.  (What
    # was still in flight on the network at the signal never reached the service.)
    assert sum(received.values()) == int(line.group(5)) <= sum(sent.values()), (received, out)


def test_sigterm_with_a_short_grace_counts_exactly_what_it_leaves(
    heavy_stream: list[tuple[str, bytes]], tmp_path: Path
) -> None:
    out, sent, received = _stop_under_load(heavy_stream, grace_s=0.5, tmp_path=tmp_path)
    line = STOP_LINE.search(out)
    assert line is not None and line.group(2) is not None, out
    processed, left, queued = int(line.group(2)), int(line.group(3)), int(line.group(4))
    assert left > 0 and processed + left == queued  # every queued sample: processed or counted
    plots_left = int(re.search(r"\((\d+) plot batches\)", out).group(1))  # type: ignore[union-attr]
    assert sum(received.values()) == int(line.group(5)) <= sum(sent.values()) - plots_left, (received, out)


def test_a_stop_while_connecting_ends_the_connector_and_leaks_no_session(
    caplog: pytest.LogCaptureFixture,
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nobody listens
    node = ServiceNode(
        EngineConfig(), ZenohOptions(mode="client", connect=(endpoint,)), correlation_process=False
    )
    node.start()
    assert node.not_ready_reason == "connecting to zenoh"
    t0 = time.monotonic()
    with caplog.at_level("INFO"):
        node.stop()
    assert time.monotonic() - t0 < 5.0
    assert node._session is None and "no zenoh session was open" in caplog.text
    # a router that comes up now is not joined by the stopped node
    router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
    try:
        time.sleep(1.0)
        assert node._session is None
        assert not [t for t in threading.enumerate() if t.name == "topofusion-connect"]
    finally:
        router.close()


def test_a_payload_above_the_bound_is_rejected_without_being_queued(
    router: str, client: zenoh.Session
) -> None:
    from service.wire.models import MAX_PAYLOAD_BYTES

    node = ServiceNode(
        EngineConfig(), ZenohOptions(mode="client", connect=(router,)), correlation_process=False
    )
    node.start()
    try:
        wait_subscribed(client, "fusion/radar/A/plots")
        put_json(client, "fusion/radar/A/site", site("A"))
        # (BLOCK: a message this large is otherwise dropped when Zenoh's queues are busy)
        client.put(
            "fusion/radar/A/plots",
            b" " * (MAX_PAYLOAD_BYTES + 1),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        put_json(client, "fusion/radar/A/plots", plot_batch(1))
        put_json(client, "fusion/radar/A/plots", plot_batch(2))
        wait_for(lambda: node.processed == 4, timeout=30)
    finally:
        node.stop()  # (which flushes: the sequencer may hold the newest batch for the watermark)
    status = node.status()
    assert status["rejected"] == {"too_large": 1}
    assert status["radars"][0]["batches"] == 2  # the valid batches after it, as if it were not there
    assert node.queue.high_water_bytes < MAX_PAYLOAD_BYTES  # never held in the queue


def test_the_other_workers_queue_is_bounded_too(router: str, client: zenoh.Session) -> None:
    """Partitioned: anyone who may put on the keys workers send each other could flood the queue
    those messages take ahead of inputs; it has the same bounds, and drops are counted by key."""
    from service.pipeline.partition import Partition

    node = ServiceNode(
        EngineConfig(partition=Partition(1, 2)),
        ZenohOptions(mode="client", connect=(router,)),
        queue_size=3,
        queue_wait_s=0.1,
        correlation_process=False,
    )
    gate = hold_the_worker(node)
    node.start()
    try:
        key = "fusion/registration/A/B"
        wait_subscribed(client, key)
        for _ in range(10):
            client.put(key, b"{}")
        wait_for(lambda: node.peer_queue.dropped_total > 0, timeout=30)
        assert node.peer_queue.qsize() <= 3
        assert node.status()["queue"]["dropped_by_key"][key] > 0
    finally:
        gate.set()
        node.stop()


def test_a_worker_does_not_hear_back_what_it_puts_for_the_others(router: str, client: zenoh.Session) -> None:
    """A partitioned worker's track states reach the others, not its own queue of the others'
    messages: the keys it takes from them take other sessions' samples only."""
    from service.pipeline.partition import Partition

    partition = Partition(1, 2)
    node = ServiceNode(
        EngineConfig(partition=partition),
        ZenohOptions(mode="client", connect=(router,)),
        correlation_process=False,
    )
    heard: list[str] = []
    sub = client.declare_subscriber("fusion/radar/*/track-states", lambda s: heard.append(str(s.key_expr)))
    node.start()
    try:
        stream = scenario_messages("three-radar", duration_s=30.0)
        own = [(k, p) for k, p in stream if partition.owns(k.split("/")[2])]
        assert own, "worker 1 of 2 owns a radar of the scenario"
        wait_subscribed(client, own[0][0])
        for key, payload in own:
            put_json(client, key, payload)
        wait_for(lambda: len(heard) >= 5, timeout=30)
        assert node.peer_queue.taken == 0 and node.peer_queue.qsize() == 0
    finally:
        sub.undeclare()
        node.stop()


def test_a_router_that_refuses_the_session_is_told_from_one_that_is_down(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Zenoh says "unable to connect" both when nothing listens and when the far end refuses the
    session (credentials it does not take, or no Zenoh router at all); the log tells them apart."""
    import socket

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    endpoint = f"tcp/127.0.0.1:{listener.getsockname()[1]}"

    def refuse() -> None:  # accepts every connection and hangs up at once: no Zenoh session
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            conn.close()

    threading.Thread(target=refuse, daemon=True).start()
    node = ServiceNode(
        EngineConfig(), ZenohOptions(mode="client", connect=(endpoint,)), correlation_process=False
    )
    try:
        with caplog.at_level("WARNING"):
            node.start()
            wait_for(lambda: "refused the session" in caplog.text, timeout=30)
        assert node.not_ready_reason == "connecting to zenoh"
        assert f"zenoh router at {endpoint} accepts connections" in caplog.text
    finally:
        node.stop()
        listener.close()
