"""Benchmark of the correlators (prints figures; never run by the tests).

1. Time of one match (one candidate per call, 6 neighbours) for svd-topology vs
   basic-topology at 0.5, 2 and 5 deg azimuth bias of radar A (the basic method searches
   +-(bias + 0.5) deg in 0.25 deg steps and +-200 m in 50 m steps).  Goal: >= 10x faster at
   2 deg and flat in the bias.
2. One full ``PairCorrelator.update`` of 1 000 x 1 000 tracks (svd-topology, both the
   unregistered start and the registered steady state).  Goal: <= 50 ms.

Usage: ``.venv/bin/python bench/bench_correlation.py``
"""

from __future__ import annotations

import time

import numpy as np

from service.correlation import PairCorrelator
from service.evaluation.correlation_scenario import make_sites
from service.evaluation.correlation_single import time_per_match
from service.evaluation.correlation_stream import RadarTrackSim, StreamScenario, make_targets


def bench_single_match() -> None:
    biases = (0.5, 2.0, 5.0)
    t = time_per_match(seed=0, biases_deg=biases, reps=300)
    print("time of one match (ms), 6 neighbours")
    head = ("azimuth bias", "svd-topology", "basic-topology", "speed-up", "svd batched/cand")
    print(f"{head[0]:>14} {head[1]:>13} {head[2]:>15} {head[3]:>9} {head[4]:>17}")
    for k, b in enumerate(biases):
        s, bb, sb = t["svd-topology"][k], t["basic-topology"][k], t["svd-topology (batched)"][k]
        print(f"{b:>12.1f}deg {s:>13.3f} {bb:>15.3f} {bb / s:>8.1f}x {sb:>17.4f}")


def bench_full_update(n: int = 1000, updates: int = 8) -> None:
    sc = StreamScenario(
        sparse_targets=n, box_m=400_000.0, cluster_targets=0, max_range_m=450_000.0, confirm_scans=1
    )
    rng = np.random.default_rng(1)
    a, b = make_sites()
    pos0, vel = make_targets(rng, sc, a)
    ra = RadarTrackSim(rng, a, sc.bias_a, n, sc)
    rb = RadarTrackSim(rng, b, sc.bias_b, n, sc)
    tables = [
        (ra.table(a, pos0, vel, k * 4.0), rb.table(a, pos0, vel, k * 4.0), k * 4.0 + 4.0)
        for k in range(updates)
    ]
    corr = PairCorrelator("svd-topology", a, b)
    wall = []
    for ta, tb, t in tables:
        t0 = time.perf_counter()
        corr.update(ta, tb, t)
        wall.append((time.perf_counter() - t0) * 1e3)
    conf = sum(p.status == "confirmed" for p in corr.pairs())
    print(f"\nfull correlation update, {len(tables[0][0])} x {len(tables[0][1])} tracks (svd-topology)")
    print(
        f"  candidates per update: {len(corr.last_decisions)}; registered: {corr.registered}; "
        f"confirmed: {conf}"
    )
    print(f"  first update (unregistered): {wall[0]:.1f} ms")
    steady = np.median(wall[4:])
    print(f"  steady state (registered), median of {len(wall) - 4}: {steady:.1f} ms  (goal <= 50 ms)")


if __name__ == "__main__":
    bench_single_match()
    bench_full_update()
