"""Valid but hostile input: each message is allowed by the contract's grammar and must not cost
the good input anything (service/pipeline/sequencer.py, tracking_stage.py, correlation_stage.py).

Each test runs a real simulated stream with and without the hostile messages and checks that
the honest radars' tracks and pairs come out exactly as without them.
"""

from __future__ import annotations

import functools
import json
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from service.engine import Engine, EngineConfig
from service.pipeline.sequencer import SequencerParams
from tests.scenario_helpers import scenario_messages
from tests.support import run_engine

Stream = list[tuple[str, bytes]]


def results(engine: Engine, radars: tuple[str, ...] = ("A", "B")) -> dict[str, Any]:
    snap = engine.snapshot()
    return {
        "tracks": [b for b in snap.track_batches("all") if b["radar_id"] in radars],
        "pairs": [ps for ps in snap.pair_sets(status="all") if {ps["radar_a"], ps["radar_b"]} <= set(radars)],
        "biases": [b for b in snap.biases() if b["radar_id"] in radars],
    }


def errors(out: list[Any]) -> list[dict[str, Any]]:
    return [json.loads(o.payload) for o in out if o.key == "fusion/errors"]


@pytest.fixture(scope="module")
def stream() -> Stream:
    return scenario_messages("two-radar", duration_s=90.0)


@pytest.fixture(scope="module")
def baseline(stream: Stream) -> tuple[Engine, list[Any]]:
    return run_engine(stream)


def batches(stream: Stream, radar: str) -> list[tuple[int, dict[str, Any]]]:
    return [(i, json.loads(p)) for i, (k, p) in enumerate(stream) if k == f"fusion/radar/{radar}/plots"]


def insert_after(stream: Stream, index: int, extra: Stream) -> Stream:
    return [*stream[: index + 1], *extra, *stream[index + 1 :]]


def test_batch_far_in_the_future_is_rejected_and_costs_nothing(
    stream: Stream, baseline: tuple[Engine, list[Any]]
) -> None:
    i, body = batches(stream, "A")[10]
    future = {**body, "seq": body["seq"] + 1, "time_s": body["time_s"] + 1e9}
    future["plots"] = {**body["plots"], "time_s": [body["time_s"] + 1e9] * len(body["plots"]["time_s"])}
    # It carries the seq of the next honest batch: rejected whole, it never happened.
    engine, out = run_engine(insert_after(stream, i, [("fusion/radar/A/plots", json.dumps(future).encode())]))
    (err,) = errors(out)
    assert err["reason"] == "out_of_range" and "ahead of the other sources" in err["detail"]
    assert results(engine) == results(baseline[0])
    assert engine.sequencer.sources["A"].lost_batches == 0 and engine.sequencer.sources["A"].rejected == 1


def test_future_source_first_cannot_hold_or_release_the_others(
    stream: Stream, baseline: tuple[Engine, list[Any]]
) -> None:
    """A rogue source whose very first batch is 10^9 s ahead, before any other clock: its clock
    is lone, the honest ones refute it, and it is withdrawn (rejected) without holding them back
    or releasing anything."""
    sites = [m for m in stream if m[0].endswith("/site")]
    rogue_site = json.loads(sites[0][1]) | {"radar_id": "R", "latitude_deg": 10.0}
    _, a0 = batches(stream, "A")[0]
    rogue = {**a0, "radar_id": "R", "seq": 1, "time_s": a0["time_s"] + 1e9}
    rogue["plots"] = {**a0["plots"], "time_s": [a0["time_s"] + 1e9] * len(a0["plots"]["time_s"])}
    head = [
        ("fusion/radar/R/site", json.dumps(rogue_site).encode()),
        ("fusion/radar/R/plots", json.dumps(rogue).encode()),
    ]
    rest = [m for m in stream if not m[0].endswith("/site")]
    engine, out = run_engine([*sites, *head, *rest])
    assert [(e["radar_id"], e["reason"]) for e in errors(out)] == [("R", "out_of_range")]
    assert "no other source had a live data clock" in errors(out)[0]["detail"]
    assert results(engine) == results(baseline[0])
    later = {**rogue, "seq": 2, "time_s": rogue["time_s"] + 4}
    (err,) = errors(engine.ingest("fusion/radar/R/plots", json.dumps(later).encode()))
    assert err["reason"] == "out_of_range"


@pytest.mark.parametrize("back_s", [120.0, 3600.0])
def test_a_batch_stepping_back_in_data_time_is_rejected_and_costs_nothing(
    stream: Stream, baseline: tuple[Engine, list[Any]], back_s: float
) -> None:
    """A batch whose ``seq`` goes on but whose data time is far behind its radar's clock (a
    stale batch): rejected whole, said, and nothing of it taken (taken, it was counted and its
    plots, older than the radar's tracks, made nothing, silently)."""
    i, body = batches(stream, "A")[20]
    _, nxt = batches(stream, "A")[21]
    stale = {**body, "seq": nxt["seq"], "time_s": body["time_s"] - back_s}
    stale["plots"] = {**body["plots"], "time_s": [t - back_s for t in body["plots"]["time_s"]]}
    engine, out = run_engine(insert_after(stream, i, [("fusion/radar/A/plots", json.dumps(stale).encode())]))
    (err,) = errors(out)
    assert err["reason"] == "out_of_range" and "behind this source's data clock" in err["detail"]
    assert results(engine) == results(baseline[0])
    a = engine.sequencer.sources["A"]
    assert a.rejected == 1 and a.batches == baseline[0].sequencer.sources["A"].batches


def test_absurd_seq_jump_is_rejected_and_the_radar_goes_on(
    stream: Stream, baseline: tuple[Engine, list[Any]]
) -> None:
    i, body = batches(stream, "B")[5]
    extra = [
        ("fusion/radar/B/plots", json.dumps({**body, "seq": 10**30}).encode()),  # beyond int64
        ("fusion/radar/B/plots", json.dumps({**body, "seq": body["seq"] + 10**6}).encode()),  # in int64
    ]
    engine, out = run_engine(insert_after(stream, i, extra))
    assert [e["reason"] for e in errors(out)] == ["out_of_range", "out_of_range"]
    assert "skips" in errors(out)[1]["detail"]
    assert results(engine) == results(baseline[0])
    assert engine.sequencer.sources["B"].batches == baseline[0].sequencer.sources["B"].batches


def test_long_outage_may_skip_many_seq_numbers() -> None:
    """A jump that the elapsed data time explains is a gap, not an attack."""
    engine = Engine(EngineConfig(sequencer=SequencerParams(max_seq_jump=10, max_batch_rate_hz=5.0)))
    engine.ingest(
        "fusion/radar/A/site",
        json.dumps({"radar_id": "A", "latitude_deg": 31, "longitude_deg": 118}).encode(),
    )

    def batch(seq: int, t: float) -> bytes:
        plots = {"time_s": [t], "range_m": [5e4], "azimuth_deg": [10.0], "elevation_deg": [1.0]}
        return json.dumps({"radar_id": "A", "seq": seq, "time_s": t, "plots": plots}).encode()

    assert not errors(engine.ingest("fusion/radar/A/plots", batch(1, 1000.0)))
    assert errors(engine.ingest("fusion/radar/A/plots", batch(500, 1010.0)))  # 498 in 10 s: > 5 Hz
    assert not errors(engine.ingest("fusion/radar/A/plots", batch(500, 1200.0)))  # 498 in 200 s: fine
    assert engine.sequencer.sources["A"].lost_batches == 498


def test_publisher_restart_is_recognised_not_locked_out(stream: Stream) -> None:
    """A radar restarts its counter (seq back to 1) at a later time: counted, and tracked on."""
    b_batches = batches(stream, "B")
    k = len(b_batches) // 2
    restarted = list(stream)
    for n, (j, b) in enumerate(b_batches[k:]):
        restarted[j] = (restarted[j][0], json.dumps({**b, "seq": n + 1}).encode())
    engine, out = run_engine(restarted)
    assert errors(out) == []
    assert engine.sequencer.sources["B"].restarts == 1
    assert engine.sequencer.sources["B"].batches == len(b_batches)
    base, _ = run_engine(stream)
    assert results(engine) == results(base)
    # a true duplicate is still one: the first batch after the restart, sent again
    j, _ = b_batches[k]
    (err,) = errors(engine.ingest(*restarted[j]))
    assert err["reason"] == "duplicate_seq"


def test_site_resent_slightly_moved_changes_nothing(
    stream: Stream, baseline: tuple[Engine, list[Any]]
) -> None:
    site_b = json.loads(next(p for k, p in stream if k == "fusion/radar/B/site"))
    mixed: Stream = []
    n = 0
    for key, payload in stream:
        mixed.append((key, payload))
        if key.endswith("/plots"):
            n += 1
            jitter = (n % 2) * 1e-6  # 1e-6 deg of latitude is 0.11 m
            moved = {**site_b, "latitude_deg": site_b["latitude_deg"] + jitter}
            mixed.append(("fusion/radar/B/site", json.dumps(moved).encode()))
    engine, out = run_engine(mixed)
    assert errors(out) == []
    assert results(engine) == results(baseline[0])
    assert engine.snapshot().status_core()["pairs_confirmed"] > 10


def test_a_real_move_reregisters_only_that_radars_pairs() -> None:
    stream = scenario_messages("three-radar", duration_s=90.0)
    times = [json.loads(p).get("time_s") for _, p in stream]
    start = min(t for t in times if t is not None)
    first = stream[: next(i for i, t in enumerate(times) if t is not None and t > start + 60.0)]
    engine = Engine()
    for key, payload in first:
        engine.ingest(key, payload)
    before = {k: (c, c.book, c.memory) for k, c in engine.correlation.stage.pair_correlators.items()}
    assert set(before) == {("A", "B"), ("A", "C"), ("B", "C")}
    site_c = json.loads(next(p for k, p in stream if k == "fusion/radar/C/site"))
    moved = {**site_c, "latitude_deg": site_c["latitude_deg"] + 0.01}  # 1.1 km
    engine.ingest("fusion/radar/C/site", json.dumps(moved).encode())
    after = engine.correlation.stage.pair_correlators
    assert after[("A", "B")] is before[("A", "B")][0]  # untouched
    for key in (("A", "C"), ("B", "C")):
        assert after[key].book is before[key][1]  # the pairs are kept...
        assert len(after[key].memory) == 0 < len(before[key][2])  # ...the registration starts again
        assert after[key].site_b is not None and after[key].site_b.latitude_deg == moved["latitude_deg"]
    # ... and go on: a pair confirmed before the move whose tracks live on is the same pair
    # after it (its first hit unchanged), not one dropped and found again
    kept = {
        key: {
            (s.track_a, s.track_b): s.first_time_s for s in before[key][1].states() if s.status == "confirmed"
        }
        for key in (("A", "C"), ("B", "C"))
    }
    for key, payload in stream[len(first) :]:
        engine.ingest(key, payload)
    engine.flush()
    for key, was in kept.items():
        now = {(s.track_a, s.track_b): s.first_time_s for s in after[key].book.states()}
        lasting = set(was) & set(now)
        assert len(lasting) > len(was) // 2 > 0
        assert all(now[pair] == was[pair] for pair in lasting)


def test_many_fake_radar_ids_cost_nothing(stream: Stream, baseline: tuple[Engine, list[Any]]) -> None:
    """300 ids with a site near the real radars and one 5-plot batch each: the honest radars'
    results are unchanged and the fakes are never correlated (cost follows tracks, not ids)."""
    site_a = json.loads(next(p for k, p in stream if k == "fusion/radar/A/site"))
    _, a0 = batches(stream, "A")[0]
    extra: Stream = []
    for n in range(300):
        rid = f"A{n:03d}"
        extra.append(
            (
                f"fusion/radar/{rid}/site",
                json.dumps(
                    {**site_a, "radar_id": rid, "longitude_deg": site_a["longitude_deg"] + n * 1e-3}
                ).encode(),
            )
        )
        plots = {k: v[:5] for k, v in a0["plots"].items()}
        extra.append(
            (
                f"fusion/radar/{rid}/plots",
                json.dumps({"radar_id": rid, "seq": 1, "time_s": a0["time_s"], "plots": plots}).encode(),
            )
        )
    i, _ = batches(stream, "A")[0]
    engine, out = run_engine(insert_after(stream, i, extra))
    assert errors(out) == []
    assert results(engine) == results(baseline[0])
    assert set(engine.correlation.stage.pair_correlators) == {("A", "B")}
    assert engine.correlation.stage.updates == baseline[0].correlation.stage.updates
    assert engine.sequencer.sources["A042"].batches == 1


def test_silent_source_expires_and_its_pairs_empty(stream: Stream) -> None:
    params = SequencerParams(source_expiry_s=20.0, max_lag_s=10.0)
    engine = Engine(EngineConfig(sequencer=params))
    cut = None
    for key, payload in stream:
        body = json.loads(payload)
        if key == "fusion/radar/B/plots" and body["time_s"] > stream_start(stream) + 50:
            cut = cut or body["time_s"]
            continue
        engine.ingest(key, payload)
    engine.flush()
    b = engine.sequencer.sources["B"]
    assert b.expired and not engine.sequencer.sources["A"].expired
    assert len(engine.tracking.tracked["B"].table) == 0
    (ps,) = engine.snapshot().pair_sets(status="all")
    assert ps["pairs"] == []
    status = {r["radar_id"]: r for r in engine.snapshot().status_core()["radars"]}
    assert status["B"]["expired"] is True


def stream_start(stream: Stream) -> float:
    return min(json.loads(p)["time_s"] for k, p in stream if k.endswith("/plots"))


def test_source_table_is_bounded() -> None:
    engine = Engine(EngineConfig(sequencer=SequencerParams(max_sources=3)))
    site = {"latitude_deg": 31.0, "longitude_deg": 118.0}
    for rid in ("A", "B", "C"):
        assert engine.ingest(f"fusion/radar/{rid}/site", json.dumps({**site, "radar_id": rid}).encode()) == []
    (err,) = errors(engine.ingest("fusion/radar/D/site", json.dumps({**site, "radar_id": "D"}).encode()))
    assert err["reason"] == "out_of_range" and "source table full" in err["detail"]
    assert "D" not in engine.sequencer.sources and len(engine.sequencer.sources) == 3


def _declaring(stream: Stream, radar: str, period_s: float, after: int | None) -> Stream:
    """``stream`` with ``radar``'s site declaring ``period_s``: from the start (``after`` None)
    or re-sent after its ``after``-th batch."""
    key = f"fusion/radar/{radar}/site"
    site = {**json.loads(next(p for k, p in stream if k == key)), "scan_period_s": period_s}
    if after is None:
        return [(k, json.dumps(site).encode() if k == key else p) for k, p in stream]
    return insert_after(stream, batches(stream, radar)[after][0], [(key, json.dumps(site).encode())])


def _confirmed(engine: Engine) -> tuple[dict[str, int], dict[tuple[str, str], int]]:
    snap = engine.snapshot()
    tracks = {
        b["radar_id"]: sum(t["status"] == "confirmed" for t in b["tracks"]) for b in snap.track_batches("all")
    }
    return tracks, {(p["radar_a"], p["radar_b"]): len(p["pairs"]) for p in snap.pair_sets(status="confirmed")}


@pytest.mark.slow
@pytest.mark.parametrize(("period_s", "after"), [(1.0, None), (1.0, 30), (2.0, None), (6.0, 30)])
def test_a_site_declaring_the_wrong_scan_period_does_not_cost_the_radar_its_tracks(
    period_s: float, after: int | None
) -> None:
    """Radar B turns in 4 s; its site says ``period_s``.  Counting its life cycle in a period 4x
    too short deleted every track before its next look (B held no track, its pairs none).  The
    tracker measures the revisit period from the plots and counts in that: B's tracks and pairs
    are within a few of the honest run's, and ``/status`` shows the observed period."""
    honest = scenario_messages("three-radar", duration_s=120.0)
    wrong = _declaring(honest, "B", period_s, after)
    engine, out = run_engine(wrong)
    assert errors(out) == []
    (tracks, pairs), (clean_tracks, clean_pairs) = _confirmed(engine), _honest_confirmed()
    assert tracks["B"] >= 0.95 * clean_tracks["B"] > 50
    assert set(pairs) == set(clean_pairs) and all(pairs[k] >= 0.9 * clean_pairs[k] for k in pairs)
    status = {r["radar_id"]: r for r in engine.snapshot().status_core()["radars"]}
    assert status["B"]["scan_period_observed_s"] == pytest.approx(4.0, rel=0.02)


@functools.cache
def _honest_confirmed() -> tuple[dict[str, int], dict[tuple[str, str], int]]:
    """The honest three-radar run's (120 s) confirmed tracks and pairs, the reference of the
    tests of wrong sites: run once per test process (a run is deterministic)."""
    return _confirmed(run_engine(scenario_messages("three-radar", duration_s=120.0))[0])


def _without(*rules: str) -> EngineConfig:
    """The default configuration with the tracker's ``rules`` (``revisit``, ``noise``) off."""
    tracking = EngineConfig().tracking
    off = {rule: replace(getattr(tracking, rule), enabled=False) for rule in rules}
    return replace(EngineConfig(), tracking=replace(tracking, **off))


def test_an_honest_site_keeps_the_tracker_exactly_as_it_was() -> None:
    """The observed period and the innovations agree with the site: every output is the one of
    a tracker that never measures them; and with the measurements off, a wrong period or
    sigmas still cost the radar its tracks (what the rules are for)."""
    honest = scenario_messages("three-radar", duration_s=90.0)
    _, out = run_engine(honest)
    _, out_off = run_engine(honest, _without("revisit", "noise"))
    assert [(o.key, o.payload) for o in out] == [(o.key, o.payload) for o in out_off]
    blind, _ = run_engine(_declaring(honest, "B", 1.0, None), _without("revisit"))
    assert _confirmed(blind)[0].get("B", 0) == 0


@pytest.mark.slow
@pytest.mark.parametrize("share", [1 / 2, 1 / 3])
def test_a_site_declaring_sigmas_too_small_does_not_cost_the_radar_its_tracks(share: float) -> None:
    """Radar B's site declares its range, azimuth and elevation sigmas at ``share`` of the
    truth: the filter trusted its plots too much and its gate refused the next ones (a third:
    B kept half its tracks).  The innovations show it, the sigmas grow, B's tracks and pairs
    are within a few of the honest run's."""
    honest = scenario_messages("three-radar", duration_s=120.0)
    key = "fusion/radar/B/site"
    site = json.loads(next(p for k, p in honest if k == key))
    site.update({f: site[f] * share for f in ("range_sigma_m", "azimuth_sigma_deg", "elevation_sigma_deg")})
    wrong = [(k, json.dumps(site).encode() if k == key else p) for k, p in honest]
    engine, out = run_engine(wrong)
    blind, _ = run_engine(wrong, _without("noise"))
    assert errors(out) == []
    (tracks, pairs), (clean_tracks, clean_pairs) = _confirmed(engine), _honest_confirmed()
    assert tracks["B"] >= 0.95 * clean_tracks["B"] > 50
    assert set(pairs) == set(clean_pairs) and all(pairs[k] >= 0.9 * clean_pairs[k] for k in pairs)
    status = {r["radar_id"]: r for r in engine.snapshot().status_core()["radars"]}
    assert status["B"]["measurement_sigma_scale"] > 1.5 and status["A"]["measurement_sigma_scale"] == 1.0
    assert _confirmed(blind)[0]["B"] < tracks["B"]


@pytest.mark.slow
def test_heavy_clutter_does_not_set_the_site_checks_off() -> None:
    """Radar B's batches each carry 400 clutter plots spread over its sector (3 200 a scan):
    the gaps between plots show no period (the declared one stands) and the clutter its gates
    take raises the innovations, but growing the sigmas does not bring them down, so the
    growth is undone and held: B's confirmed tracks stay near those of a tracker without
    either check (grown on, the sigmas reached ten times and B confirmed 3 500 tracks against
    270), and the pairs with B stand."""
    honest = scenario_messages("three-radar", duration_s=120.0)
    rng = np.random.default_rng(7)
    cluttered = []
    for key, payload in honest:
        if key == "fusion/radar/B/plots":
            body = json.loads(payload)
            plots, n = body["plots"], 400
            t0, az = min(plots["time_s"], default=body["time_s"] - 0.5), plots["azimuth_deg"]
            extra = {
                "time_s": rng.uniform(t0, body["time_s"], n),
                "range_m": rng.uniform(5e3, 250e3, n),
                "azimuth_deg": rng.uniform(min(az, default=0.0), max(az, default=45.0), n),
                "altitude_m": rng.uniform(1e3, 12e3, n),
                "elevation_deg": rng.uniform(0.0, 5.0, n),
            }
            for column, values in plots.items():
                plots[column] = values + (list(extra[column]) if column in extra else [None] * n)
            payload = json.dumps(body).encode()
        cluttered.append((key, payload))
    engine, out = run_engine(cluttered)
    blind, _ = run_engine(cluttered, _without("revisit", "noise"))
    assert errors(out) == []
    status = {r["radar_id"]: r for r in engine.snapshot().status_core()["radars"]}
    assert status["B"]["measurement_sigma_scale"] == 1.0
    assert (
        status["B"]["scan_period_observed_s"] is None
        or abs(status["B"]["scan_period_observed_s"] - 4.0) < 0.2
    )
    (tracks, pairs), (blind_tracks, blind_pairs) = _confirmed(engine), _confirmed(blind)
    assert tracks["B"] <= 1.3 * blind_tracks["B"]
    assert set(pairs) == set(blind_pairs) and all(pairs[k] >= 0.9 * blind_pairs[k] for k in pairs)


@pytest.mark.slow
def test_a_site_updated_to_a_longer_scan_period_widens_the_tracker_s_window() -> None:
    """Every radar's site said 4 s for its first four batches and then the true period (8, 10
    and 6 s: the formation scene).  The tracker's window was sized once, when its first batch
    was released, to three looks of 4 s: it held one look of a 10 s radar, and no track ever
    started on A or B.  The window follows the site: the radars track as in the honest run."""
    honest = scenario_messages("formation", duration_s=200.0)
    periods = {k.split("/")[2]: json.loads(p)["scan_period_s"] for k, p in honest if k.endswith("/site")}
    assert max(periods.values()) >= 8.0
    wrong = honest
    for radar in periods:
        wrong = _declaring(wrong, radar, 4.0, None)
    for radar in periods:
        key = f"fusion/radar/{radar}/site"
        true_site = next(p for k, p in honest if k == key)
        wrong = insert_after(wrong, batches(wrong, radar)[3][0], [(key, true_site)])
    clean, _ = run_engine(honest)
    engine, out = run_engine(wrong)
    assert errors(out) == []
    tracks, clean_tracks = _confirmed(engine)[0], _confirmed(clean)[0]
    assert set(tracks) == set(periods)
    assert all(tracks[r] >= 0.9 * clean_tracks[r] > 10 for r in periods), (tracks, clean_tracks)
