"""The correlation stage in a child process gives the in-process results (correlation_process.py)."""

from __future__ import annotations

import json
import time

import pytest

from service.engine import Engine, EngineConfig
from service.pipeline.correlation_process import ChildProcessRunner
from service.pipeline.correlation_stage import timings_dict
from tests.scenario_helpers import run_engine, scenario_messages
from topofusion_lab.evaluation.promptness import OutputMonitor


@pytest.mark.slow
def test_same_tracks_pairs_and_biases_as_in_process() -> None:
    stream = scenario_messages("three-radar", duration_s=90.0, targets=40)
    local, out_local = run_engine(stream, process=False)
    remote, out_remote = run_engine(stream, process=True)
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


def test_a_site_move_gives_the_same_system_tracks_as_in_process() -> None:
    """The system tracks are drawn in the engine's process from the tables it sent the child:
    after a radar's move (a new site, the same tables: its next batches come 20 s later) they
    are those of the in-process stage."""
    stream = scenario_messages("three-radar", duration_s=60.0, targets=30)
    site_c = json.loads(next(p for k, p in stream if k == "fusion/radar/C/site"))
    moved = {**site_c, "latitude_deg": site_c["latitude_deg"] + 0.01}  # 1.1 km
    half = len(stream) // 2
    rest = stream[half:]
    move_s = json.loads(rest[0][1])["time_s"]
    rest = [(k, p) for k, p in rest if k != "fusion/radar/C/plots" or json.loads(p)["time_s"] > move_s + 20]
    stream = [*stream[:half], ("fusion/radar/C/site", json.dumps(moved).encode()), *rest]
    local, out_local = run_engine(stream, process=False)
    remote, out_remote = run_engine(stream, process=True)
    assert remote["system"] == local["system"] and local["system"]["system_tracks"]
    assert [(o.key, o.payload) for o in out_remote] == [(o.key, o.payload) for o in out_local]


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
    ``internal`` rejection, and correlates again with a fresh process.  The system tracks are
    drawn in the engine's process, so their numbers go on: a number of before still shown
    follows the aircraft it followed."""
    stream = scenario_messages("two-radar", duration_s=60.0)
    engine = Engine(EngineConfig(), correlation_process=True)
    try:
        third = len(stream) // 3
        for key, payload in stream[:third]:
            engine.ingest(key, payload)
        remote = engine.correlation
        assert isinstance(remote, ChildProcessRunner)

        def numbers() -> dict[tuple[str, str], str]:
            """The system track number of each member radar track."""
            tracks = engine.snapshot().system_tracks("all")["system_tracks"]
            return {
                (m["radar_id"], m["track_id"]): t["system_track_id"] for t in tracks for m in t["members"]
            }

        # every message answered before the kill: what the child loses is then its state alone,
        # not a varying number of messages in flight (up to the bound), so the test is the same
        # on a slow machine and a fast one
        deadline = time.monotonic() + 60
        while engine.answers_pending and time.monotonic() < deadline:
            engine.poll()
            time.sleep(0.01)
        assert not engine.answers_pending
        before = numbers()
        remote._process.kill()
        remote._process.join(10)
        out = []
        for key, payload in stream[third:]:
            out.extend(engine.ingest(key, payload))
        out.extend(engine.flush())
        errors = [json.loads(o.payload) for o in out if o.key == "fusion/errors"]
        assert remote.restarts == 1
        assert [e["reason"] for e in errors] == ["internal"] and "died" in errors[0]["detail"]
        after = numbers()
        # a number of before that is still shown holds a member it held before (it was not
        # given out again to another aircraft), and most of before's numbers are still shown
        members_of: dict[str, dict[str, set[tuple[str, str]]]] = {"before": {}, "after": {}}
        for when, got in (("before", before), ("after", after)):
            for member, number in got.items():
                members_of[when].setdefault(number, set()).add(member)
        shown = members_of["before"].keys() & members_of["after"].keys()
        assert len(shown) >= len(members_of["before"]) // 2
        assert all(members_of["before"][n] & members_of["after"][n] for n in shown)
        # numbers stay unique: no two system tracks share one
        tracks = engine.snapshot().system_tracks("all")["system_tracks"]
        assert len({t["system_track_id"] for t in tracks}) == len(tracks)
        assert engine.snapshot().status_core()["pairs_confirmed"] > 0
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


def test_status_timings_follow_every_update_as_taken_afresh() -> None:
    # /status's correlation timings are taken again only after a pair's full update: after
    # every message they equal those computed afresh from the stage's own figures
    stream = scenario_messages("three-radar", duration_s=60.0, targets=20)
    engine = Engine(EngineConfig(), correlation_process=False)
    try:
        stage = engine.correlation.stage  # type: ignore[attr-defined]
        seen = set()
        for key, payload in stream:
            engine.ingest(key, payload, receive_time_s=0.0)
            shown = {k: v for k, v in engine.snapshot().correlation.items() if k != "pending"}
            fresh = timings_dict(
                stage.updates, stage.last_ms, stage.timings_ms, stage.duration_counts, stage.duration_sum_s
            )
            assert shown == fresh
            seen.add(shown["updates"])
        assert len(seen) > 10  # (many updates, each shown)
    finally:
        engine.close()
