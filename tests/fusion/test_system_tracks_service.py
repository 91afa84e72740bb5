"""System tracks through the engine and the running service (contract §4.4): a simulated
three-radar stream, scored by the simulator's truth (evaluation only)."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import zenoh

from service.correlation.prediction import predict_states
from service.engine import Engine
from service.geo import geodetic_to_ecef
from service.wire.models import SystemTrackBatch
from tests.support import put_json, run_engine, running_service, wait_for, wait_subscribed
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import AdsbSpec, identity_of, wire_messages

Truth = dict[tuple[str, float], np.ndarray]


def three_radar(duration_s: float) -> tuple[list[tuple[str, bytes]], Truth]:
    """The stream, and each aircraft's true position every second: an ADS-B source without
    errors that the service is not given."""
    exact = AdsbSpec(
        "truth", report_period_s=1.0, batch_period_s=1.0, position_sigma_m=0.0, height_sigma_m=0.0
    )
    sc = replace(get_scenario("three-radar"), duration_s=duration_s, adsb=(exact,))
    stream, truth = [], {}
    for key, payload in wire_messages(sc, 1):
        if "/adsb/" not in key:
            stream.append((key, payload))
            continue
        r = json.loads(payload)["reports"]
        for t, icao, la, lo, al in zip(
            r["time_s"], r["icao24"], r["latitude_deg"], r["longitude_deg"], r["altitude_m"], strict=True
        ):
            truth[(icao, round(t))] = geodetic_to_ecef(la, lo, al)
    return stream, truth


@pytest.fixture(scope="module")
def run() -> tuple[Engine, Truth]:
    stream, truth = three_radar(240.0)
    engine, _ = run_engine(stream)
    return engine, truth


def labels(engine: Engine) -> dict[tuple[str, str], str | None]:
    return {
        (rid, tid): t
        for rid, (_, table) in engine.snapshot().tracks.items()
        for tid, t in zip(table.track_id.tolist(), table.truth_id.tolist(), strict=True)
    }


def test_one_system_track_per_aircraft(run: tuple[Engine, Truth]) -> None:
    engine, _ = run
    body = engine.snapshot().system_tracks("confirmed")
    SystemTrackBatch.model_validate(body)
    truth = labels(engine)
    tracks = body["system_tracks"]
    ids = [s["system_track_id"] for s in tracks]
    assert len(set(ids)) == len(ids)
    aircraft: Counter[str] = Counter()
    pure = 0
    for s in tracks:
        sources = [m["radar_id"] for m in s["members"]]
        assert len(set(sources)) == len(sources)  # at most one track per radar
        names = {truth[(m["radar_id"], m["track_id"])] for m in s["members"]}
        pure += len(names) == 1 and None not in names
        aircraft.update(n for n in names if n is not None)
    seen = {t for (rid, tid), t in truth.items() if t is not None}  # aircraft with a radar track
    assert pure >= 0.99 * len(tracks)
    assert sum(n > 1 for n in aircraft.values()) <= 0.05 * len(aircraft)  # duplicates
    assert len(aircraft) >= 0.97 * len(seen)  # coverage
    assert sum(len(s["members"]) == 3 for s in tracks) >= 0.8 * len(tracks)


def test_the_fused_state_is_bias_compensated(run: tuple[Engine, Truth]) -> None:
    """RMS position error of the system tracks against that of their raw member tracks
    (which carry the radars' biases), at the system tracks' time."""
    engine, truth_pos = run
    snap = engine.snapshot()
    body = snap.system_tracks("confirmed")
    when = body["time_s"]
    names = labels(engine)
    fused, raw = [], []
    for s in body["system_tracks"]:
        label = {names[(m["radar_id"], m["track_id"])] for m in s["members"]}
        if len(label) != 1 or None in label:
            continue
        icao = identity_of(label.pop())[1]
        k, frac = int(np.floor(when)), when - np.floor(when)
        a = truth_pos[(icao, k)]  # (the last picture is at the input's end: no second after it)
        true = a if frac == 0 else a + (truth_pos[(icao, k + 1)] - a) * frac
        fused.append(np.linalg.norm(np.array(s["position_ecef_m"]) - true))
        for m in s["members"]:
            table = snap.tracks[m["radar_id"]][1]
            i = int(np.flatnonzero(table.track_id == m["track_id"])[0])
            dt = np.array([when - table.time_s[i]])
            pos, _, _ = predict_states(
                table.position_ecef_m[i : i + 1],
                table.velocity_ecef_mps[i : i + 1],
                table.covariance[i : i + 1],
                dt,
                1.0,
            )
            raw.append(np.linalg.norm(pos[0] - true))
    assert len(fused) > 50
    rms = float(np.sqrt(np.mean(np.square(fused))))
    assert rms <= 0.5 * float(np.sqrt(np.mean(np.square(raw))))


def test_system_tracks_over_zenoh_and_http(router: str, client: zenoh.Session) -> None:
    stream, _ = three_radar(90.0)
    with running_service(router) as svc:
        received: list[Any] = []
        sub = client.declare_subscriber(
            "fusion/system/tracks", lambda s: received.append(s.payload.to_bytes())
        )
        try:
            wait_subscribed(client, "fusion/radar/A/plots")
            for key, payload in stream:
                put_json(client, key, payload)
            got = wait_for(
                lambda: (b := svc.http.get("/system-tracks").json())["system_tracks"] and b, timeout=60
            )
            SystemTrackBatch.model_validate(got)
            assert all(s["status"] == "confirmed" for s in got["system_tracks"])
            everything = svc.http.get("/system-tracks", params={"status": "all"}).json()
            assert len(everything["system_tracks"]) >= len(got["system_tracks"])
            replies = list(client.get("fusion/system/tracks"))
            body = json.loads(replies[0].ok.payload.to_bytes())
            SystemTrackBatch.model_validate(body)
            # an unknown status is answered with an error reply, which quotes it only in part
            for asked in ("bogus", "x" * 3000, ""):  # (empty: as GET /system-tracks?status= , 422)
                (reply,) = list(client.get(f"fusion/system/tracks?status={asked}"))
                assert reply.err is not None
                said = reply.err.payload.to_string()
                assert "expected one of confirmed, tentative, all" in said and len(said) < 200
            wait_for(lambda: received, timeout=10)
            SystemTrackBatch.model_validate_json(received[-1])
        finally:
            sub.undeclare()


def test_the_picture_at_the_end_of_the_input_never_steps_back_in_data_time() -> None:
    """The pictures go forward in data time, and the one drawn at the end of the input (a
    replay's end, a stop) is of the last release: not of the last pair update, before it."""
    stream, _ = three_radar(61.0)
    _, out = run_engine(stream)
    times = [json.loads(o.payload)["time_s"] for o in out if o.key == "fusion/system/tracks"]
    last_batch = max(json.loads(p)["time_s"] for k, p in stream if k.endswith("/plots"))
    assert len(times) > 10 and times == sorted(times)
    assert times[-1] == last_batch
