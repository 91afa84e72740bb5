"""Outputs that agree with each other and come promptly (contract §5.1), through the public
interface: a scenario streamed into the running service over Zenoh, every output heard by a
subscriber and checked after every single one; the HTTP snapshot checked as a client reads it."""

from __future__ import annotations

import json
import threading
from typing import Any

import pytest
import zenoh

from service.recording.completion import RecordingEnd
from service.recording.reader import RecordedMessage
from tests.scenario_helpers import scenario_messages
from tests.support import put_json, running_service, wait_for, wait_subscribed
from topofusion_lab.evaluation.promptness import OutputMonitor


def _end(stream: list[tuple[str, bytes]]) -> float:
    """The data time through which the service can be complete once it has the whole stream."""
    end = RecordingEnd()
    for key, payload in stream:
        kind = key.split("/")[-1]
        end.add(RecordedMessage(key, "plots" if kind == "plots" else "site", payload, 0, 0, 0))  # type: ignore[arg-type]
    target = end.target_s()
    assert target is not None
    return target


@pytest.mark.slow
def test_every_output_names_only_tracks_the_latest_tables_hold(router: str, client: zenoh.Session) -> None:
    stream = scenario_messages("three-radar", duration_s=150.0, seed=3)
    scans = {
        json.loads(p)["radar_id"]: json.loads(p)["scan_period_s"] for k, p in stream if k.endswith("/site")
    }
    heard: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            heard.append((str(sample.key_expr), sample.payload.to_bytes()))

    # one subscriber for every output: one callback sequence, in the order the service put them
    subscribers = [client.declare_subscriber("fusion/**", on_sample)]
    try:
        with running_service(router) as svc:
            wait_subscribed(client, "fusion/radar/A/plots")
            for key, payload in stream:
                put_json(client, key, payload)
            end = _end(stream)

            def complete() -> bool:
                st = svc.http.get("/status").json()
                return bool(st["outputs_time_s"] is not None and st["outputs_time_s"] >= end)

            wait_for(complete, timeout=90, interval=0.2)
            status = svc.http.get("/status").json()
            pairs = svc.http.get("/pairs", params={"status": "all"}).json()
            tables = {
                rid: {
                    t["track_id"]
                    for t in svc.http.get(f"/radars/{rid}/tracks", params={"status": "all"}).json()["tracks"]
                }
                for rid in scans
            }
            system = svc.http.get("/system-tracks", params={"status": "all"}).json()
            wait_for(lambda: len(heard) >= 100, timeout=10)
    finally:
        for sub in subscribers:
            sub.undeclare()

    assert status["correlation"]["pending"] == 0
    # every output, as a subscriber hears them one after the other
    monitor = OutputMonitor(scans)
    with lock:
        for key, payload in heard:
            monitor.feed(key, json.loads(payload))
    report = monitor.report()
    assert report.dangling.references == 0, report.dangling.examples
    assert report.confirmed_at_end >= 100 and report.false_at_end == 0
    # promptly, in scans of the slower radar: within a scan, the cold start included (this
    # stream is mostly the service's first minute, before the radars are registered)
    assert report.median <= 0.5 and report.p95 <= 1.0, report.lines()
    # the HTTP snapshot is whole too: pairs and system tracks name tracks the same snapshot holds
    named = [(ps["radar_a"], p["track_a"]) for ps in pairs for p in ps["pairs"]]
    named += [(ps["radar_b"], p["track_b"]) for ps in pairs for p in ps["pairs"]]
    named += [(m["radar_id"], m["track_id"]) for t in system["system_tracks"] for m in t["members"]]
    assert named and all(tid in tables[rid] for rid, tid in named)


@pytest.mark.slow
def test_a_track_that_goes_leaves_its_pairs_in_the_same_release() -> None:
    """Engine level, message by message: after a radar's table drops tracks, no pair set or
    system track of that release or later names them (the pair's own update may be scans away)."""
    from service.engine import Engine

    stream = scenario_messages("three-radar", duration_s=240.0, seed=5)
    scans = {
        json.loads(p)["radar_id"]: json.loads(p)["scan_period_s"] for k, p in stream if k.endswith("/site")
    }
    engine = Engine()
    monitor = OutputMonitor(scans)
    dropped = 0
    last: dict[str, set[str]] = {}
    for key, payload in stream:
        for out in engine.ingest(key, payload, receive_time_s=0.0):
            body: Any = out.body()
            monitor.feed(out.key, body)
            if out.key.endswith("/tracks") and "/radar/" in out.key:
                ids = {t["track_id"] for t in body["tracks"]}
                dropped += len(last.get(body["radar_id"], set()) - ids)
                last[body["radar_id"]] = ids
    engine.close()
    assert dropped > 10  # the stream does delete tracks (aircraft leave, clutter tracks die)
    assert monitor.report().dangling.references == 0
