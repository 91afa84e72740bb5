"""A simulated two-radar scenario with ADS-B, encoded to CAT048/034/021 and streamed over UDP
through `topofusion asterix` into the real service, gives the tracks, pairs and biases its
JSON input gives (at the resolution ASTERIX carries), pair for pair; it crosses midnight."""

from __future__ import annotations

import datetime as dt
import json
import signal
import socket
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from service.engine import Engine, EngineConfig
from service.wire.keys import Keys
from tests.asterix.test_asterix_service import bridge, output, wait_listening
from tests.support import free_port, running_service, wait_for
from topofusion_lab.asterix_scenario import asterix_datagrams, at_asterix_resolution
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import AdsbSpec, Scenario, SimMessage, generate

MIDNIGHT = 1_764_028_800.0  # 2025-11-25T00:00:00Z
assert MIDNIGHT % 86_400 == 0


def scenario() -> Scenario:
    base = get_scenario("two-radar")
    radars = tuple(
        replace(r, two_d=True, identity=True, sac=25, sic=10 + i, clutter_per_scan=4.0)
        for i, r in enumerate(base.radars)
    )
    return replace(
        base,
        radars=radars,
        targets=40,
        duration_s=200.0,
        start_time_s=MIDNIGHT - 100.0,  # midnight half-way through
        adsb=(AdsbSpec("adsb", batch_period_s=2.0, stride=2, no_height=0.1),),
    )


def run_offline(sc: Scenario, messages: list[tuple[str, bytes]]) -> Engine:
    engine = Engine(EngineConfig(sites=tuple(r.wire_site() for r in sc.radars)))
    for key, payload in messages:
        assert engine.ingest(key, payload, receive_time_s=0.0) is not None
    return engine  # not flushed: the live service holds what its watermark holds too


def json_messages(sim: list[SimMessage], rounded: bool) -> list[tuple[str, bytes]]:
    keys = Keys("fusion")
    out = []
    for m in sim:
        body = at_asterix_resolution(m.kind, m.body) if rounded else m.body
        if rounded and m.kind == "plots":
            assert "truth_id" not in body["plots"]
        out.append((keys.input(m.kind, m.radar_id), json.dumps(body).encode()))
    return out


def comparable_tracks(batch: dict[str, Any]) -> list[dict[str, Any]]:
    return [{k: v for k, v in t.items() if k != "truth_id"} for t in batch["tracks"]]


def assert_close(live: Any, offline: Any, path: str = "") -> None:
    if isinstance(live, dict):
        assert live.keys() == offline.keys(), path
        for k in live:
            assert_close(live[k], offline[k], f"{path}.{k}")
    elif isinstance(live, list):
        assert len(live) == len(offline), path
        for i, (a, b) in enumerate(zip(live, offline, strict=True)):
            assert_close(a, b, f"{path}[{i}]")
    elif isinstance(live, float):
        assert live == pytest.approx(offline, rel=1e-9, abs=1e-6), path
    else:
        assert live == offline, path


def pair_ids(pair_sets: list[dict[str, Any]]) -> set[tuple[str, str, str, str, str]]:
    return {
        (ps["radar_a"], ps["radar_b"], p["track_a"], p["track_b"], p["status"])
        for ps in pair_sets
        for p in ps["pairs"]
    }


@pytest.mark.slow
def test_a_scenario_through_asterix_over_udp_equals_its_json_input(router: str, tmp_path: Path) -> None:
    sc = scenario()
    sim = list(generate(sc, seed=4))
    sac_sic = {r.radar_id: (r.sac, r.sic) for r in sc.radars}
    datagrams = list(asterix_datagrams(sim, sac_sic))  # type: ignore[arg-type]
    offline = run_offline(sc, json_messages(sim, rounded=True)).snapshot()
    batches = {
        r.radar_id: sum(m.kind == "plots" and m.radar_id == r.radar_id for m in sim) for r in sc.radars
    }

    sites = tmp_path / "sites.json"
    sites.write_text(json.dumps([r.wire_site().model_dump(exclude_none=True) for r in sc.radars]))
    port = free_port()
    date = dt.datetime.fromtimestamp(sc.start_time_s, dt.timezone.utc).date().isoformat()
    config = EngineConfig(sites=tuple(r.wire_site() for r in sc.radars))
    with running_service(router, config, correlation_process=False) as svc:
        args = ["--udp", f"127.0.0.1:{port}", "--sites", str(sites), "--connect", router]
        args += ["--date", date, "--adsb-batch", "2"]
        with bridge(args) as (proc, lines):
            seen = wait_listening(proc, lines)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
                for i, d in enumerate(datagrams):
                    tx.sendto(d, ("127.0.0.1", port))
                    if i % 20 == 19:
                        time.sleep(0.005)  # a feed's pace, not a burst into the socket buffer

            def all_batches() -> bool:
                st = svc.http.get("/status").json()
                return {r["radar_id"]: r["batches"] for r in st["radars"]} == batches

            wait_for(all_batches, timeout=60)
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=30) == 0
            text = "".join(seen) + output(lines)
        assert "left out: nothing" in text, text
        wait_for(
            lambda: svc.node.snapshot.correlation["updates"] >= offline.correlation["updates"], timeout=30
        )
        time.sleep(0.5)  # the last ADS-B batch (sent on stop) reaches the service
        live = svc.node.snapshot
        assert live.status()["rejected"] == {}
        for r in sc.radars:
            lt, ot = live.track_batch(r.radar_id, "all"), offline.track_batch(r.radar_id, "all")
            assert lt is not None and ot is not None
            assert_close(comparable_tracks(lt), comparable_tracks(ot), r.radar_id)
        assert_close(live.pair_sets(status="all"), offline.pair_sets(status="all"))
        assert_close(live.biases(), offline.biases())
    # the scenario is worth the comparison: radar-radar and radar-ADS-B pairs across midnight
    confirmed = pair_ids(offline.pair_sets(status="confirmed"))
    assert {(a, b) for a, b, *_ in confirmed} == {("A", "B"), ("A", "adsb"), ("B", "adsb")}
    assert len(confirmed) > 40
    assert max(ps["time_s"] for ps in offline.pair_sets()) > MIDNIGHT + 60
    # and at full precision the JSON input pairs the same tracks
    full = run_offline(sc, json_messages(sim, rounded=False)).snapshot()
    assert pair_ids(full.pair_sets(status="confirmed")) == confirmed
