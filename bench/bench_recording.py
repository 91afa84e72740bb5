"""Benchmark of recording and replay (prints figures; never run by the tests).

1. MCAP writer alone: plot batches of 1 000 plots written by ``RecordingWriter`` (zstd chunks).
2. Record over Zenoh: a client publishes plot batches as fast as a BLOCK publisher goes, through
   a router on a free loopback port, into the real recorder (callback -> queue -> writer thread).
3. Reading back: the whole file through ``RecordingReader`` (indexed path and, after cutting the
   footer off, the damaged-file path).
4. Replay over Zenoh at ``--speed 0`` into a counting subscriber.
5. Offline replay of a simulated three-radar run into the engine (engine-bound: the numerics).

Usage: ``.venv/bin/python bench/bench_recording.py [--batches N] [--plots P]``
"""

from __future__ import annotations

import argparse
import json
import socket
import tempfile
import threading
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import zenoh

from service.recording import (
    Recorder,
    RecordingReader,
    RecordingWriter,
    ReplayOptions,
    replay,
    replay_offline,
)
from service.recording.publisher import ZenohReplayPublisher
from service.transport.session import ZenohOptions, open_session

PREFIX = "fusion"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _batches(n: int, plots: int, radars: int = 4) -> list[tuple[str, bytes]]:
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        rid = f"R{i % radars}"
        t = 1.7e9 + i * 0.5
        body = {
            "radar_id": rid,
            "seq": i // radars,
            "time_s": t,
            "plots": {
                "time_s": np.round(t - rng.uniform(0, 0.5, plots), 4).tolist(),
                "range_m": np.round(rng.uniform(1e3, 3e5, plots), 1).tolist(),
                "azimuth_deg": np.round(rng.uniform(0, 360, plots), 3).tolist(),
                "elevation_deg": np.round(rng.uniform(0, 10, plots), 3).tolist(),
            },
        }
        out.append((f"{PREFIX}/radar/{rid}/plots", json.dumps(body).encode()))
    return out


def _line(what: str, messages: int, plots: int, nbytes: int, seconds: float) -> None:
    print(
        f"{what:<44} {messages / seconds:>10.0f} msg/s {plots / seconds:>12.0f} plots/s "
        f"{nbytes / seconds / 1e6:>8.1f} MB/s  ({messages} msgs in {seconds:.2f} s)"
    )


def bench_writer(path: Path, batches: list[tuple[str, bytes]], plots: int) -> None:
    nbytes = sum(len(p) for _, p in batches)
    t0 = time.perf_counter()
    with RecordingWriter(path, PREFIX) as w:
        for i, (key, payload) in enumerate(batches):
            w.write(key, payload, 1_700_000_000_000_000_000 + i * 1000)
    dt = time.perf_counter() - t0
    _line("1. MCAP writer alone", len(batches), len(batches) * plots, nbytes, dt)
    print(f"   file {path.stat().st_size / 1e6:.1f} MB for {nbytes / 1e6:.1f} MB of JSON payload")


def bench_record_zenoh(path: Path, batches: list[tuple[str, bytes]], plots: int) -> None:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    client = ZenohOptions(mode="client", connect=(endpoint,))
    router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
    try:
        rec_session, pub = open_session(client), open_session(client)
        try:
            recorder = Recorder(rec_session, path, f"{PREFIX}/**", PREFIX).start()
            probe = pub.declare_publisher(f"{PREFIX}/probe")
            while not probe.matching_status.matching:
                time.sleep(0.01)
            probe.undeclare()
            publishers = {
                k: pub.declare_publisher(
                    k,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    reliability=zenoh.Reliability.RELIABLE,
                )
                for k in {k for k, _ in batches}
            }
            t0 = time.perf_counter()
            for key, payload in batches:
                publishers[key].put(payload)
            deadline = time.monotonic() + 120
            while recorder._writer.totals.messages + sum(recorder.queue.dropped.values()) < len(batches):
                if time.monotonic() > deadline:
                    break
                time.sleep(0.005)
            dt = time.perf_counter() - t0
            report = recorder.stop()
        finally:
            pub.close()
            rec_session.close()
    finally:
        router.close()
    nbytes = sum(len(p) for _, p in batches)
    _line("2. record over Zenoh (router, 2 clients)", report.messages, report.messages * plots, nbytes, dt)
    print(f"   dropped {report.dropped}, queue high water {report.queue_high_water} samples")


def bench_read(path: Path, plots: int) -> None:
    for label, file in (
        ("3a. read back (indexed)", path),
        ("3b. read back (no footer: scan path)", _cut(path)),
    ):
        t0 = time.perf_counter()
        n = nbytes = 0
        with RecordingReader(file, PREFIX) as reader:
            channels = list(reader.survey().channels.values())
            for m in reader.messages(channels):
                n += 1
                nbytes += len(m.payload)
        _line(label, n, n * plots, nbytes, time.perf_counter() - t0)


def _cut(path: Path) -> Path:
    cut = path.with_name("cut.mcap")
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) - 64])
    return cut


def bench_replay_zenoh(path: Path, plots: int) -> None:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    client = ZenohOptions(mode="client", connect=(endpoint,))
    router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
    try:
        sub_session, pub = open_session(client), open_session(client)
        got = [0]
        done = threading.Event()
        try:

            def count(_sample: zenoh.Sample) -> None:
                got[0] += 1

            sub = sub_session.declare_subscriber(f"{PREFIX}/**", count)
            probe = pub.declare_publisher(f"{PREFIX}/probe")
            while not probe.matching_status.matching:
                time.sleep(0.01)
            probe.undeclare()
            t0 = time.perf_counter()
            with ZenohReplayPublisher(pub) as publish:
                report = replay(path, publish, PREFIX, ReplayOptions(speed=0), progress=False)
            deadline = time.monotonic() + 60
            while got[0] < report.messages and time.monotonic() < deadline:
                time.sleep(0.002)
            dt = time.perf_counter() - t0
            done.set()
            sub.undeclare()
        finally:
            pub.close()
            sub_session.close()
    finally:
        router.close()
    nbytes = sum(report.bytes_by_key.values())
    _line("4. replay over Zenoh --speed 0 (received)", got[0], got[0] * plots, nbytes, dt)


def bench_offline(tmp: Path, duration_s: float, targets: int) -> None:
    from service.engine import Engine, EngineConfig
    from service.wire.keys import Keys
    from topofusion_lab.scenarios.catalog import get_scenario
    from topofusion_lab.scenarios.simulator import generate

    sc = replace(get_scenario("three-radar"), duration_s=duration_s, targets=targets)
    keys = Keys(PREFIX)
    path = tmp / "sim.mcap"
    with RecordingWriter(path, PREFIX) as w:
        for i, m in enumerate(generate(sc, 1)):
            key = keys.site(m.radar_id) if m.kind == "site" else keys.plots(m.radar_id)
            w.write(key, json.dumps(m.body).encode(), 1_700_000_000_000_000_000 + i * 10**6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        result = replay_offline(path, Engine(EngineConfig(prefix=PREFIX)), PREFIX)
    _line(
        f"5. offline into the engine ({duration_s:.0f} s, {targets} targets, 3 radars)",
        result.messages,
        result.plots,
        path.stat().st_size,
        result.wall_s,
    )
    pairs = sum(p["status"] == "confirmed" for ps in result.pairs for p in ps["pairs"])
    print(f"   {pairs} confirmed pairs at the end")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batches", type=int, default=5000, help="plot batches for 1-4")
    parser.add_argument("--plots", type=int, default=1000, help="plots per batch for 1-4")
    parser.add_argument("--sim-duration", type=float, default=300.0, help="data seconds simulated for 5")
    parser.add_argument("--sim-targets", type=int, default=50, help="targets simulated for 5")
    args = parser.parse_args()
    batches = _batches(args.batches, args.plots)
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        bench_writer(tmp / "writer.mcap", batches, args.plots)
        bench_record_zenoh(tmp / "recorded.mcap", batches, args.plots)
        bench_read(tmp / "recorded.mcap", args.plots)
        bench_replay_zenoh(tmp / "recorded.mcap", args.plots)
        bench_offline(tmp, args.sim_duration, args.sim_targets)


if __name__ == "__main__":
    main()
