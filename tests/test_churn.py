"""Sources that come and go cost nothing once forgotten (service/pipeline/sequencer.py
``forget_after_s``): memory stays flat under radar-id churn."""

from __future__ import annotations

import json
from dataclasses import replace
from typing import Any

import pytest
import zenoh

from service.engine import Engine, EngineConfig
from service.pipeline.sequencer import SequencerParams
from service.transport import node as node_module
from tests.scenario_helpers import scenario_messages
from tests.support import put_json, running_service, wait_for, wait_subscribed

Stream = list[tuple[str, bytes]]

PARAMS = SequencerParams(source_expiry_s=20.0, forget_after_s=30.0, max_lag_s=10.0)


def held_for(engine: Engine, source_id: str) -> dict[str, Any]:
    """What the engine still holds of a source, stage by stage."""
    stage = engine.correlation.stage  # type: ignore[attr-defined]  (in-process correlation)
    radar = engine.tracking.tracked.get(source_id)
    return {
        "correlators": sorted(k for k in stage.pair_correlators if source_id in k),
        "views": sorted(k for k in engine.publication.views if source_id in k),
        "table": source_id in engine.publication.tables and len(engine.publication.tables[source_id][1]) > 0,
        "tracks": 0 if radar is None else len(radar.table),
        "window": 0 if radar is None or radar.tracker is None else radar.tracker.window_plots,
    }


def test_a_radar_silent_past_its_forget_time_leaves_nothing_and_comes_back_cleanly() -> None:
    stream = scenario_messages("three-radar", duration_s=200.0)
    t0 = min(json.loads(p)["time_s"] for k, p in stream if k.endswith("/plots"))
    engine = Engine(EngineConfig(sequencer=PARAMS))
    ids_before: set[str] = set()
    checked = False
    for key, payload in stream:
        t = json.loads(payload).get("time_s", t0)
        if key == "fusion/radar/C/plots" and t0 + 60 < t < t0 + 150:
            continue  # C silent for 90 s: expired after 20, forgotten 30 later
        if not checked and t > t0 + 140:
            checked = True
            assert engine.sequencer.sources["C"].expired
            assert held_for(engine, "C") == {
                "correlators": [],
                "views": [],
                "table": False,
                "tracks": 0,
                "window": 0,
            }
            assert "C" in engine.tracking.tracked  # its site stays: it may come back without one
            assert held_for(engine, "A")["correlators"] == [("A", "B")]
        engine.ingest(key, payload)
        if key == "fusion/radar/C/plots" and t <= t0 + 60:
            ids_before |= {tr["track_id"] for tr in _tracks(engine, "C")}
    engine.flush()
    assert checked and ids_before
    # back: tracked and paired again, with track ids never given before
    after = {tr["track_id"] for tr in _tracks(engine, "C")}
    assert after and not after & ids_before
    assert {k for k in engine.correlation.stage.pair_correlators if "C" in k} == {("A", "C"), ("B", "C")}  # type: ignore[attr-defined]
    c_pairs = [
        ps for ps in engine.snapshot().pair_sets(status="confirmed") if "C" in (ps["radar_a"], ps["radar_b"])
    ]
    assert any(ps["pairs"] for ps in c_pairs)


def _tracks(engine: Engine, radar: str) -> list[dict[str, Any]]:
    return [t for b in engine.snapshot().track_batches("all") if b["radar_id"] == radar for t in b["tracks"]]


def test_radar_ids_that_come_and_go_do_not_grow_what_the_engine_holds() -> None:
    """Thirty radar ids, each live for a while then retired (new ids replace them), over a long
    stream: the correlators, pair views and tables held stay those of the live radars."""
    base = scenario_messages("two-radar", duration_s=400.0)
    site = json.loads(next(p for k, p in base if k == "fusion/radar/B/site"))
    t0 = min(json.loads(p)["time_s"] for k, p in base if k.endswith("/plots"))
    stream: Stream = []
    for key, payload in base:
        if key == "fusion/radar/B/plots":
            body = json.loads(payload)
            generation = int((body["time_s"] - t0) // 40)  # B's batches under a new id every 40 s
            rid = f"B{generation}"
            if body["seq"] == 1 or (body["time_s"] - t0) % 40 < 0.3:
                stream.append((f"fusion/radar/{rid}/site", json.dumps({**site, "radar_id": rid}).encode()))
            stream.append((f"fusion/radar/{rid}/plots", json.dumps({**body, "radar_id": rid}).encode()))
        elif key != "fusion/radar/B/site":
            stream.append((key, payload))
    engine = Engine(EngineConfig(sequencer=replace(PARAMS, max_lag_s=30.0)))
    most = 0
    for key, payload in stream:
        engine.ingest(key, payload)
        stage = engine.correlation.stage  # type: ignore[attr-defined]
        most = max(
            most, len(stage.pair_correlators), len(engine.publication.views), len(engine.publication.tables)
        )
    engine.flush()
    retired = {sid for sid, s in engine.sequencer.sources.items() if s.expired}
    assert len(retired) >= 6
    # a new id lives 40 s, expires 20 s after, is forgotten 30 s later: at most three B ids held
    assert most <= 4


def test_the_output_publishers_are_bounded(
    router: str, client: zenoh.Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Output keys come and go with radar ids: the node holds at most MAX_PUBLISHERS publishers
    (the least recently used goes), and every output still reaches a subscriber."""
    monkeypatch.setattr(node_module, "MAX_PUBLISHERS", 3)
    stream = scenario_messages("three-radar", duration_s=40.0)
    got: list[str] = []
    sub = client.declare_subscriber("fusion/radar/*/tracks", lambda s: got.append(str(s.key_expr)))
    try:
        with running_service(router) as svc:
            wait_subscribed(client, "fusion/radar/A/plots")
            for key, payload in stream:
                put_json(client, key, payload)
            n = sum(k.endswith("/plots") for k, _ in stream)
            wait_for(lambda: sum(r["batches"] for r in svc.http.get("/status").json()["radars"]) == n)
            wait_for(lambda: {k.split("/")[2] for k in got} == {"A", "B", "C"})
            assert len(svc.node._publishers) <= 3
    finally:
        sub.undeclare()
