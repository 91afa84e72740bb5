"""The correlation stage in a child process gives the in-process results (correlation_process.py)."""

from __future__ import annotations

import json
from typing import Any

from service.engine import Engine, EngineConfig
from service.pipeline.correlation_process import ChildProcessRunner
from tests.scenario_helpers import scenario_messages
from topofusion_lab.evaluation.promptness import OutputMonitor


def run(messages: list[tuple[str, bytes]], process: bool) -> tuple[dict[str, Any], list[Any]]:
    engine = Engine(EngineConfig(), correlation_process=process)
    try:
        out = []
        for key, payload in messages:
            out.extend(engine.ingest(key, payload, receive_time_s=0.0))
        out.extend(engine.flush())
        snap = engine.snapshot()
        return {
            "tracks": snap.track_batches("all"),
            "pairs": snap.pair_sets(status="all"),
            "biases": snap.biases(),
            "system": snap.system_tracks("all"),
            "updates": snap.correlation["updates"],
        }, out
    finally:
        engine.close()


def test_same_tracks_pairs_and_biases_as_in_process() -> None:
    stream = scenario_messages("three-radar", duration_s=90.0, targets=40)
    local, out_local = run(stream, process=False)
    remote, out_remote = run(stream, process=True)
    assert remote == local
    assert local["pairs"] and any(ps["pairs"] for ps in local["pairs"]) and local["biases"]
    assert local["system"]["system_tracks"]
    # the same messages are published in the same order: a table is published with what the
    # correlation answered for it, so a subscriber never holds outputs that disagree
    assert [(o.key, o.payload) for o in out_remote] == [(o.key, o.payload) for o in out_local]
    monitor = OutputMonitor({rid: 4.0 for rid in "ABC"})
    for o in out_remote:
        monitor.feed(o.key, json.loads(o.payload))
    assert monitor.report().dangling.references == 0 and monitor.outputs > 100


def test_a_failing_update_is_reported_and_the_process_goes_on() -> None:
    """A message the stage cannot take (here: a site move of an unknown kind of object) costs
    that message only; the next batches are correlated as before."""
    stream = scenario_messages("two-radar", duration_s=40.0)
    engine = Engine(EngineConfig(), correlation_process=True)
    try:
        half = len(stream) // 2
        for key, payload in stream[:half]:
            engine.ingest(key, payload)
        engine.correlation._send("moved", "not a site")  # type: ignore[union-attr]
        out = []
        for key, payload in stream[half:]:
            out.extend(engine.ingest(key, payload))
        out.extend(engine.flush())
        errors = [json.loads(o.payload) for o in out if o.key == "fusion/errors"]
        assert [e["reason"] for e in errors] == ["internal"]
        assert "correlation failed" in errors[0]["detail"]
        assert engine.snapshot().status_core()["pairs_confirmed"] > 0
    finally:
        engine.close()


def test_a_killed_correlation_process_is_restarted_and_reported() -> None:
    """The child dies (killed from outside): the engine does not wait for it, says so once as an
    ``internal`` rejection, and correlates again with a fresh process."""
    stream = scenario_messages("two-radar", duration_s=60.0)
    engine = Engine(EngineConfig(), correlation_process=True)
    try:
        third = len(stream) // 3
        for key, payload in stream[:third]:
            engine.ingest(key, payload)
        remote = engine.correlation
        assert isinstance(remote, ChildProcessRunner)

        def system_ids() -> set[str]:
            return {t["system_track_id"] for t in engine.snapshot().system_tracks("all")["system_tracks"]}

        before = system_ids()
        remote._process.kill()
        remote._process.join(10)
        out = []
        for key, payload in stream[third:]:
            out.extend(engine.ingest(key, payload))
        out.extend(engine.flush())
        errors = [json.loads(o.payload) for o in out if o.key == "fusion/errors"]
        assert remote.restarts == 1
        assert [e["reason"] for e in errors] == ["internal"] and "died" in errors[0]["detail"]
        # the fresh process numbers its system tracks on: no number of before comes again
        after = system_ids()
        assert before and after and not before & after
        assert (
            engine.snapshot().status_core()["pairs_tentative"]
            + engine.snapshot().status_core()["pairs_confirmed"]
            > 0
        )
    finally:
        engine.close()


def test_a_ctrl_c_to_the_process_group_leaves_the_child_to_its_parent() -> None:
    """A terminal's Ctrl-C reaches every process of the group: the child goes on answering (it
    stopped with exit code 1 before, and the service restarted it in the middle of its stop)."""
    import os
    import signal
    import time

    stream = scenario_messages("two-radar", duration_s=30.0)
    engine = Engine(EngineConfig(), correlation_process=True)
    try:
        remote = engine.correlation
        assert isinstance(remote, ChildProcessRunner)
        for key, payload in stream[: len(stream) // 2]:
            engine.ingest(key, payload)
        engine.flush()  # the child has started and answered
        os.kill(remote._process.pid, signal.SIGINT)
        time.sleep(0.5)
        for key, payload in stream[len(stream) // 2 :]:
            engine.ingest(key, payload)
        errors = [o for o in engine.flush() if o.key == "fusion/errors"]
        assert remote._process.is_alive() and remote.restarts == 0 and errors == []
    finally:
        engine.close()
