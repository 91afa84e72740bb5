"""``GET /radars/{radar_id}/performance`` and ``get {prefix}/radar/{radar_id}/performance``
through the running service: real Zenoh (router + client) and real HTTP (contract §5.3)."""

from __future__ import annotations

import json

import pytest
import zenoh

from service.wire.models import RadarPerformance
from tests.scenario_helpers import scenario_messages
from tests.support import put_json, running_service, wait_for, wait_subscribed


def test_the_route_the_queryable_and_the_metrics_answer_each_radar_s_performance(
    router: str, client: zenoh.Session
) -> None:
    lab = pytest.importorskip("topofusion_lab.scenarios.simulator")
    stream = scenario_messages(
        "two-radar", duration_s=90.0, targets=20, adsb=(lab.AdsbSpec("ads-b", identity=True),)
    )
    with running_service(router) as svc:
        assert svc.http.get("/radars/A/performance").status_code == 404  # no site yet
        wait_subscribed(client, "fusion/radar/A/plots")
        wait_subscribed(client, "fusion/adsb/ads-b/reports")
        for key, payload in stream:
            put_json(client, key, payload)

        def assessed() -> bool:
            body = svc.http.get("/radars/A/performance").json()
            return body.get("position", {}).get("plots", 0) > 50

        wait_for(assessed, timeout=60)
        body = svc.http.get("/radars/A/performance").json()
        got = RadarPerformance.model_validate(body)
        assert got.radar_id == "A" and got.references == ["ads-b"] and got.window_s == 600.0
        assert got.detection.pd is not None and 0.8 < got.detection.pd <= 1.0
        assert got.position.range_rms_m is not None and 100.0 < got.position.range_rms_m < 300.0
        assert got.requirements.pd_min == 0.97
        assert svc.http.get("/radars/nope/performance").status_code == 404

        replies = [r.ok for r in client.get("fusion/radar/*/performance") if r.ok is not None]
        keys = sorted(str(r.key_expr) for r in replies)
        assert keys == ["fusion/radar/A/performance", "fusion/radar/B/performance"]
        one = [r.ok for r in client.get("fusion/radar/B/performance") if r.ok is not None]
        assert len(one) == 1 and json.loads(one[0].payload.to_bytes())["radar_id"] == "B"

        metrics = svc.http.get("/metrics").text
        assert 'topofusion_performance_pd{radar="A"}' in metrics
        assert 'topofusion_performance_position_rms_m{radar="B"}' in metrics
