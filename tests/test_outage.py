"""A whole-feed outage that ended, and its lone-source look-alike (service/pipeline/sequencer.py).

The stream of three radars is cut after 60 s of data and comes back ``GAP_S`` later, every radar
at once, as after a link or bridge outage longer than ``max_clock_skew_s``.  The service must
take the data after the gap (the quorum vote), let the tracks of before the gap expire, and pair
again; a single radar's jump of the same size is still refused.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from typing import Any

import pytest
import zenoh

from service.engine import Engine, EngineConfig
from service.pipeline.errors import RejectionError
from service.pipeline.feed import FeedParams, FeedWatch
from service.pipeline.sequencer import RADAR, Sequencer, SequencerParams, SourceClock
from tests.scenario_helpers import scenario_messages
from tests.support import put_json, run_engine, running_service, wait_for, wait_subscribed

Stream = list[tuple[str, bytes]]

GAP_S = 900.0
CUT_S = 60.0


def shifted(payload: bytes, by: float) -> bytes:
    body = json.loads(payload)
    body["time_s"] += by
    body["plots"]["time_s"] = [t + by for t in body["plots"]["time_s"]]
    return json.dumps(body).encode()


def with_gap(stream: Stream, radars: set[str] | None = None) -> tuple[Stream, int]:
    """The stream with ``GAP_S`` of silence after ``CUT_S`` (for ``radars``, default all);
    and how many batches come after the gap."""
    t0 = min(json.loads(p)["time_s"] for k, p in stream if k.endswith("/plots"))
    out, later = [], 0
    for key, payload in stream:
        late = key.endswith("/plots") and json.loads(payload)["time_s"] > t0 + CUT_S
        if late and (radars is None or key.split("/")[2] in radars):
            payload = shifted(payload, GAP_S)
            later += 1
        out.append((key, payload))
    if radars is not None:  # one radar jumps: the stream stays in arrival (data-time) order
        out.sort(key=lambda m: json.loads(m[1]).get("time_s", -1e18))
    return out, later


def errors(out: list[Any]) -> list[dict[str, Any]]:
    return [json.loads(o.payload) for o in out if o.key == "fusion/errors"]


@pytest.fixture(scope="module")
def stream() -> Stream:
    return scenario_messages("three-radar", duration_s=200.0)


def confirmed_pairs(engine: Any) -> set[tuple[str, str, Any, Any]]:
    """Confirmed pairs as (radar, radar, truth, truth): the simulator's labels, for scoring only."""
    snap = engine.snapshot()
    truth = {
        (b["radar_id"], t["track_id"]): t["truth_id"] for b in snap.track_batches("all") for t in b["tracks"]
    }
    return {
        (ps["radar_a"], ps["radar_b"], truth[ps["radar_a"], p["track_a"]], truth[ps["radar_b"], p["track_b"]])
        for ps in snap.pair_sets(status="confirmed")
        for p in ps["pairs"]
    }


@pytest.mark.slow
def test_whole_feed_outage_is_taken_counted_and_the_picture_renews(stream: Stream) -> None:
    gapped, later = with_gap(stream)
    engine, out = run_engine(gapped)
    rejected = [e for e in errors(out) if e["reason"] == "out_of_range"]
    # at most the first batch of the radars that came back before the quorum did
    assert len(rejected) <= 2 and len(rejected) <= 0.05 * later
    assert engine.sequencer.outages == 1
    assert abs(engine.sequencer.last_outage_s - GAP_S) < 30.0
    status = engine.snapshot().status_core()
    assert all(not r["expired"] for r in status["radars"])
    # the tracks of before the gap expired: every track now held was updated after it
    t_back = min(json.loads(p)["time_s"] for k, p in gapped if k.endswith("/plots")) + CUT_S + GAP_S
    for batch in engine.snapshot().track_batches("all"):
        assert all(t["time_s"] > t_back for t in batch["tracks"])
    # and the picture after the gap is the one a service that never refused it would hold
    lenient = EngineConfig(sequencer=SequencerParams(max_clock_skew_s=1e6))
    clean, _ = run_engine(gapped, lenient)
    pairs, clean_pairs = confirmed_pairs(engine), confirmed_pairs(clean)
    assert len(clean_pairs) > 10
    assert len(pairs & clean_pairs) >= 0.9 * len(clean_pairs)
    assert all(a == b for _, _, a, b in pairs)  # and none is false


def expired_on_the_wall_clock(stream: Stream, monkeypatch: pytest.MonkeyPatch) -> tuple[Engine, Stream]:
    """An engine fed the stream with a ``GAP_S`` outage up to the gap, then silent on the wall
    clock until every source expired; and the stream after the gap."""
    now = [1000.0]
    monkeypatch.setattr("service.pipeline.feed.time.monotonic", lambda: now[0])
    gapped, _ = with_gap(stream)
    t0 = min(json.loads(p)["time_s"] for k, p in gapped if k.endswith("/plots"))
    cut = next(
        i for i, (k, p) in enumerate(gapped) if k.endswith("/plots") and json.loads(p)["time_s"] > t0 + CUT_S
    )
    engine = Engine(EngineConfig(feed=FeedParams(source_expiry_wall_s=2.5)))
    for key, payload in gapped[:cut]:
        engine.ingest(key, payload)
    now[0] += 10.0  # silence on the wall clock: every source expires
    engine.expire_silent(now[0])
    return engine, gapped[cut:]


def test_an_outage_every_source_expired_in_is_counted_when_the_feed_returns(
    stream: Stream, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A live outage longer than ``source_expiry_wall_s``: every source expires on the wall
    clock first, so no quorum is left to vote on the return; it is an outage all the same, and
    ``/status`` ``feed`` counts it (it said 0 after a real 15-minute outage)."""
    engine, rest = expired_on_the_wall_clock(stream, monkeypatch)
    assert all(r["expired"] for r in engine.snapshot().status_core()["radars"])
    out = [o for key, payload in rest for o in engine.ingest(key, payload)]
    assert errors(out) == []
    assert engine.sequencer.outages == 1 and abs(engine.sequencer.last_outage_s - GAP_S) < 30.0


def test_one_radar_jumping_alone_is_still_refused(stream: Stream) -> None:
    gapped, _ = with_gap(stream, radars={"A"})
    engine, out = run_engine(gapped)
    refused = [e for e in errors(out) if e["radar_id"] == "A"]
    # every batch of A after its jump is refused until the others catch up with it in data time
    assert refused and all(e["reason"] == "out_of_range" for e in refused)
    assert engine.sequencer.outages == 0
    assert not [e for e in errors(out) if e["radar_id"] != "A"]


@pytest.mark.slow
def test_over_zenoh_the_outage_is_taken_and_a_silent_feed_is_reported_stale(
    router: str, client: zenoh.Session, caplog: pytest.LogCaptureFixture
) -> None:
    """Through the public interface: the whole feed comes back 900 s later (taken, counted in
    ``/status`` ``feed``), then falls silent: ``/readyz`` turns 503 with the reason once the data
    clock has stood still for ``stale_s``, and the radars expire on the wall clock; a new batch
    makes the service ready again.  A lone refused input is logged with its source and reason."""
    stream = scenario_messages("three-radar", duration_s=90.0)
    gapped, later = with_gap(stream)
    assert later > 40
    feed = FeedParams(stale_s=1.5, source_expiry_wall_s=2.5)
    caplog.set_level(logging.WARNING)
    with running_service(router, EngineConfig(feed=feed)) as svc:
        wait_subscribed(client, "fusion/radar/A/plots")
        for key, payload in gapped:
            put_json(client, key, payload)
        n = sum(k.endswith("/plots") for k, _ in gapped)

        def taken() -> int:
            st = svc.http.get("/status").json()
            return sum(r["batches"] + r["rejected"] for r in st["radars"]) == n and st

        status = wait_for(taken, timeout=60)
        assert sum(r["batches"] for r in status["radars"]) >= n - 2  # ≥ 95 % of `later`, and more
        assert status["feed"]["outages"] == 1 and status["feed"]["stale"] is False
        assert status["feed"]["behind_s"] >= 0.0
        assert svc.http.get("/readyz").status_code == 200
        # silence: stale, then every radar expires on the wall clock
        ready = wait_for(lambda: (r := svc.http.get("/readyz")).status_code == 503 and r.json(), timeout=10)
        assert "outputs stale" in ready["reason"] and "data clock has not moved" in ready["reason"]
        assert svc.http.get("/status").json()["feed"]["stale"] is True

        def all_expired() -> Any:
            st = svc.http.get("/status").json()
            return all(r["expired"] for r in st["radars"]) and st

        status = wait_for(all_expired, timeout=10)
        assert status["feed"]["expired_by_wall_clock"] == 3
        # and their tracks left the picture (published once the correlation has answered)
        wait_for(
            lambda: all(svc.http.get(f"/radars/{r}/tracks?status=all").json()["tracks"] == [] for r in "ABC")
        )
        assert svc.http.get("/pairs").json()[0]["pairs"] == []
        # a batch of the next scan: live again
        last = json.loads(next(p for k, p in reversed(gapped) if k == "fusion/radar/A/plots"))
        put_json(
            client,
            "fusion/radar/A/plots",
            shifted(json.dumps({**last, "seq": last["seq"] + 1}).encode(), 5.0),
        )
        wait_for(lambda: svc.http.get("/readyz").status_code == 200, timeout=10)
    lines = [r.getMessage() for r in caplog.records]
    assert any("outage" in m and "900 s" in m for m in lines)
    assert any(m.startswith("rejected out_of_range from A") and "ahead" in m for m in lines)


def test_the_feed_says_how_far_the_outputs_are_behind_the_newest_batch() -> None:
    """A source flooding the queue, or lagging, holds the release back up to ``max_lag_s``:
    ``/status`` ``feed.behind_s`` is the data time between the newest batch taken and the
    outputs (``outputs_time_s``); null before any output."""
    seq = Sequencer(SequencerParams())
    watch = FeedWatch(FeedParams())
    assert watch.status(0.0, seq, None)["behind_s"] is None
    for n, t in enumerate((100.0, 130.5)):
        seq.accept(seq.check("A", RADAR, n + 1, t), None)
    assert watch.status(0.0, seq, 100.0)["behind_s"] == 30.5
    assert watch.status(0.0, seq, 130.5)["behind_s"] == 0.0


def test_how_far_behind_counts_from_the_clock_the_release_follows() -> None:
    """A radar whose clock runs two minutes ahead of the others alone (within the skew, so its
    batches are taken) does not lead the release (the pace, :meth:`Sequencer._pace`), and the
    outputs are not behind it: ``behind_s`` counts from the honest clocks (it said 120 s, and
    up to 600 s with a clock running away, while the outputs were on time)."""
    seq = Sequencer(SequencerParams())
    watch = FeedWatch(FeedParams())
    n = 0
    for t in (100.0, 110.0, 120.0, 130.0):
        for rid in ("A", "B", "C"):
            n += 1
            seq.accept(seq.check(rid, RADAR, n, t), None)
    for k, t in enumerate((250.0, 254.0)):  # C two minutes ahead from now on (a step held, then taken)
        seq.accept(seq.check("C", RADAR, n + 1 + k, t), None)
    n += 2
    for t in (140.0, 150.0):
        for rid in ("A", "B"):
            n += 1
            seq.accept(seq.check(rid, RADAR, n, t), None)
    assert seq.newest_s == 254.0 and seq.pace_s() == 150.0
    assert watch.status(0.0, seq, 150.0)["behind_s"] == 0.0
    assert watch.status(0.0, seq, 140.0)["behind_s"] == 10.0


def test_a_source_with_input_queued_is_not_silent_on_the_wall_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker that stalls longer than ``source_expiry_wall_s`` with a source's batches still
    queued is behind, not facing a silent feed: only the source with nothing queued expires."""
    now = [100.0]
    monkeypatch.setattr("service.pipeline.feed.time.monotonic", lambda: now[0])
    watch = FeedWatch(FeedParams(source_expiry_wall_s=2.5))
    watch.taken("A", 10.0)
    watch.taken("B", 10.0)
    now[0] += 3.0
    assert watch.silent(now[0], waiting={"A"}) == ["B"]
    assert watch.silent(now[0]) == ["A"]  # the queue ran dry with nothing of A's: silent now
    assert watch.expired_by_wall == 2 and watch.silent(now[0] + 10) == []  # each once


# -- a lone step ahead: one batch stamped ahead within max_clock_skew_s ---------------------------
def _outputs(out: list[Any]) -> list[tuple[str, Any]]:
    """What a run published, but its error reports (a rejection's detail says why)."""
    return [(o.key, o.payload) for o in out if o.key != "fusion/errors"]


def _pair_counts(engine: Any) -> dict[tuple[str, str], int]:
    return {
        (p["radar_a"], p["radar_b"]): len(p["pairs"]) for p in engine.snapshot().pair_sets(status="confirmed")
    }


@pytest.mark.parametrize("ahead_s", [30.0, 100.0, 500.0])
def test_one_batch_stamped_ahead_is_held_then_refused_and_changes_nothing(ahead_s: float) -> None:
    """One batch of radar B stamped ``ahead_s`` into the future (a corrupted time stamp, within
    ``max_clock_skew_s``), the next ones on time: taken at once, it moved B's clock ahead and its
    honest batches found their tracks ahead of them (B's pairs went from 20 to 0).  Held, the
    next batch refutes it: it is rejected, and every output is the one of the stream without it."""
    stream = scenario_messages("three-radar", duration_s=90.0)
    b_batches = [i for i, (k, _) in enumerate(stream) if k == "fusion/radar/B/plots"]
    i = b_batches[len(b_batches) // 2]
    glitched = [*stream[:i], (stream[i][0], shifted(stream[i][1], ahead_s)), *stream[i + 1 :]]
    without = [*stream[:i], *stream[i + 1 :]]
    engine, out = run_engine(glitched)
    clean, clean_out = run_engine(without)
    refused = errors(out)
    assert [(e["radar_id"], e["reason"]) for e in refused] == [("B", "out_of_range")]
    assert "max_step_s" in refused[0]["detail"] and "came back" in refused[0]["detail"]
    assert _outputs(out) == _outputs(clean_out)
    assert _pair_counts(engine) == _pair_counts(clean)
    assert all(n >= 10 for n in _pair_counts(engine).values()) and len(_pair_counts(engine)) == 3
    radar_b = next(r for r in engine.snapshot().status_core()["radars"] if r["radar_id"] == "B")
    assert radar_b["rejected"] == 1
    assert radar_b["plots"] == next(
        r["plots"] for r in clean.snapshot().status_core()["radars"] if r["radar_id"] == "B"
    )


@pytest.mark.parametrize("refuted", [True, False])
def test_a_refused_step_is_reported_at_its_own_receipt(refuted: bool) -> None:
    """A Rejection's ``time_s`` is when the service received the message (contract §2.8;
    offline, the recorded time): for a held step refused later (refuted by the next batch, or
    unconfirmed when the input ends), its own receipt, never the wall clock of the process (a
    replay must give the same errors whenever it runs)."""
    stream = scenario_messages("three-radar", duration_s=60.0)
    b_batches = [i for i, (k, _) in enumerate(stream) if k == "fusion/radar/B/plots"]
    i = b_batches[len(b_batches) // 2]
    glitched = [*stream[:i], (stream[i][0], shifted(stream[i][1], 100.0)), *stream[i + 1 :]]
    if not refuted:  # the input ends on the held batch
        glitched = glitched[: i + 1]
    engine = Engine(EngineConfig())
    received = [5_000.0 + 0.25 * n for n in range(len(glitched))]  # a recording's receipt times
    out = [o for n, (key, payload) in enumerate(glitched) for o in engine.ingest(key, payload, received[n])]
    reported = errors([*out, *engine.flush()])
    assert [(e["radar_id"], e["reason"]) for e in reported] == [("B", "out_of_range")]
    assert reported[0]["time_s"] == received[i]


def test_a_step_ahead_confirmed_by_the_next_batch_is_taken() -> None:
    """Every radar silent for 300 s (an outage shorter than ``max_clock_skew_s``): the first
    radars back are ahead of the others' clock and their first batch is held, then confirmed
    by the next.  Nothing is refused, and every output is the one the service gave before it
    held steps (``max_step_s`` beyond the skew: never), some a batch later."""
    stream = scenario_messages("three-radar", duration_s=150.0)
    t0 = min(json.loads(p)["time_s"] for k, p in stream if k.endswith("/plots"))
    gapped = [
        (k, shifted(p, 300.0) if k.endswith("/plots") and json.loads(p)["time_s"] > t0 + CUT_S else p)
        for k, p in stream
    ]
    engine, out = run_engine(gapped)
    never = EngineConfig(sequencer=SequencerParams(max_step_s=1e6))
    before, before_out = run_engine(gapped, never)
    assert errors(out) == [] and errors(before_out) == []
    # the same outputs, every one of them; those of a held radar come a batch later
    assert sorted(_outputs(out)) == sorted(_outputs(before_out))
    assert _pair_counts(engine) == _pair_counts(before) and len(_pair_counts(engine)) == 3


def test_a_held_step_confirmed_by_a_batch_before_it_is_not_a_step_back() -> None:
    """A radar silent 44 s comes back with a batch 15 s ahead of the others (held, 59 s ahead of
    its own clock), then one at the others' clock: past the middle, so it confirms the held
    batch; it is measured for a step back against the clock taken before, not against the held
    time (else it, and every honest batch after it, would be refused until the data time
    reached the held one)."""
    seq = Sequencer(SequencerParams())
    for t in (0.0, 1.0):
        for n, sid in enumerate(("A", "B", "C")):
            seq.accept(seq.check(sid, RADAR, int(t) + 1, 100.0 + t + n / 10), None)
    for t in range(2, 46):
        seq.accept(seq.check("A", RADAR, t + 1, 100.0 + t), None)
        seq.accept(seq.check("C", RADAR, t + 1, 100.0 + t), None)
    held = seq.check("B", RADAR, 3, 160.0)
    assert held.step_from_s == 101.1
    seq.accept(held, None)
    nxt = seq.check("B", RADAR, 4, 146.0)  # not refused
    assert nxt.resolves == 1
    seq.accept(nxt, None)
    assert seq.sources["B"].last_time_s == 160.0 and seq.sources["B"].held is None


def test_a_step_ahead_that_ends_the_input_is_refused() -> None:
    """The input ends on a batch held as a step ahead: no next batch confirms it, so the flush
    rejects it rather than take a clock it may not have."""
    stream = scenario_messages("three-radar", duration_s=40.0)
    last_b = max(i for i, (k, _) in enumerate(stream) if k == "fusion/radar/B/plots")
    glitched = [
        *stream[:last_b],
        (stream[last_b][0], shifted(stream[last_b][1], 100.0)),
        *stream[last_b + 1 :],
    ]
    engine, out = run_engine(glitched)
    refused = errors(out)
    assert [(e["radar_id"], e["reason"]) for e in refused] == [("B", "out_of_range")]
    assert "no next batch came" in refused[0]["detail"]
    status = {r["radar_id"]: r for r in engine.snapshot().status_core()["radars"]}
    assert status["B"]["last_time_s"] < json.loads(glitched[last_b][1])["time_s"]


# -- a first clock no other source can check -------------------------------------------------------
def _first_batch_shifted(stream: Stream, radar: str, by: float) -> tuple[Stream, Stream, int]:
    """The stream with ``radar``'s first batch stamped ``by`` later, the stream without that
    batch, and its index."""
    i = next(n for n, (k, _) in enumerate(stream) if k == f"fusion/radar/{radar}/plots")
    return (
        [*stream[:i], (stream[i][0], shifted(stream[i][1], by)), *stream[i + 1 :]],
        [*stream[:i], *stream[i + 1 :]],
        i,
    )


@pytest.mark.parametrize("radar", ["A", "B"])
def test_a_first_clock_an_hour_ahead_is_withdrawn_when_the_others_refute_it(radar: str) -> None:
    """A fresh service whose first batch of a radar is stamped an hour ahead (a wrong date in
    the first message, no other clock to check it against): taken at once it set the network's
    clock, and the radar's honest batches after it were refused as steps back for an hour.  Its
    clock is lone until data settles it: the other radars' agreeing clocks refute it, it is
    withdrawn (rejected), and every output is the one of the stream without it."""
    stream = scenario_messages("three-radar", duration_s=90.0)
    glitched, without, _ = _first_batch_shifted(stream, radar, 3600.0)
    engine, out = run_engine(glitched)
    clean, clean_out = run_engine(without)
    refused = errors(out)
    assert [(e["radar_id"], e["reason"]) for e in refused] == [(radar, "out_of_range")]
    assert "no other source had a live data clock" in refused[0]["detail"]
    assert _outputs(out) == _outputs(clean_out)
    assert _pair_counts(engine) == _pair_counts(clean) and all(n >= 10 for n in _pair_counts(engine).values())


def test_a_lone_radars_first_clock_is_withdrawn_by_its_own_next_batch() -> None:
    """One radar alone: its first batch an hour ahead, its next on time.  The next batch refutes
    the first (more than ``max_step_s`` behind it), which is withdrawn; the radar tracks from
    its honest batches as if the bad one never came."""
    stream = [
        (k, p)
        for k, p in scenario_messages("three-radar", duration_s=90.0)
        if not k.startswith("fusion/radar/") or "/A/" in k
    ]
    glitched, without, _ = _first_batch_shifted(stream, "A", 3600.0)
    engine, out = run_engine(glitched)
    _, clean_out = run_engine(without)
    refused = errors(out)
    assert [(e["radar_id"], e["reason"]) for e in refused] == [("A", "out_of_range")]
    assert "next batch came back" in refused[0]["detail"]
    assert _outputs(out) == _outputs(clean_out)
    radar_a = engine.snapshot().status_core()["radars"][0]
    assert radar_a["tracks_confirmed"] > 0 and radar_a["rejected"] == 1
    assert radar_a["last_time_s"] < json.loads(glitched[-1][1])["time_s"] + 1


def test_a_first_clock_after_every_source_expired_is_checked_too(
    stream: Stream, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A live outage long enough for every source to expire on the wall clock, and the first
    batch back stamped an hour beyond the others' return: withdrawn when they come, and the
    outage is counted once, at its true length."""
    engine, rest = expired_on_the_wall_clock(stream, monkeypatch)
    rogue = (rest[0][0], shifted(rest[0][1], 3600.0))
    out = [o for key, payload in [rogue, *rest[1:]] for o in engine.ingest(key, payload)]
    refused = errors(out)
    assert [(e["radar_id"], e["reason"]) for e in refused] == [(rogue[0].split("/")[2], "out_of_range")]
    assert engine.sequencer.outages == 1 and abs(engine.sequencer.last_outage_s - GAP_S) < 30.0
    assert all(
        not r["expired"] and r["tracks_confirmed"] > 0 for r in engine.snapshot().status_core()["radars"]
    )


def test_the_first_batch_waits_for_the_next_whichever_radar_comes_first() -> None:
    """An honest start: the first batch's clock is lone until the next batch confirms it, so
    nothing is released before two batches agree, and the outputs are the same whichever
    radar's first batch arrives first."""
    stream = scenario_messages("three-radar", duration_s=60.0)
    plots = [n for n, (k, _) in enumerate(stream) if k.endswith("/plots")]
    a, b = plots[0], next(n for n in plots if stream[n][0] != stream[plots[0]][0])
    swapped = list(stream)
    swapped[a], swapped[b] = swapped[b], swapped[a]
    _, out = run_engine(stream)
    _, swapped_out = run_engine(swapped)
    assert errors(out) == [] and errors(swapped_out) == []
    assert _outputs(out) == _outputs(swapped_out)
    seq = Sequencer(SequencerParams())
    seq.announce("A", RADAR)
    seq.accept(seq.check("A", RADAR, 1, 100.0), "a1")
    assert list(seq.release()) == [] and seq.newest_s == -float("inf")
    seq.accept(seq.check("B", RADAR, 1, 100.5), "b1")
    assert [r.item for r in seq.release()] == ["a1"] and seq.newest_s == 100.5
    one = Sequencer(SequencerParams())  # a replay of one batch still gives it at its end
    one.accept(one.check("A", RADAR, 1, 100.0), "only")
    assert [r.item for r in one.flush()] == ["only"]


def test_an_outage_ended_by_one_radar_alone_is_counted_once(
    stream: Stream, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every source expired on the wall clock, and one radar comes back alone: its first batch
    back is lone, its second confirms it; the outage is counted once (the second batch, judged
    against the clock of before the outage too, was counted again)."""
    engine, rest = expired_on_the_wall_clock(stream, monkeypatch)
    out = [o for key, payload in rest if "/A/" in key for o in engine.ingest(key, payload)]
    assert errors(out) == []
    assert engine.sequencer.outages == 1 and abs(engine.sequencer.last_outage_s - GAP_S) < 30.0


def test_a_second_radars_first_batch_a_step_ahead_of_a_lone_clock_is_refused_alone() -> None:
    """A fresh service: radar A's first batch is lone when radar B's first comes stamped 120 s
    ahead (a corrupted stamp).  The two do not agree, so B's is lone too; B's next batch refutes
    it.  Only that batch is rejected (taken, it had moved B's clock ahead and every honest batch
    of B after it was refused as a step back: 219 rejections in 120 s)."""
    stream = scenario_messages("three-radar", duration_s=90.0)
    first = next(k for k, _ in stream if k.endswith("/plots"))
    other = next(k.split("/")[2] for k, _ in stream if k.endswith("/plots") and k != first)
    glitched, without, _ = _first_batch_shifted(stream, other, 120.0)
    _, out = run_engine(glitched)
    _, clean_out = run_engine(without)
    assert [(e["radar_id"], e["reason"]) for e in errors(out)] == [(other, "out_of_range")]
    assert _outputs(out) == _outputs(clean_out)


def test_a_publisher_restarting_after_a_refuted_first_batch_is_taken() -> None:
    """A's first batch is seq 200 stamped an hour ahead; its publisher then restarts at seq 1 on
    time.  The restart refutes the lone batch and is judged as if it never came (not as a
    duplicate of seq 200): every batch after it is taken."""
    seq = Sequencer(SequencerParams())
    seq.accept(seq.check("A", RADAR, 200, 4600.0), "rogue")
    _, refused = seq.accept(seq.check("A", RADAR, 1, 1000.0), "a1")
    assert [(sid, rej.reason) for sid, rej, _ in refused] == [("A", "out_of_range")]
    for n in (2, 3):
        seq.accept(seq.check("A", RADAR, n, 998.0 + 2 * n), f"a{n}")
    assert [r.item for r in seq.release()] == ["a1", "a2", "a3"]
    a = seq.sources["A"]
    assert (a.batches, a.last_seq, a.lost_batches, a.restarts) == (3, 3, 0, 0)


def test_a_radar_agreeing_with_its_own_rogue_clock_is_not_confirmed_by_itself(
    stream: Stream, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every source expired on the wall clock; radar A's first five batches back come stamped an
    hour ahead, before any other radar's.  Agreeing with itself, A had confirmed its clock: its
    batches were released, the picture's clock went an hour ahead and A's honest batches were
    refused as steps back (114 in an outside run).  While other sources are known, A's own few
    batches prove nothing: the others' return refutes all five, each is rejected, and A tracks
    on."""
    engine, rest = expired_on_the_wall_clock(stream, monkeypatch)
    a_batches = [n for n, (k, _) in enumerate(rest) if k == "fusion/radar/A/plots"][:5]
    rogue = [(rest[n][0], shifted(rest[n][1], 3600.0)) for n in a_batches]
    honest = [m for n, m in enumerate(rest) if n not in set(a_batches)]
    out = [o for key, payload in [*rogue, *honest] for o in engine.ingest(key, payload)]
    assert [(e["radar_id"], e["reason"]) for e in errors(out)] == [("A", "out_of_range")] * 5
    status = {r["radar_id"]: r for r in engine.snapshot().status_core()["radars"]}
    assert status["A"]["tracks_confirmed"] > 0 and status["A"]["rejected"] == 5
    assert engine.snapshot().system_tracks()["time_s"] < json.loads(rest[-1][1])["time_s"] + 1


@pytest.mark.parametrize("lead", [2, 5])
def test_a_radar_whose_clock_is_an_hour_off_from_its_first_batch_is_refused_whole(lead: int) -> None:
    """A fresh service knowing three radars' sites; radar A's clock is an hour ahead (a wrong
    time zone) from its first batch on, and its first ``lead`` batches come before any other.
    Agreeing with itself, A had set the network's clock an hour ahead: the other radars expired
    against it and the picture emptied (no pairs, two system-track pictures in 200 s).  Now its
    batches stay lone until the others' first batches refute them; every batch of A is
    rejected, and every output is the one of the stream without A's batches."""
    stream = scenario_messages("three-radar", duration_s=120.0)
    sites = [m for m in stream if m[0].endswith("/site")]
    a = [(k, shifted(p, 3600.0)) for k, p in stream if k == "fusion/radar/A/plots"]
    others = [m for m in stream if m[0].endswith("/plots") and m[0] != "fusion/radar/A/plots"]
    rest = sorted([*a[lead:], *others], key=lambda m: json.loads(m[1])["time_s"] % 3600.0)
    engine, out = run_engine([*sites, *a[:lead], *rest])
    clean, clean_out = run_engine([*sites, *others])
    assert [(e["radar_id"], e["reason"]) for e in errors(out)] == [("A", "out_of_range")] * len(a)
    assert _outputs(out) == _outputs(clean_out)
    assert _pair_counts(engine) == _pair_counts(clean) and _pair_counts(engine)[("B", "C")] >= 10


def _known(*radars: str, params: SequencerParams | None = None) -> Sequencer:
    """A sequencer that knows the sites of ``radars``."""
    seq = Sequencer(params or SequencerParams())
    for rid in radars:
        seq.announce(rid, RADAR)
    seq.sites_known = len(radars)
    return seq


def test_a_lone_run_confirms_itself_after_max_lag_s_of_continuous_data() -> None:
    """A radar alone while another is known but silent: its batches stay lone (released
    nothing) until they have gone on for ``max_lag_s`` of data time, then they are confirmed
    and released as the silent radar's lag bound allows.  A jump ahead inside the run is held
    for the next batch (refuted here), and does not count as run time."""
    lag = SequencerParams().max_lag_s
    seq = _known("A", "B")
    times = [100.0 + 4.0 * n for n in range(int(lag // 4.0) + 2)]
    refused = []
    for n, t in enumerate(times[:-1]):
        refused += seq.accept(seq.check("A", RADAR, 2 * n + 1, t), f"a{n}")[1]
        if n == 1:  # a corrupted stamp inside the run: held, refuted by the next batch
            seq.accept(seq.check("A", RADAR, 2 * n + 2, t + lag + 1.0), "glitch")
            assert seq.sources["A"].held is not None
    assert [(sid, rej.reason) for sid, rej, _ in refused] == [("A", "out_of_range")]
    assert seq.sources["A"].lone is not None and list(seq.release()) == []
    seq.accept(seq.check("A", RADAR, 99, times[-1]), "last")
    assert seq.sources["A"].lone is None and times[-1] - times[0] >= lag
    released = [r.item for r in seq.release()]
    assert released and released[0] == "a0" and "glitch" not in released


def test_a_jump_inside_a_lone_run_is_held_and_does_not_confirm_the_run() -> None:
    """A lone run (another radar known, silent) with one batch stamped ``max_lag_s`` ahead and
    the source going on from there: the jump is held, its next batch confirms it, but the run
    counts from the jump, so the run is still lone (a single jump of that size had confirmed
    the whole run at once)."""
    lag = SequencerParams().max_lag_s
    seq = _known("A", "B")
    seq.accept(seq.check("A", RADAR, 1, 100.0), "a1")
    seq.accept(seq.check("A", RADAR, 2, 104.0), "a2")
    seq.accept(seq.check("A", RADAR, 3, 104.0 + lag + 5.0), "jump")
    assert seq.sources["A"].held is not None
    seq.accept(seq.check("A", RADAR, 4, 108.0 + lag + 5.0), "after")
    assert seq.sources["A"].held is None and seq.sources["A"].lone is not None
    assert list(seq.release()) == []
    # the other radar's first batch agrees with the run's start: the run is confirmed, in order
    seq.accept(seq.check("B", RADAR, 1, 101.0), "b1")
    assert seq.sources["A"].lone is None
    assert [r.item for r in seq.flush()] == ["a1", "b1", "a2", "jump", "after"]


def test_a_lone_source_whose_clock_stands_still_is_bounded() -> None:
    """A lone source whose stamp stands still never makes run time: at most
    ``max_lone_batches`` of its batches are held, the next are rejected (counted, nothing held),
    and another source's agreeing clock still confirms what was held."""
    seq = Sequencer(SequencerParams(max_lone_batches=5))
    seq.announce("A", RADAR)
    seq.announce("B", RADAR)
    seq.sites_known = 2
    for n in range(1, 6):
        seq.accept(seq.check("A", RADAR, n, 100.0), f"a{n}")
    with pytest.raises(RejectionError, match="max_lone_batches"):
        seq.check("A", RADAR, 6, 100.0)
    assert len(seq.sources["A"].pending) == 5
    seq.accept(seq.check("B", RADAR, 1, 100.0), "b1")
    assert seq.sources["A"].lone is None and len(list(seq.flush())) == 6


def test_a_partitioned_worker_owning_one_radar_is_not_the_network_s_only_source() -> None:
    """Partitioned, a worker's sequencer holds only its own radars, yet every site is known: a
    worker owning one radar whose first batches come an hour ahead does not confirm them by
    themselves; another worker's confirmed clock (observed) refutes them all."""
    seq = Sequencer(SequencerParams())
    seq.announce("A", RADAR)
    seq.sites_known = 3  # A's, and the radars of the other workers
    for n in range(1, 4):
        seq.accept(seq.check("A", RADAR, n, 4600.0 + 4.0 * n), f"rogue{n}")
    assert seq.sources["A"].lone is not None and list(seq.release()) == []
    seq.observe("B", 1000.0)
    _, refused = seq.accept(seq.check("A", RADAR, 4, 1004.0), "a4")
    assert [(sid, rej.reason) for sid, rej, _ in refused] == [("A", "out_of_range")] * 3
    assert seq.sources["A"].last_time_s == 1004.0 and seq.sources["A"].batches == 1


def test_a_radar_of_a_long_scan_alone_among_known_sites_is_confirmed_after_max_lag_s() -> None:
    """A radar of a 12 s scan (steps over ``max_step_s``), the only one reporting while another
    radar is known: its gaps are no jump, so its run confirms itself after ``max_lag_s`` and is
    released (each of its steps was held and restarted the run: never released, then
    refused once ``max_lone_batches`` were held)."""
    lag = SequencerParams().max_lag_s
    seq = _known("A", "B")
    released = []
    for n in range(1, 60):
        seq.accept(seq.check("A", RADAR, n, 100.0 + 12.0 * n), n)
        released += [r.item for r in seq.release()]
        assert (seq.sources["A"].lone is None) == (12.0 * (n - 1) >= lag), n
    assert released == list(range(1, len(released) + 1)) and len(released) > 50


def test_a_step_held_inside_a_lone_run_goes_with_the_run_when_it_is_withdrawn() -> None:
    """A's lone run an hour ahead holds a jump inside it when the other radars' agreeing clocks
    refute the run: the held batch is rejected with it, and A's counters are those of before
    (the held batch had stayed, its lost batches counted after the withdrawal)."""
    seq = _known("A", "B", "C")
    seq.accept(seq.check("A", RADAR, 10, 4600.0), "r10")
    seq.accept(seq.check("A", RADAR, 11, 4604.0), "r11")
    seq.accept(seq.check("A", RADAR, 15, 4700.0), "jump")  # held: 3 seqs lost before it
    assert seq.sources["A"].held is not None
    seq.accept(seq.check("B", RADAR, 1, 1000.0), "b1")
    _, refused = seq.accept(seq.check("C", RADAR, 1, 1000.5), "c1")  # B and C agree
    assert [(sid, rej.reason) for sid, rej, _ in refused] == [("A", "out_of_range")] * 3
    a = seq.sources["A"]
    assert (a.held, a.lone, a.last_seq, a.batches, a.lost_batches) == (None, None, None, 0, 0)
    seq.accept(seq.check("A", RADAR, 16, 1001.0), "a16")
    assert (a.batches, a.lost_batches, a.last_seq) == (1, 0, 16)


def test_a_full_lone_run_is_still_confirmed_by_a_clock_elsewhere() -> None:
    """A's stamp stood still until ``max_lone_batches`` were held, then B's and C's confirmed
    clock came 15 s behind (more than ``max_step_s``: A's run waits for its next batch).  That
    batch is confirmed by their clock, so it is taken, not refused as one more lone batch."""
    seq = _known("A", "B", "C", params=SequencerParams(max_lone_batches=3))
    for n in range(1, 4):
        seq.accept(seq.check("A", RADAR, n, 100.0), f"a{n}")
    seq.accept(seq.check("B", RADAR, 1, 85.0), "b1")
    seq.accept(seq.check("C", RADAR, 1, 85.5), "c1")  # B and C agree: a confirmed clock
    assert seq.sources["A"].lone is not None and seq.sources["B"].lone is None
    seq.accept(seq.check("A", RADAR, 4, 104.0), "a4")
    assert seq.sources["A"].lone is None and seq.sources["A"].batches == 4


def test_a_radar_two_minutes_fast_does_not_set_the_pace_of_the_picture() -> None:
    """Radar A's clock runs 120 s fast (within ``max_clock_skew_s``, so taken).  Leading alone,
    it set the release's pace: B and C, lagging it by more than ``max_lag_s``, stopped holding
    the release back, the picture went on at A's clock and held A's tracks alone (three-radar,
    at 100 s of data: outputs at 220 s, 78 system tracks, every one of A only).  A clock no
    other comes within ``max_lag_s`` of does not lead while three or more clocks can outvote
    it: the picture follows B and C and holds their tracks, paired."""
    stream = scenario_messages("three-radar", duration_s=120.0)
    sites = [m for m in stream if m[0].endswith("/site")]
    plots = [
        (k, shifted(p, 120.0) if k == "fusion/radar/A/plots" else p)
        for k, p in stream
        if k.endswith("/plots")
    ]
    t0 = min(json.loads(p)["time_s"] for _, p in stream if not _.endswith("/site"))
    engine = Engine(EngineConfig())
    for key, payload in sites:
        engine.ingest(key, payload)
    for key, payload in sorted(plots, key=lambda m: json.loads(m[1])["time_s"] - 120.0 * ("/A/" in m[0])):
        engine.ingest(key, payload)
        if json.loads(payload)["time_s"] >= t0 + 100.0 and "/A/" not in key:
            break
    snap = engine.snapshot()
    assert snap.outputs_time_s is not None and snap.outputs_time_s <= t0 + 100.0
    members = Counter(m["radar_id"] for t in snap.system_tracks()["system_tracks"] for m in t["members"])
    assert members["B"] >= 60 and members["C"] >= 60, members
    assert _pair_counts(engine)[("B", "C")] >= 60


def test_outputs_complete_through_never_go_back_for_a_radar_running_slow() -> None:
    """Radar C's clock runs 60 s slow: it lags the others by more than ``max_lag_s``, so the
    release does not wait for it and each of its batches is released as it comes, a minute
    behind.  With the correlation in its own process, such a batch waiting for its answer
    pulled ``outputs_time_s`` back by a minute (a client waiting on it, or an alert on it, saw
    the outputs go back and forth under a lagging or flooding radar); it never goes back."""
    stream = scenario_messages("three-radar", duration_s=90.0)
    arriving = [(k, shifted(p, -60.0) if k == "fusion/radar/C/plots" else p) for k, p in stream]
    engine = Engine(EngineConfig(), correlation_process=True)
    try:
        seen = []
        for key, payload in arriving:  # in the order of true time: C's stamps a minute behind
            engine.ingest(key, payload)
            if (t := engine.outputs_time_s) is not None:
                seen.append(t)
        engine.flush()
        c = next(r for r in engine.snapshot().status()["radars"] if r["radar_id"] == "C")
        assert c["batches"] > 0 and c["tracks_confirmed"] > 0  # (C is taken, and tracked)
    finally:
        engine.close()
    assert len(seen) > 100 and seen == sorted(seen)


@pytest.mark.parametrize(
    ("clocks", "pace"),
    [  # (clock, the newest clock of all when it was last heard)
        (((100.0, 219.0), (101.0, 219.0), (220.0, 220.0)), 101.0),  # one ahead alone: outvoted
        (((100.0, 100.0), (101.0, 101.0), (220.0, 220.0)), 220.0),  # the others stopped: it leads
        (((100.0, 219.0), (220.0, 220.0)), 220.0),  # two: no majority, the newest leads
        (((50.0, 50.0), (200.0, 201.0), (201.0, 201.0)), 201.0),  # one stuck behind (an outage)
        (((100.0, 221.0), (101.0, 221.0), (220.0, 221.0), (221.0, 221.0)), 221.0),  # two ahead together
        (((100.0, 300.0), (200.0, 300.0), (300.0, 300.0)), 300.0),  # no clock with a neighbour
    ],
)
def test_the_release_follows_the_newest_clock_unless_it_runs_ahead_alone(
    clocks: tuple[tuple[float, float], ...], pace: float
) -> None:
    seq = Sequencer(SequencerParams())
    for n, (t, heard) in enumerate(clocks):
        seq.sources[f"R{n}"] = SourceClock(RADAR, last_seq=1, last_time_s=t, heard_at_s=heard)
    lag = seq.params.max_lag_s
    assert seq.watermark() == min(c for c, _ in clocks if pace - lag <= c <= pace)


def test_two_radars_of_three_stopping_do_not_freeze_the_picture() -> None:
    """B and C stop reporting after 40 s (their feed is down), A goes on: once A is ``max_lag_s``
    ahead of them they no longer hold the release back, and the picture follows A (the rule
    against a clock running ahead alone asks that the others are still reporting)."""
    stream = scenario_messages("three-radar", duration_s=120.0)
    t0 = min(json.loads(p)["time_s"] for k, p in stream if k.endswith("/plots"))
    cut = [
        (k, p)
        for k, p in stream
        if not k.endswith("/plots") or "/A/" in k or json.loads(p)["time_s"] <= t0 + 40.0
    ]
    engine = Engine(EngineConfig())
    for key, payload in cut:
        engine.ingest(key, payload)
    snap = engine.snapshot()
    assert snap.outputs_time_s is not None and snap.outputs_time_s >= t0 + 110.0
    status = {r["radar_id"]: r for r in snap.status_core()["radars"]}
    assert status["A"]["tracks_confirmed"] > 0


def test_radars_whose_stamps_stand_still_are_not_still_reporting() -> None:
    """B and C keep sending batches stamped 40 s (their clocks stuck) while A goes on: batches
    at a stamp that stands still are no sign of life, so A leads once it is ``max_lag_s``
    ahead, as before the rule against a clock running ahead alone (they had counted as still
    reporting: the release stayed at 40 s)."""
    seq = _known("A", "B", "C")
    for n in range(1, 100):
        t = 2.0 * n
        seq.accept(seq.check("A", RADAR, n, t), f"a{n}")
        for rid in "BC":
            seq.accept(seq.check(rid, RADAR, n, min(t, 40.0)), f"{rid}{n}")
        list(seq.release())
    assert seq.watermark() >= 198.0 - seq.params.max_lag_s


def test_a_worker_saying_the_same_clocks_again_is_no_sign_of_life() -> None:
    """Partitioned: another worker's radars A, B and C stopped at 40 s, and its clock message
    names their clocks again each time (unchanged); this worker's D goes on.  D leads once it
    is ``max_lag_s`` ahead, as one worker would release (the repeated clocks had counted as
    heard: the release stayed at 40 s)."""
    seq = Sequencer(SequencerParams())
    seq.announce("D", RADAR)
    seq.sites_known = 4
    for n in range(1, 100):
        t = 2.0 * n
        for rid in "ABC":
            seq.observe(rid, min(t, 40.0))
        seq.accept(seq.check("D", RADAR, n, t), f"d{n}")
        list(seq.release())
    assert seq.watermark() >= 198.0 - seq.params.max_lag_s
