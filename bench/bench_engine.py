"""Whole-engine benchmark: how much sky one box holds.

Pre-generates simulated streams (the simulator's cost is excluded), then feeds them through
one Engine (tracking + correlation + bias estimation, the production code path, no Zenoh)
and prints, per scenario size: messages/s, plots/s, the real-time factor (data seconds per
wall second: above 1 means the box keeps up), and correlation update times (p50/p99).

Run: .venv/bin/python bench/bench_engine.py
"""

from __future__ import annotations

import json
import time
from dataclasses import replace

from service.engine import Engine
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import wire_messages

DATA_S = 120.0


def stream(name: str, targets: int, half_width_m: float) -> list[tuple[str, bytes]]:
    sc = replace(get_scenario(name), duration_s=DATA_S, targets=targets, half_width_m=half_width_m)
    return list(wire_messages(sc, 1))


def main() -> None:
    print(f"{DATA_S:.0f} s of data per row; engine only (tracking + correlation + biases), one process")
    print(
        f"{'scenario':12s} {'targets':>7s} {'msgs/s':>8s} {'plots/s':>9s} {'x real time':>11s} "
        f"{'corr p50 ms':>11s} {'corr p99 ms':>11s} {'pairs':>6s}"
    )
    for name, targets, width in [
        ("two-radar", 40, 120e3),
        ("two-radar", 200, 120e3),
        ("three-radar", 80, 140e3),
        ("three-radar", 300, 140e3),
        ("two-radar", 1000, 150e3),
    ]:
        msgs = stream(name, targets, width)
        plots = sum(len(json.loads(p)["plots"]["time_s"]) for k, p in msgs if k.endswith("/plots"))
        engine = Engine()
        t0 = time.perf_counter()
        for key, payload in msgs:
            engine.ingest(key, payload)
        engine.flush()
        dt = time.perf_counter() - t0
        snap = engine.snapshot()
        corr = snap.correlation
        pairs = snap.status_core()["pairs_confirmed"]
        print(
            f"{name:12s} {targets:7d} {len(msgs) / dt:8.0f} {plots / dt:9.0f} {DATA_S / dt:11.1f} "
            f"{corr['p50_ms']:11.1f} {corr['p99_ms']:11.1f} {pairs:6d}",
            flush=True,
        )


if __name__ == "__main__":
    main()
