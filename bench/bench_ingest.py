"""Raw ingest benchmark: 1 000-plot batches through Zenoh into the engine's windows.

Prints batches/s and plots/s, side by side in one run, for
  1. validation alone (pydantic parse + numpy columns),
  2. Zenoh transport alone (client put -> service callback -> queue),
  3. the full node (Zenoh -> queue -> worker -> engine) with window-only trackers, i.e. raw
     ingest into the radars' sliding windows, no tracking,
  4. the full node with the real tracker (clutter-like random plots: a worst case for it).
Target: >= 200 000 plots/s for 3 on 2 cores.  Run: .venv/bin/python bench/bench_ingest.py
"""

from __future__ import annotations

import json
import queue
import socket
import time

import numpy as np

from service.engine import EngineConfig
from service.geo import Site
from service.pipeline.decode import plot_columns
from service.tracking.base import PlotColumns, Tracker, TrackTable
from service.tracking.window import PlotWindow
from service.transport.node import ServiceNode
from service.transport.session import ZenohOptions, open_session
from service.wire.models import PlotBatch, RadarSite

PLOTS = 1000
T0 = 1_763_769_600.0


class WindowOnly(Tracker):
    """Keeps the sliding window only: isolates ingest from tracking."""

    def __init__(self, site: Site, radar_id: str) -> None:
        super().__init__(site, 12.0)
        self.window = PlotWindow(self.window_s)

    def update(self, plots: PlotColumns, time_s: float) -> None:
        self.window.extend(plots, time_s)

    def tracks(self) -> TrackTable:
        return TrackTable.empty()

    @property
    def window_plots(self) -> int:
        return len(self.window)


def make_batches(n_batches: int, radars: list[str]) -> list[tuple[str, bytes]]:
    rng = np.random.default_rng(0)
    out = []
    for i in range(n_batches):
        rid = radars[i % len(radars)]
        t = T0 + 0.5 * (i // len(radars) + 1)
        body = {
            "radar_id": rid,
            "seq": i // len(radars) + 1,
            "time_s": t,
            "plots": {
                "time_s": (t - rng.uniform(0, 0.5, PLOTS)).round(4).tolist(),
                "range_m": rng.uniform(5e3, 3e5, PLOTS).round(2).tolist(),
                "azimuth_deg": rng.uniform(0, 360, PLOTS).round(5).tolist(),
                "elevation_deg": rng.uniform(0, 10, PLOTS).round(5).tolist(),
            },
        }
        out.append((f"fusion/radar/{rid}/plots", json.dumps(body).encode()))
    return out


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def bench_validation(batches: list[tuple[str, bytes]]) -> float:
    t0 = time.perf_counter()
    for _, payload in batches:
        plot_columns(PlotBatch.model_validate_json(payload))
    return time.perf_counter() - t0


def bench_transport(batches: list[tuple[str, bytes]]) -> float:
    endpoint = free_endpoint()
    server = open_session(ZenohOptions(mode="peer", listen=(endpoint,)))
    q: queue.Queue[bytes] = queue.Queue(maxsize=4096)
    sub = server.declare_subscriber("fusion/radar/*/plots", lambda s: q.put(s.payload.to_bytes()))
    client = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
    try:
        time.sleep(0.5)
        import zenoh

        t0 = time.perf_counter()
        for key, payload in batches:
            client.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        for _ in batches:
            q.get(timeout=30)
        return time.perf_counter() - t0
    finally:
        sub.undeclare()
        client.close()
        server.close()


def bench_node(batches: list[tuple[str, bytes]], radars: list[str], window_only: bool) -> float:
    endpoint = free_endpoint()
    sites = tuple(
        RadarSite(radar_id=r, latitude_deg=31.2, longitude_deg=118.5 + i) for i, r in enumerate(radars)
    )
    node = ServiceNode(
        EngineConfig(sites=sites, method="nearest"), ZenohOptions(mode="peer", listen=(endpoint,))
    )
    if window_only:  # trackers are made at a radar's first batch, by the stage's factory
        node.engine.tracking.factory = WindowOnly
    node.start()
    client = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
    try:
        import zenoh

        time.sleep(0.5)
        t0 = time.perf_counter()
        for key, payload in batches:
            client.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        total = len(batches)
        while (
            sum(r.batches for r in node.engine.sequencer.sources.values()) < total or not node.queue.empty()
        ):
            time.sleep(0.001)
        elapsed = time.perf_counter() - t0
        assert node.queue.dropped_total == 0
        return elapsed
    finally:
        client.close()
        node.stop()


def main() -> None:
    radars = ["A", "B", "C", "D"]
    batches = make_batches(400, radars)
    n = len(batches)
    rows = [
        ("validation only", bench_validation(batches)),
        ("zenoh transport only", bench_transport(batches)),
        ("node, windows only (raw ingest)", bench_node(batches, radars, window_only=True)),
        ("node, real tracker (random plots)", bench_node(batches[:80], radars, window_only=False) * n / 80),
    ]
    print(f"{n} batches x {PLOTS} plots, {len(radars)} radars")
    print(f"{'stage':38s} {'batches/s':>10s} {'plots/s':>12s}")
    for name, dt in rows:
        print(f"{name:38s} {n / dt:10.0f} {n * PLOTS / dt:12.0f}")


if __name__ == "__main__":
    main()
