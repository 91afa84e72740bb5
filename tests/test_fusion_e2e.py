"""End to end through Zenoh: a biased two-radar stream in, correct tracks, pairs and biases out.

The simulator's ``truth_id`` (carried to the tracks) is read here, by the evaluation only.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import zenoh

from tests.scenario_helpers import scenario_messages
from tests.support import put_json, running_service, wait_for, wait_subscribed
from topofusion_lab.scenarios.catalog import get_scenario


def test_large_bias_stream_gives_right_tracks_pairs_and_biases(router: str, client: zenoh.Session) -> None:
    scenario = get_scenario("large-bias")  # 1 km / 1 deg and -800 m / -0.8 deg: nearest neighbour fails here
    stream = scenario_messages("large-bias", duration_s=150.0, seed=5)
    n_batches = sum(k.endswith("/plots") for k, _ in stream)
    with running_service(router) as svc:
        wait_subscribed(client, "fusion/radar/A/plots")
        for key, payload in stream:
            put_json(client, key, payload)
        wait_for(
            lambda: sum(r["batches"] for r in svc.http.get("/status").json()["radars"]) == n_batches,
            timeout=120,
        )
        tracks: dict[str, dict[str, Any]] = {
            rid: {t["track_id"]: t for t in svc.http.get(f"/radars/{rid}/tracks").json()["tracks"]}
            for rid in ("A", "B")
        }
        pairs = svc.http.get("/pairs", params={"radar_a": "A", "radar_b": "B"}).json()[0]["pairs"]
        biases = {b["radar_id"]: b for b in svc.http.get("/biases").json()}

    for rid, by_id in tracks.items():
        truths = Counter(t["truth_id"] for t in by_id.values())
        assert len(by_id) >= 30, f"radar {rid}: only {len(by_id)} confirmed tracks of 40 aircraft"
        assert truths[None] == 0, f"radar {rid}: confirmed tracks on clutter"
        assert max(truths.values()) == 1, f"radar {rid}: duplicate tracks"

    common = set(t["truth_id"] for t in tracks["A"].values()) & set(
        t["truth_id"] for t in tracks["B"].values()
    )
    right = [
        p for p in pairs if tracks["A"][p["track_a"]]["truth_id"] == tracks["B"][p["track_b"]]["truth_id"]
    ]
    assert len(right) >= 0.9 * len(common), f"{len(right)} right pairs of {len(common)} common targets"
    assert len(pairs) - len(right) <= 0.02 * len(pairs), "false pairs"
    assert len({p["track_a"] for p in pairs}) == len(pairs) == len({p["track_b"] for p in pairs})

    for spec in scenario.radars:
        est = biases[spec.radar_id]
        assert abs(est["range_bias_m"] - spec.range_bias_m) <= 0.1 * abs(spec.range_bias_m), est
        assert abs(est["azimuth_bias_deg"] - spec.azimuth_bias_deg) <= 0.1 * abs(spec.azimuth_bias_deg), est
