"""ADS-B as a bias-free reference source, and identity codes through to tracks and pairs
(contract §4.1, §4.2): real simulated streams through the engine."""

from __future__ import annotations

import json
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import zenoh

from service.correlation.correlator import CorrelationParams
from service.engine import Engine, EngineConfig
from service.pipeline.sequencer import REFERENCE
from service.reference import ReferenceParams, ReferenceTracks
from service.tracking.identity import LatestCodes
from tests.support import put_json, run_engine, running_service, wait_for, wait_subscribed
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import AdsbSpec, identity_of, wire_messages

BIAS = {"range_bias_m": 300.0, "azimuth_bias_deg": 0.25, "elevation_bias_deg": 0.05}


def lone_radar_stream(duration_s: float = 420.0, seed: int = 3) -> list[tuple[str, bytes]]:
    """One biased secondary radar with no other radar in reach, and an ADS-B receiver that
    hears every other aircraft (a fifth of its reports without a height)."""
    base = get_scenario("two-radar")
    radar = replace(base.radars[0], identity=True, **BIAS)  # type: ignore[arg-type]
    sc = replace(
        base,
        radars=(radar,),
        targets=80,
        duration_s=duration_s,
        adsb=(AdsbSpec("adsb-1", stride=2, no_height=0.2),),
    )
    return list(wire_messages(sc, seed))


@pytest.fixture(scope="module")
def lone() -> tuple[Engine, list[Any]]:
    return run_engine(lone_radar_stream())


def truth_of(engine: Engine, radar: str) -> dict[str, str | None]:
    table = engine.snapshot().tracks[radar][1]
    return dict(zip(table.track_id.tolist(), table.truth_id.tolist(), strict=True))


def test_a_lone_radar_gets_absolute_biases_from_adsb(lone: tuple[Engine, list[Any]]) -> None:
    engine, out = lone
    assert not [o for o in out if o.key == "fusion/errors"]
    (bias,) = engine.snapshot().biases()
    assert bias["radar_id"] == "A"
    assert bias["range_bias_m"] == pytest.approx(BIAS["range_bias_m"], rel=0.10)
    assert bias["azimuth_bias_deg"] == pytest.approx(BIAS["azimuth_bias_deg"], rel=0.10)


def test_radar_adsb_pairs_are_right(lone: tuple[Engine, list[Any]]) -> None:
    engine, _ = lone
    (ps,) = engine.snapshot().pair_sets(status="confirmed")
    assert (ps["radar_a"], ps["radar_b"], ps["method"]) == ("A", "adsb-1", "cfar")
    truth = truth_of(engine, "A")
    right = [p for p in ps["pairs"] if (t := truth.get(p["track_a"])) and identity_of(t)[1] == p["track_b"]]
    wrong = len(ps["pairs"]) - len(right)
    # the aircraft the ADS-B receiver hears and the radar holds a confirmed track of
    heard = {identity_of(t)[1] for t in truth.values() if t is not None}
    icao = {p["track_b"] for p in ps["pairs"]}
    assert icao <= heard | icao  # ids are addresses
    equipped = {
        t
        for tid, t in truth.items()
        if t is not None and int(t[1:]) % 2 == 1 and engine_confirmed(engine, tid)
    }
    assert len(right) >= 0.95 * len(equipped) > 0
    assert wrong <= 0.02 * len(ps["pairs"])


def engine_confirmed(engine: Engine, track_id: str) -> bool:
    table = engine.snapshot().tracks["A"][1]
    return bool(table.confirmed[table.track_id == track_id].any())


def test_tracks_carry_their_latest_codes_and_the_identity_figure_counts_them(
    lone: tuple[Engine, list[Any]],
) -> None:
    engine, _ = lone
    snap = engine.snapshot()
    batch = snap.track_batch("A", "confirmed")
    assert batch is not None
    labelled = [t for t in batch["tracks"] if t["truth_id"] is not None]
    codes_right = [t for t in labelled if (t["mode_3a"], t["mode_s"]) == identity_of(t["truth_id"])]
    assert len(codes_right) >= 0.95 * len(labelled) > 20
    ident = snap.status()["identity"]
    (ps,) = snap.pair_sets(status="confirmed")
    mode_s = {t["track_id"]: t["mode_s"] for t in snap.track_batch("A", "all")["tracks"]}  # type: ignore[index]
    both = [p for p in ps["pairs"] if mode_s.get(p["track_a"]) is not None]
    equal = [p for p in both if mode_s[p["track_a"]] == p["track_b"]]
    assert ident["pairs_with_mode_s"] == len(both) > 20
    assert ident["mode_s_equal"] == len(equal)
    assert ident["agreement"] == pytest.approx(len(equal) / len(both))
    assert ident["by_pair"] == [
        {"radar_a": "A", "radar_b": "adsb-1", "pairs_with_mode_s": len(both), "mode_s_equal": len(equal)}
    ]


def test_identity_veto_setting_is_off_by_default_and_forbids_conflicting_pairs() -> None:
    """With the veto, no confirmed pair joins two different Mode S addresses, even where the
    kinematics alone chose one (a lone radar against ADS-B, codes swapped on one aircraft's
    radar plots)."""
    assert CorrelationParams().identity_veto is False
    stream = lone_radar_stream(duration_s=240.0)
    swapped = []
    for key, payload in stream:
        if key.endswith("/plots"):
            body = json.loads(payload)
            # aircraft T1's radar plots carry T3's address: the kinematics pair it with T1
            t3 = identity_of("T3")[1]
            body["plots"]["mode_s"] = [
                t3 if t == "T1" else s
                for t, s in zip(body["plots"]["truth_id"], body["plots"]["mode_s"], strict=True)
            ]
            payload = json.dumps(body).encode()
        swapped.append((key, payload))
    t1 = identity_of("T1")[1]

    def pairs_of_t1(config: EngineConfig | None) -> list[dict[str, Any]]:
        engine, _ = run_engine(swapped, config)
        (ps,) = engine.snapshot().pair_sets(status="confirmed")
        return [p for p in ps["pairs"] if p["track_b"] == t1]

    assert len(pairs_of_t1(None)) == 1  # kinematics alone: T1's track and T1's reports
    veto = EngineConfig(correlation=CorrelationParams(identity_veto=True))
    assert pairs_of_t1(veto) == []


def test_bad_adsb_batches_are_rejected_whole() -> None:
    good = {
        "source_id": "adsb-1",
        "seq": 1,
        "time_s": 100.0,
        "reports": {"time_s": [99.0], "icao24": ["3c6444"], "latitude_deg": [48.7], "longitude_deg": [2.3]},
    }
    engine = Engine(EngineConfig())
    key = "fusion/adsb/adsb-1/reports"
    for bad, reason in [
        ({**good, "reports": {**good["reports"], "icao24": ["3C6444"]}}, "schema"),  # upper case
        ({**good, "reports": {**good["reports"], "altitude_m": [1.0, 2.0]}}, "schema"),  # lengths
        ({**good, "reports": {**good["reports"], "altitude_m": [2e6]}}, "out_of_range"),
    ]:
        (o,) = engine.ingest(key, json.dumps(bad).encode(), receive_time_s=0.0)
        assert json.loads(o.payload)["reason"] == reason
    assert all(s.kind != REFERENCE for s in engine.sequencer.sources.values())
    assert engine.ingest(key, json.dumps(good).encode()) == []
    # the same id as an AIS source: taken
    ais = {
        "source_id": "adsb-1",
        "seq": 2,
        "time_s": 101.0,
        "reports": {"time_s": [100.0], "mmsi": ["1"], "latitude_deg": [1.0], "longitude_deg": [1.0]},
    }
    (o,) = engine.ingest("fusion/ais/adsb-1/reports", json.dumps(ais).encode(), receive_time_s=0.0)
    assert json.loads(o.payload)["reason"] == "schema"
    assert engine.reference_kinds == {"adsb-1": "adsb"}
    # ... and as a radar: its site is refused too, and no radar of that id appears
    site = {"radar_id": "adsb-1", "latitude_deg": 48.0, "longitude_deg": 2.0}
    (o,) = engine.ingest("fusion/radar/adsb-1/site", json.dumps(site).encode(), receive_time_s=0.0)
    body = json.loads(o.payload)
    assert body["reason"] == "schema" and "reference source" in body["detail"], body
    assert "adsb-1" not in engine.tracking.tracked
    assert all(r["radar_id"] != "adsb-1" for r in engine.snapshot().status_core()["radars"])


def test_reports_without_height_take_their_aircraft_s_last_one() -> None:
    refs = ReferenceTracks(ReferenceParams(), "adsb")
    nan = np.nan
    refs.add(
        np.array([1.0, 1.0, 2.0]),
        np.array(["aaaaaa", "bbbbbb", "aaaaaa"]),
        np.array([48.0, 48.1, 48.0]),
        np.array([2.0, 2.1, 2.001]),
        np.array([nan, 9000.0, 10000.0]),  # aaaaaa's first report: no height known yet
        2.0,
    )
    refs.add(np.array([3.0]), np.array(["bbbbbb"]), np.array([48.1]), np.array([2.1]), np.array([nan]), 3.0)
    table = refs.table(3.0)
    from service.geo import ecef_to_geodetic

    alt = dict(
        zip(table.track_id.tolist(), np.atleast_1d(ecef_to_geodetic(table.position_ecef_m)[2]), strict=True)
    )
    assert alt["aaaaaa"] == pytest.approx(10000.0, abs=1e-3)
    assert alt["bbbbbb"] == pytest.approx(9000.0, abs=1e-3)
    assert table.plots.tolist() == [1, 2]  # aaaaaa's report without a height is left out
    assert table.mode_s.tolist() == ["aaaaaa", "bbbbbb"]


def latest_codes_reference(chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> dict[int, object]:
    """Plain form of :class:`LatestCodes`: walk every plot in order."""
    best: dict[int, tuple[float, object]] = {}
    for uids, times, codes in chunks:
        for u, t, c in zip(uids.tolist(), times.tolist(), codes.tolist(), strict=True):
            if c is not None and (u not in best or t >= best[u][0]):
                best[u] = (t, c)
    return {u: c for u, (_, c) in best.items()}


def test_latest_codes_equals_the_plain_form() -> None:
    rng = np.random.default_rng(5)
    codes = LatestCodes()
    every: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for _ in range(30):
        chunks = []
        for _ in range(int(rng.integers(0, 4))):
            n = int(rng.integers(0, 12))
            uid = rng.integers(0, 15, n).astype(np.int64)
            t = rng.integers(0, 20, n).astype(float)  # ties in time
            c = np.array(
                [None if rng.random() < 0.3 else f"{x:04o}" for x in rng.integers(0, 4096, n)], dtype=object
            )
            chunks.append((uid, t, c))
        codes.add_chunks(chunks)
        every += chunks
        want = latest_codes_reference(every)
        uids = np.arange(15, dtype=np.int64)
        assert codes.of(uids).tolist() == [want.get(u) for u in range(15)]


@pytest.mark.parametrize(
    ("column", "values", "reason"),
    [
        ("mode_3a", ["7000", "8000"], "schema"),  # not octal
        ("mode_s", ["3c6444", "3c644"], "schema"),  # 5 digits
        ("flight_level", [330.0, 5000.0], "out_of_range"),
        ("flight_level", [330.0], "schema"),  # length
        ("altitude_m", [9000.0, 2e6], "out_of_range"),
    ],
)
def test_bad_identity_columns_reject_the_batch_and_change_nothing(
    column: str, values: list[object], reason: str
) -> None:
    site = {"radar_id": "A", "latitude_deg": 31.0, "longitude_deg": 118.0}
    plots = {"time_s": [99.0, 99.5], "range_m": [5e4, 6e4], "azimuth_deg": [10.0, 20.0]}
    engine = Engine(EngineConfig())
    engine.ingest("fusion/radar/A/site", json.dumps(site).encode())
    bad = {"radar_id": "A", "seq": 1, "time_s": 100.0, "plots": {**plots, column: values}}
    (o,) = engine.ingest("fusion/radar/A/plots", json.dumps(bad).encode(), receive_time_s=0.0)
    assert json.loads(o.payload)["reason"] == reason
    assert engine.sequencer.sources["A"].last_seq is None
    ok = {"radar_id": "A", "seq": 1, "time_s": 100.0, "plots": {**plots, "mode_s": ["3c6444", None]}}
    keys = [x.key for x in [*engine.ingest("fusion/radar/A/plots", json.dumps(ok).encode()), *engine.flush()]]
    assert keys[0] == "fusion/radar/A/tracks" and "fusion/errors" not in keys


def test_adsb_over_zenoh_and_the_identity_figure_over_http(router: str, client: zenoh.Session) -> None:
    """The node subscribes to ADS-B sources; /status and /metrics serve the identity figure."""
    stream = lone_radar_stream(duration_s=240.0)
    with running_service(router) as svc:
        wait_subscribed(client, "fusion/adsb/adsb-1/reports")
        wait_subscribed(client, "fusion/radar/A/plots")
        for key, payload in stream:
            put_json(client, key, payload)

        def identity() -> dict[str, Any] | None:
            ident = svc.http.get("/status").json()["identity"]
            return ident if ident["pairs_with_mode_s"] >= 20 else None

        ident = wait_for(identity, timeout=60)
        assert ident["agreement"] == ident["mode_s_equal"] / ident["pairs_with_mode_s"] >= 0.95
        pairs = svc.http.get("/pairs", params={"radar_a": "adsb-1"}).json()
        assert [(ps["radar_a"], ps["radar_b"], ps["method"]) for ps in pairs] == [("A", "adsb-1", "cfar")]
        metrics = svc.http.get("/metrics").text
        assert 'topofusion_identity_pairs_with_mode_s{radar_a="A",radar_b="adsb-1"}' in metrics
        assert "topofusion_identity_agreement " in metrics
