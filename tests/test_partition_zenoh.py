"""Partitioned workers on a real Zenoh router: two workers give one worker's results.

One worker runs on prefix ``one``, workers 1/2 and 2/2 on prefix ``two``; a client puts the
same stream under both prefixes (also with the aid of association on).  Each pair's PairSet
updates on ``two`` are those on ``one`` (the newest may still be held back at the end of the
input), including the pairs whose two radars the two workers track; the joint bias estimate is
one the single worker made, and every worker serves it; worker 1 draws the system tracks the
single worker draws, and both serve them; ``/status``, ``/pairs`` and ``get {prefix}/...``
describe the whole network.
"""

from __future__ import annotations

import contextlib
import itertools
import subprocess
import threading
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import orjson
import pytest
import zenoh

from service.engine import EngineConfig
from service.pipeline.partition import Partition
from service.transport.node import ServiceNode
from service.transport.session import ZenohOptions
from tests.doc_commands import PROCESS_S, TOPOFUSION, environment
from tests.scenario_helpers import scenario_messages
from tests.support import (
    RunningService,
    put_json,
    running_service,
    wait_for,
    wait_subscribed,
)
from tests.test_examples_asterix import CAPTURE, SITES, assert_cat062_written


class Collector:
    """Every sample under a key expression, in arrival order, by key."""

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self.by_key: dict[str, list[bytes]] = defaultdict(list)
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key_expr, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.by_key[str(sample.key_expr)].append(sample.payload.to_bytes())

    def snapshot(self) -> dict[str, list[bytes]]:
        with self._lock:
            return {k: list(v) for k, v in self.by_key.items()}

    def close(self) -> None:
        self._sub.undeclare()


@contextlib.contextmanager
def network(
    router: str, config: EngineConfig | None = None
) -> Iterator[tuple[RunningService, RunningService, RunningService]]:
    base = config or EngineConfig()
    with (
        running_service(router, replace(base, prefix="one"), correlation_process=False) as one,
        running_service(
            router, replace(base, prefix="two", partition=Partition(1, 2)), correlation_process=False
        ) as w1,
        running_service(
            router, replace(base, prefix="two", partition=Partition(2, 2))
        ) as w2,  # its own process
    ):
        yield one, w1, w2


def _put_both(
    client: zenoh.Session, services: tuple[RunningService, ...], stream: list[tuple[str, bytes]]
) -> None:
    """The stream under both prefixes: the sites first, until every worker has them (then all
    hear the plots), then the rest."""
    for prefix in ("one", "two"):
        wait_subscribed(client, f"{prefix}/radar/A/plots")
    wait_for(lambda: not services[1].http.get("/status").json()["partition"]["missing"], timeout=15)
    sites = [(k, p) for k, p in stream if k.endswith("/site")]
    for key, payload in sites:
        for prefix in ("one", "two"):
            put_json(client, prefix + key.removeprefix("fusion"), payload)
    for svc in services:
        wait_for(lambda svc=svc: len(svc.http.get("/radars").json()) == len(sites), timeout=15)
    for key, payload in stream[len(sites) :]:
        for prefix in ("one", "two"):
            put_json(client, prefix + key.removeprefix("fusion"), payload)


def _same_updates(one_pairs: dict[str, list[bytes]], two_pairs: dict[str, list[bytes]]) -> None:
    """Every pair's updates on ``two`` are those on ``one`` (the newest may be held back)."""
    assert sorted(two_pairs) == [k.replace("one/", "two/", 1) for k in sorted(one_pairs)] and one_pairs
    for key, want in one_pairs.items():
        got = two_pairs[key.replace("one/", "two/", 1)]
        assert len(want) - 1 <= len(got) <= len(want), key
        assert got == want[: len(got)], key


def _batches(svc: RunningService) -> int:
    return sum(r["batches"] for r in svc.http.get("/status").json()["radars"])


def _settled(collectors: list[Collector]) -> Any:
    last: list[Any] = []

    def same_twice() -> bool:
        now = [{k: len(v) for k, v in c.snapshot().items()} for c in collectors]
        stable = now == last[-1:][0] if last else False
        last.append(now)
        return stable

    return same_twice


@pytest.mark.slow
def test_two_workers_give_the_results_of_one(router: str, client: zenoh.Session) -> None:
    stream = scenario_messages("three-radar", duration_s=150.0, seed=2)
    n_batches = sum(k.endswith("/plots") for k, _ in stream)
    pairs_one, pairs_two = Collector(client, "one/pairs/**"), Collector(client, "two/pairs/**")
    biases_two = Collector(client, "two/biases")
    system_one, system_two = Collector(client, "one/system/tracks"), Collector(client, "two/system/tracks")
    try:
        with network(router) as (one, w1, w2):
            _put_both(client, (one, w1, w2), stream)
            wait_for(lambda: _batches(one) == n_batches, timeout=120)
            wait_for(lambda: _batches(w1) == n_batches, timeout=120)  # w1's /status: the whole network
            wait_for(_settled([pairs_one, pairs_two, biases_two, system_two]), timeout=60, interval=1.0)

            one_pairs, two_pairs = pairs_one.snapshot(), pairs_two.snapshot()
            status = w1.http.get("/status").json()
            status2 = w2.http.get("/status").json()
            http_pairs = {
                w: s.http.get("/pairs", params={"status": "all"}).json() for w, s in (("1", w1), ("2", w2))
            }
            single_pairs = one.http.get("/pairs", params={"status": "all"}).json()
            single_biases = one.http.get("/biases").json()
            worker_biases = [w1.http.get("/biases").json(), w2.http.get("/biases").json()]
            gathered = {str(r.ok.key_expr) for r in client.get("two/pairs/**") if r.ok is not None}
            zstatus = [orjson.loads(r.ok.payload.to_bytes()) for r in client.get("two/status") if r.ok]
            published = [orjson.loads(b)["biases"] for b in biases_two.snapshot()["two/biases"]]
            pictures = [w.http.get("/system-tracks", params={"status": "all"}).json() for w in (w1, w2)]
            zpicture = [
                orjson.loads(r.ok.payload.to_bytes()) for r in client.get("two/system/tracks") if r.ok
            ]
            drawn_one: dict[float, Any] = {}  # as drawn: the first of each time (then held)
            for body in map(orjson.loads, system_one.snapshot()["one/system/tracks"]):
                drawn_one.setdefault(body["time_s"], body)
            drawn_two = [orjson.loads(b) for b in system_two.snapshot()["two/system/tracks"]]
    finally:
        for c in (pairs_one, pairs_two, biases_two, system_one, system_two):
            c.close()

    # Pair updates: the same, update for update, each pair from one worker only.
    _same_updates(one_pairs, two_pairs)
    owner = Partition(1, 2).owner
    crossing = [k for k in one_pairs if len({owner(r) for r in k.split("/")[-2:]}) == 2]
    assert crossing, "no pair whose radars two workers track"
    # Every worker's HTTP port answers for the whole network.
    assert http_pairs["1"] == http_pairs["2"]
    assert [(p["radar_a"], p["radar_b"]) for p in http_pairs["1"]] == [
        (p["radar_a"], p["radar_b"]) for p in single_pairs
    ]
    assert gathered == set(two_pairs)
    assert (
        sorted(r["radar_id"] for r in status["radars"])
        == ["A", "B", "C"]
        == sorted(r["radar_id"] for r in status2["radars"])
    )
    assert status["partition"]["missing"] == [] and [w["alive"] for w in status["partition"]["workers"]] == [
        True,
        True,
    ]
    assert sorted(itertools.chain.from_iterable(w["radars"] for w in status["partition"]["workers"])) == [
        "A",
        "B",
        "C",
    ]
    assert len(zstatus) == 1 and sorted(r["radar_id"] for r in zstatus[0]["radars"]) == ["A", "B", "C"]
    # Biases: worker 1 solves; its estimate is one the single worker made, served by both.
    assert single_biases and single_biases in published[-2:]
    assert worker_biases[0] == worker_biases[1] == published[-1]
    # System tracks: worker 1 draws them (one answer to a get, served by both HTTP ports),
    # each picture the single worker's of the same data time.
    assert pictures[0] == pictures[1] and pictures[0]["system_tracks"]
    assert len(zpicture) == 1 and zpicture[0]["time_s"] == pictures[0]["time_s"]
    assert len(drawn_two) > 20
    for got in drawn_two:
        want = {t["system_track_id"]: t for t in drawn_one[got["time_s"]]["system_tracks"]}
        mine = {t["system_track_id"]: t for t in got["system_tracks"]}
        assert len(set(want) & set(mine)) >= 0.95 * len(want), got["time_s"]
        for sid in set(want) & set(mine):
            a, b = want[sid], mine[sid]
            assert (
                max(abs(x - y) for x, y in zip(a["position_ecef_m"], b["position_ecef_m"], strict=True))
                < 1e-3
            )
            members = {(m["radar_id"], m["track_id"]) for m in b["members"]}
            # a picture published later holds to the tables then: members may only have gone
            assert members <= {(m["radar_id"], m["track_id"]) for m in a["members"]}


@pytest.mark.slow
def test_two_workers_aid_their_tracks_as_one_worker_does(router: str, client: zenoh.Session) -> None:
    """With the aid of association (on by default; a formation among other traffic, where it
    decides associations), the workers exchange their pairs' registrations with their links and
    track at most its lag apart: every pair update is one worker's."""
    from topofusion_lab.evaluation import formation
    from topofusion_lab.scenarios.simulator import wire_messages

    point = next(p for p in formation.POINTS if p.label == "2x in traffic")
    stream = list(wire_messages(formation.scenario(point, 180.0, 12), 1))
    n_batches = sum(k.endswith("/plots") for k, _ in stream)
    config = EngineConfig()
    assert config.tracking.aid.enabled
    pairs_one, pairs_two = Collector(client, "one/pairs/**"), Collector(client, "two/pairs/**")
    try:
        with network(router, config) as (one, w1, w2):
            _put_both(client, (one, w1, w2), stream)
            wait_for(lambda: _batches(one) == n_batches, timeout=120)
            wait_for(lambda: _batches(w1) == n_batches, timeout=120)
            wait_for(_settled([pairs_one, pairs_two]), timeout=60, interval=1.0)
            statuses = [s.http.get("/status").json() for s in (one, w1, w2)]
    finally:
        pairs_one.close()
        pairs_two.close()
    _same_updates(pairs_one.snapshot(), pairs_two.snapshot())
    aided = [sum(r["aided_associations"] for r in st["radars"]) for st in statuses]
    assert aided[0] > 0 and aided[1] == aided[2] == aided[0]  # (each worker's /status: the network's)
    assert all(st["rejected"] == {} for st in statuses)


@pytest.mark.slow
def test_the_cat062_bridge_works_against_partitioned_workers(router: str, tmp_path: Path) -> None:
    """The ASTERIX bridge as against one worker (the README's walkthrough), but against workers
    1/2 and 2/2: it feeds the capture to both, and writes out as CAT062 the system tracks
    worker 1 draws from the radars and pairs of both."""
    out = tmp_path / "system-tracks.ast"
    owners = {rid: Partition(1, 2).owner(rid) for rid in "ABC"}
    assert set(owners.values()) == {1, 2}  # each worker tracks a radar of the capture
    with (
        running_service(
            router, EngineConfig(prefix="two", partition=Partition(1, 2)), correlation_process=False
        ) as w1,
        running_service(
            router, EngineConfig(prefix="two", partition=Partition(2, 2)), correlation_process=False
        ),
    ):
        argv = [TOPOFUSION, "asterix", "--mode", "client", "--connect", router, "--prefix", "two"]
        argv += ["--sites", str(SITES), "--file", str(CAPTURE), "--speed", "20", "--wait-service", "30"]
        argv += ["--out-file", str(out)]
        bridge = subprocess.run(
            argv, cwd=tmp_path, env=environment(), capture_output=True, text=True, timeout=4 * PROCESS_S
        )
        assert bridge.returncode == 0, bridge.stderr
        assert "left out: nothing" in bridge.stderr, bridge.stderr
        system = w1.http.get("/system-tracks").json()
    # the picture joins tracks of both workers' radars
    members = {m["radar_id"] for t in system["system_tracks"] for m in t["members"]}
    assert {rid for rid, k in owners.items() if k == 1} & members
    assert {rid for rid, k in owners.items() if k == 2} & members
    assert_cat062_written(out, bridge.stderr)


def test_only_the_bias_worker_subscribes_to_the_registration_rows() -> None:
    """The rows go to worker 1, which solves the biases: the others never read them, so they do
    not subscribe (the router sends them nothing), while every other exchange key stays."""
    for k in (1, 2, 3):
        config = EngineConfig(prefix="t", partition=Partition(k, 3))
        node = ServiceNode(config, ZenohOptions())  # (never started: no Zenoh session)
        subscribed = set(node._input_keys())
        assert (node.keys.registration_inputs in subscribed) == (k == 1)
        assert set(node.keys.peer_inputs) - {node.keys.registration_inputs} <= subscribed
    alone = ServiceNode(EngineConfig(prefix="t"), ZenohOptions())
    assert not set(alone.keys.peer_inputs) & set(alone._input_keys())
