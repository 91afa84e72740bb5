"""End to end: a live multi-radar run, recorded with the real recorder over Zenoh, replayed into
a fresh service at ``--speed 0`` and ``--speed 10``, and offline, gives exactly the live run's
confirmed tracks and pairs; so does a file of the same inputs written by a different writer.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType
from recording_helpers import PREFIX, foreign_mcap, wait_for, wait_subscribed

from service.engine import Engine, EngineConfig
from service.recording import Recorder, add_replay_arguments, replay_main, replay_offline
from service.recording.completion import RecordingEnd
from service.recording.reader import RecordingReader
from service.transport.node import ServiceNode
from service.transport.session import ZenohOptions, open_session
from topofusion_lab.publisher import SITE_REPEAT_BATCHES, publish_scenario
from topofusion_lab.scenarios.catalog import get_scenario

#: Three radars (one with a 5 s scan), light clutter: 40 s of data is enough to confirm
#: tracks on every radar and pairs on every radar pair, in a few seconds of compute.
SCENARIO = replace(get_scenario("three-radar"), duration_s=40.0, targets=12)
SEED = 7
LIVE_SPEED = 10.0  # the live run is paced, so that replay speeds mean something
# Sites travel on the wire like everything else: the node keeps the wire order across keys,
# so a radar's site always reaches the engine before its first plots, live and replayed.
CONFIG = EngineConfig(prefix=PREFIX)


def canonical(items: list[dict[str, Any]]) -> list[str]:
    """Exact comparison form: floats by repr (bit-exact round trip), NaN equal to NaN."""
    return [json.dumps(item, sort_keys=True) for item in items]


def confirmed(node_or_snapshot: Any) -> tuple[list[str], list[str]]:
    snap = getattr(node_or_snapshot, "snapshot", node_or_snapshot)
    tracks = sorted(snap.track_batches(status="confirmed"), key=lambda b: b["radar_id"])
    pairs = sorted(snap.pair_sets(status="confirmed"), key=lambda p: (p["radar_a"], p["radar_b"]))
    return canonical(tracks), canonical(pairs)


def confirmed_from_result(body: dict[str, Any]) -> tuple[list[str], list[str]]:
    tracks = [{**b, "tracks": [t for t in b["tracks"] if t["status"] == "confirmed"]} for b in body["tracks"]]
    pairs = [{**p, "pairs": [x for x in p["pairs"] if x["status"] == "confirmed"]} for p in body["pairs"]]
    return (
        canonical(sorted(tracks, key=lambda b: b["radar_id"])),
        canonical(sorted(pairs, key=lambda p: (p["radar_a"], p["radar_b"]))),
    )


@dataclass
class LiveRun:
    recording: Path
    inputs: int
    tracks: list[str]
    pairs: list[str]


@pytest.fixture(scope="module")
def live_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LiveRun, str]]:
    """Router, live service, recorder and simulator; the router stays up for the replays."""
    from recording_helpers import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
    client = ZenohOptions(mode="client", connect=(endpoint,))
    out = tmp_path_factory.mktemp("live") / "live.mcap"
    try:
        node = ServiceNode(CONFIG, client)
        rec_session = open_session(client)
        pub = open_session(client)
        try:
            node.start()
            wait_subscribed(pub, f"{PREFIX}/radar/A/plots")
            recorder = Recorder(rec_session, out, f"{PREFIX}/**", PREFIX).start()
            wait_subscribed(pub, f"{PREFIX}/probe")  # only the recorder matches this one
            batches, _ = publish_scenario(pub, SCENARIO, PREFIX, speed=LIVE_SPEED, seed=SEED)
            inputs = batches + len(SCENARIO.radars) * (1 + batches // SITE_REPEAT_BATCHES)
            wait_for(lambda: node.processed >= inputs, timeout=60)
            node.stop()  # flushes the engine: the final state of the live run
            report = recorder.stop()
        finally:
            node.stop()
            pub.close()
            rec_session.close()
        assert report.dropped == 0 and report.error is None
        assert node.processed == inputs and node.queue.dropped_total == 0
        recorded_inputs = sum(n for k, n in report.messages_by_key.items() if k.endswith(("/site", "/plots")))
        assert recorded_inputs == inputs
        assert any(k.endswith("/tracks") for k in report.messages_by_key)  # outputs are recorded too
        tracks, pairs = confirmed(node)
        assert len(tracks) == len(SCENARIO.radars) and all(json.loads(b)["tracks"] for b in tracks)
        n_pairs = sum(len(json.loads(p)["pairs"]) for p in pairs)
        assert n_pairs >= 5, "the scenario must confirm pairs to compare"
        yield LiveRun(out, inputs, tracks, pairs), endpoint
    finally:
        router.close()


def _replay_into_fresh_service(path: Path, endpoint: str, inputs: int, extra: list[str]) -> ServiceNode:
    client = ZenohOptions(mode="client", connect=(endpoint,))
    node = ServiceNode(CONFIG, client)
    probe = open_session(client)
    try:
        node.start()
        wait_subscribed(probe, f"{PREFIX}/radar/A/plots")
        parser = argparse.ArgumentParser()
        parser.add_argument("--prefix", default=PREFIX)
        add_replay_arguments(parser)
        assert replay_main(parser.parse_args([str(path), *extra]), client) == 0
        # it returned once the service said its outputs are complete through the recording's end
        end = RecordingEnd()
        with RecordingReader(path, PREFIX) as reader:
            for message in reader.messages(list(reader.survey().channels.values())):
                end.add(message)
        target = end.target_s()
        status = node.status()
        assert target is not None and status["correlation"]["pending"] == 0
        assert status["outputs_time_s"] is not None and status["outputs_time_s"] >= target
        wait_for(lambda: node.processed >= inputs, timeout=60)
    finally:
        node.stop()
        probe.close()
    assert node.processed == inputs and node.queue.dropped_total == 0
    return node


@pytest.mark.parametrize("speed", ["0", "10"])
def test_zenoh_replay_gives_the_live_tracks_and_pairs(live_run: tuple[LiveRun, str], speed: str) -> None:
    live, endpoint = live_run
    node = _replay_into_fresh_service(live.recording, endpoint, live.inputs, ["--speed", speed])
    tracks, pairs = confirmed(node)
    assert tracks == live.tracks
    assert pairs == live.pairs


def test_offline_replay_gives_the_live_tracks_and_pairs(
    live_run: tuple[LiveRun, str], tmp_path: Path
) -> None:
    live, endpoint = live_run
    parser = argparse.ArgumentParser()
    parser.add_argument("--prefix", default=PREFIX)
    add_replay_arguments(parser)
    result = tmp_path / "result.json"
    args = parser.parse_args([str(live.recording), "--offline", "--out", str(result)])
    assert replay_main(args, ZenohOptions(mode="client", connect=(endpoint,))) == 0
    body = json.loads(result.read_text())
    assert body["replay"]["messages"] == live.inputs and body["replay"]["damage"] is None
    tracks, pairs = confirmed_from_result(body)
    assert tracks == live.tracks
    assert pairs == live.pairs
    assert body["biases"] is not None


def test_a_file_from_another_writer_gives_the_same_results(
    live_run: tuple[LiveRun, str], tmp_path: Path
) -> None:
    live, endpoint = live_run
    # Another program's MCAP: the mcap library used directly, lz4 chunks, no schemas, input
    # channels only, message times of its own (what it has in common with ours is the contract).
    with open(live.recording, "rb") as f:
        msgs = [
            (c.topic, m.data, m.log_time)
            for _, c, m in make_reader(f).iter_messages(log_time_order=True)
            if c.topic.endswith(("/site", "/plots"))
        ]
    t0 = 1_700_000_000 * 10**9
    foreign = tmp_path / "other-writer.mcap"
    foreign_mcap(
        foreign,
        [(k, p, t0 + i * 10**6) for i, (k, p, _) in enumerate(msgs)],
        compression=CompressionType.LZ4,
        chunk_size=64 * 1024,
    )
    result = replay_offline(foreign, Engine(CONFIG), PREFIX)
    assert result.messages == live.inputs
    assert confirmed_from_result(result.to_json()) == (live.tracks, live.pairs)
    node = _replay_into_fresh_service(foreign, endpoint, live.inputs, ["--speed", "0"])
    assert confirmed(node) == (live.tracks, live.pairs)
