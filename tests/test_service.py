"""The running service in-process: real Zenoh (router + clients) and real HTTP."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import zenoh

from service.engine import Engine, EngineConfig
from service.settings import Settings
from tests.scenario_helpers import scenario_messages
from tests.support import put_json, running_service, wait_for, wait_subscribed


def _radar(status: dict[str, Any], rid: str) -> dict[str, Any]:
    return next(r for r in status["radars"] if r["radar_id"] == rid)


def test_ingest_over_zenoh_reported_by_http_queryables_and_metrics(
    router: str, client: zenoh.Session
) -> None:
    stream = scenario_messages("two-radar", duration_s=40.0)
    errors: list[dict[str, Any]] = []
    tracks_seen: set[str] = set()
    sub_err = client.declare_subscriber(
        "fusion/errors", lambda s: errors.append(json.loads(s.payload.to_bytes()))
    )
    sub_trk = client.declare_subscriber("fusion/radar/*/tracks", lambda s: tracks_seen.add(str(s.key_expr)))
    with running_service(router) as svc:
        assert svc.http.get("/healthz").json() == {"status": "ok"}
        assert svc.http.get("/readyz").json() == {"status": "ready"}
        wait_subscribed(client, "fusion/radar/A/plots")
        wait_subscribed(client, "fusion/radar/A/site")
        for key, payload in stream:
            put_json(client, key, payload)
        n_plots = sum(len(json.loads(p)["plots"]["time_s"]) for k, p in stream if k.endswith("/plots"))
        n_batches = sum(k.endswith("/plots") for k, _ in stream)

        def all_in() -> bool:
            st = svc.http.get("/status").json()
            return sum(r["batches"] for r in st["radars"]) == n_batches

        wait_for(all_in, timeout=30)
        status = svc.http.get("/status").json()
        assert sum(r["plots"] for r in status["radars"]) == n_plots
        assert status["prefix"] == "fusion" and status["method"] == "svd-topology"
        assert status["queue"]["dropped"] == 0
        assert _radar(status, "A")["tracks_confirmed"] > 0

        # the status queryable answers the same counters
        replies = list(client.get("fusion/status"))
        assert len(replies) == 1 and replies[0].ok is not None
        q_status = json.loads(replies[0].ok.payload.to_bytes())
        assert _radar(q_status, "A")["plots"] == _radar(status, "A")["plots"]

        radars = svc.http.get("/radars").json()
        assert [r["radar_id"] for r in radars] == ["A", "B"]
        assert radars[0]["latitude_deg"] == 31.2 and radars[0]["batches"] > 0

        trk = svc.http.get("/radars/A/tracks").json()
        assert trk["radar_id"] == "A" and trk["tracks"]
        assert all(t["status"] == "confirmed" for t in trk["tracks"])
        assert svc.http.get("/radars/A/tracks", params={"status": "all"}).status_code == 200
        assert svc.http.get("/radars/nope/tracks").status_code == 404
        assert svc.http.get("/radars/A/tracks", params={"status": "bogus"}).status_code == 422
        wait_for(lambda: {"fusion/radar/A/tracks", "fusion/radar/B/tracks"} <= tracks_seen)

        pairs = svc.http.get("/pairs", params={"radar_a": "B", "radar_b": "A", "status": "all"}).json()
        assert [(p["radar_a"], p["radar_b"]) for p in pairs] == [("A", "B")]
        only_a = svc.http.get("/pairs", params={"radar_a": "A", "status": "all"}).json()
        assert [(p["radar_a"], p["radar_b"]) for p in only_a] == [("A", "B")]
        # a radar with itself is no pair set, even though each pair set with A names A
        assert svc.http.get("/pairs", params={"radar_a": "A", "radar_b": "A", "status": "all"}).json() == []
        replies = list(client.get("fusion/pairs/**"))
        assert [str(r.ok.key_expr) for r in replies if r.ok] == ["fusion/pairs/A/B"]
        assert isinstance(svc.http.get("/biases").json(), list)

        metrics = svc.http.get("/metrics").text
        assert f'topofusion_plots_total{{radar="A"}} {float(_radar(status, "A")["plots"])}' in metrics
        assert "topofusion_queue_dropped_total 0.0" in metrics

        # a hostile message between valid ones: rejected, published, counted; nothing lost
        put_json(client, "fusion/radar/A/plots", b"{oops")
        wait_for(lambda: errors)
        assert errors[0]["reason"] == "malformed_json" and errors[0]["radar_id"] == "A"
        wait_for(lambda: svc.http.get("/status").json()["rejected"] == {"malformed_json": 1})
        assert 'topofusion_rejected_total{reason="malformed_json"} 1.0' in svc.http.get("/metrics").text
    sub_err.undeclare()
    sub_trk.undeclare()


def test_a_radar_known_by_its_site_alone_answers_an_empty_track_batch(
    router: str, client: zenoh.Session
) -> None:
    """Contract: ``GET /radars/{id}/tracks`` is 404 for an unknown radar only.  A radar whose
    site came but no table yet (no batch, or its batches waiting in the sequencer for the
    other sources' clocks) is known: 200, no tracks."""
    stream = scenario_messages("two-radar", duration_s=10.0)
    site_key, site = next((k, p) for k, p in stream if k == "fusion/radar/A/site")
    with running_service(router) as svc:
        wait_subscribed(client, site_key)
        put_json(client, site_key, site)
        wait_for(lambda: [r["radar_id"] for r in svc.http.get("/radars").json()] == ["A"])
        for status in ("confirmed", "all"):
            got = svc.http.get("/radars/A/tracks", params={"status": status})
            assert got.status_code == 200, got.text
            assert got.json()["radar_id"] == "A" and got.json()["tracks"] == []
        assert svc.http.get("/radars/B/tracks").status_code == 404


def test_lifespan_opens_and_closes_the_node(router: str) -> None:
    with running_service(router, EngineConfig(prefix="other")) as svc:
        node = svc.node
        assert node.ready
        assert svc.http.get("/status").json()["prefix"] == "other"
    assert not node.ready  # session closed and worker joined by the lifespan's shutdown


def test_the_node_of_the_settings_runs_as_they_say(
    router: str, client: zenoh.Session, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``ServiceNode.from_settings``, as the command builds it: a config file (an engine
    parameter and node settings), an engine variable and the flags.  ``/status`` says what is
    in force, and the outputs are those of an engine of the same configuration."""
    config = tmp_path / "topofusion.yaml"
    config.write_text("method: nearest\nqueue_size: 300\ncorrelation_process: false\n")
    monkeypatch.setenv("TOPOFUSION_ENGINE__CADENCE__CADENCE_SCANS", "2")
    settings = Settings.load(config, {"zenoh_mode": "client", "zenoh_connect": [router], "prefix": None})
    assert settings.engine.method == "nearest" and settings.engine.cadence.cadence_scans == 2
    stream = scenario_messages("two-radar", duration_s=40.0)
    n_batches = sum(k.endswith("/plots") for k, _ in stream)
    with running_service(router, settings=settings) as svc:
        wait_subscribed(client, "fusion/radar/A/plots")
        for key, payload in stream:
            put_json(client, key, payload)
        wait_for(lambda: sum(r["batches"] for r in svc.http.get("/status").json()["radars"]) == n_batches)
        status = svc.http.get("/status").json()
        assert status["method"] == "nearest" and status["queue"]["capacity"] == 300
        assert status["zenoh"] == {"mode": "client", "listen": [], "connect": [router]}
        node = svc.node
    reference = Engine(settings.engine)
    for key, payload in stream:
        reference.ingest(key, payload)
    reference.flush()
    snap, ref = node.engine.snapshot(), reference.snapshot()
    assert snap.track_batches("all") == ref.track_batches("all")
    assert snap.pair_sets(status="all") == ref.pair_sets(status="all")


def test_workers_partitioned_by_radar_answer_together(router: str, client: zenoh.Session) -> None:
    """Two workers own disjoint radars; `get pairs/**` and `get status` gather both."""
    stream = scenario_messages("three-radar", duration_s=30.0, targets=20)
    with running_service(router, radars=("A", "B")) as w1, running_service(router, radars=("C",)) as w2:
        for rid in ("A", "C"):
            wait_subscribed(client, f"fusion/radar/{rid}/plots")
        for key, payload in stream:
            put_json(client, key, payload)
        n = {rid: sum(k == f"fusion/radar/{rid}/plots" for k, _ in stream) for rid in "ABC"}

        def done() -> bool:
            s1, s2 = w1.http.get("/status").json(), w2.http.get("/status").json()
            got1 = {r["radar_id"]: r["batches"] for r in s1["radars"]}
            got2 = {r["radar_id"]: r["batches"] for r in s2["radars"]}
            return got1 == {"A": n["A"], "B": n["B"]} and got2 == {"C": n["C"]}

        wait_for(done, timeout=60)
        wait_for(lambda: w1.http.get("/pairs", params={"status": "all"}).json())
        assert w2.http.get("/pairs", params={"status": "all"}).json() == []
        # every worker answers when the query targets all queryables, unconsolidated
        everyone = {"target": zenoh.QueryTarget.ALL, "consolidation": zenoh.ConsolidationMode.NONE}
        replies = [r.ok for r in client.get("fusion/pairs/**", **everyone) if r.ok is not None]
        assert [str(r.key_expr) for r in replies] == ["fusion/pairs/A/B"]
        statuses = [
            json.loads(r.ok.payload.to_bytes()) for r in client.get("fusion/status", **everyone) if r.ok
        ]
        owned = sorted(tuple(x["radar_id"] for x in s["radars"]) for s in statuses)
        assert owned == [("A", "B"), ("C",)]


def test_hostile_but_valid_input_over_zenoh_costs_the_honest_radars_nothing(
    router: str, client: zenoh.Session
) -> None:
    """Through the public interface: a batch 10^9 s ahead, an absurd seq, 50 fake radar ids and
    a site re-sent 0.1 m away after every batch.  Each is rejected or absorbed, the service stays
    ready, and the honest radars' tracks and pairs are those of the clean stream."""
    from service.engine import Engine

    stream = scenario_messages("two-radar", duration_s=60.0)
    plots_a = [json.loads(p) for k, p in stream if k == "fusion/radar/A/plots"]
    site_b = json.loads(next(p for k, p in stream if k == "fusion/radar/B/site"))
    site_a = json.loads(next(p for k, p in stream if k == "fusion/radar/A/site"))
    b5 = plots_a[5]
    future = {**b5, "seq": b5["seq"] + 1, "time_s": b5["time_s"] + 1e9}
    future["plots"] = {**b5["plots"], "time_s": [b5["time_s"] + 1e9] * len(b5["plots"]["time_s"])}
    hostile: list[tuple[str, bytes]] = [
        ("fusion/radar/A/plots", json.dumps(future).encode()),
        ("fusion/radar/A/plots", json.dumps({**b5, "seq": b5["seq"] + 10**9}).encode()),
    ]
    for n in range(50):
        rid = f"X{n}"
        hostile.append((f"fusion/radar/{rid}/site", json.dumps({**site_a, "radar_id": rid}).encode()))
        small = {k: v[:5] for k, v in b5["plots"].items()}
        body = {"radar_id": rid, "seq": 1, "time_s": b5["time_s"], "plots": small}
        hostile.append((f"fusion/radar/{rid}/plots", json.dumps(body).encode()))
    mixed: list[tuple[str, bytes]] = []
    for key, payload in stream:
        mixed.append((key, payload))
        if key == "fusion/radar/A/plots" and json.loads(payload)["seq"] == b5["seq"]:
            mixed.extend(hostile)
        if key.endswith("/plots"):
            jitter = {**site_b, "latitude_deg": site_b["latitude_deg"] + 1e-6 * (len(mixed) % 2)}
            mixed.append(("fusion/radar/B/site", json.dumps(jitter).encode()))
    clean = Engine()
    for key, payload in stream:
        clean.ingest(key, payload)
    clean.flush()
    n_batches = sum(k.endswith("/plots") for k, _ in mixed) - 2  # all but the two rejected

    with running_service(router) as svc:
        wait_subscribed(client, "fusion/radar/A/plots")
        for key, payload in mixed:
            put_json(client, key, payload)

        def all_in() -> bool:
            st = svc.http.get("/status").json()
            return sum(r["batches"] for r in st["radars"]) == n_batches

        wait_for(all_in, timeout=60)
        assert svc.http.get("/readyz").status_code == 200
        status = svc.http.get("/status").json()
        assert status["rejected"] == {"out_of_range": 2}
        node = svc.node
    # stopped: the node flushed what it held; compare with the clean stream in one engine
    snap, ref = node.engine.snapshot(), clean.snapshot()
    honest = {"A", "B"}
    assert [b for b in snap.track_batches("all") if b["radar_id"] in honest] == ref.track_batches("all")
    got = [ps for ps in snap.pair_sets(status="all") if {ps["radar_a"], ps["radar_b"]} <= honest]
    assert got == ref.pair_sets(status="all") and got[0]["pairs"]
    assert {(v.radar_a, v.radar_b) for v in snap.pair_views} == {("A", "B")}  # fakes never paired
