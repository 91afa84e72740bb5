"""Benchmark of a steady-state ``PairCorrelator.update`` (prints figures; never run by the tests).

A two-radar stream of ``n`` en-route aircraft (1 000 by default, every one seen by both
radars) goes through one ``svd-topology`` correlator for ``updates`` scans of 4 s.  Once the
pair is registered and nearly every pair is confirmed, an update should cost in proportion
to what needs a decision (new tracks, tentative pairs, failed re-checks), not to the number
of tracks.  Printed: the time of the later updates (p50 / p90 / p99 / max, those with and
without the periodic two-radar bias re-solve apart), what the last update decided, and the
correctness of the confirmed pairs against the simulator's truth.

The figures are process-independent of the module tree: run it once per tree to compare two
versions side by side (``PYTHONPATH=<tree> python bench/bench_pair_update.py``).

With 170 updates (680 s of data) the registration memory is full (``memory_s`` = 600 s), so the
re-solve figures are those of a pair in service for a long time.

Usage: ``.venv/bin/python bench/bench_pair_update.py [n] [updates]``
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from service.correlation import PairCorrelator
from topofusion_lab.evaluation.correlation_scenario import make_sites
from topofusion_lab.evaluation.correlation_stream import RadarTrackSim, StreamScenario, make_targets


def _tables(n: int, updates: int, seed: int = 1) -> list[tuple[object, object, float]]:
    sc = StreamScenario(
        sparse_targets=n, box_m=400_000.0, cluster_targets=0, max_range_m=450_000.0, confirm_scans=1
    )
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    pos0, vel = make_targets(rng, sc, a)
    ra = RadarTrackSim(rng, a, sc.bias_a, n, sc)
    rb = RadarTrackSim(rng, b, sc.bias_b, n, sc)
    return [
        (ra.table(a, pos0, vel, k * 4.0), rb.table(a, pos0, vel, k * 4.0), k * 4.0 + 4.0)
        for k in range(updates)
    ]


def bench_steady_state(n: int = 1000, updates: int = 60) -> None:
    import service.correlation as sc_mod

    tables = _tables(n, updates)
    skip = max(20, updates - 40)  # the last 40 updates (at most), registered by then
    a, b = make_sites()
    corr = PairCorrelator("svd-topology", a, b)
    wall, cpu, solved = [], [], []
    for ta, tb, t in tables:
        before = corr._solved_s
        t0, c0 = time.perf_counter(), time.process_time()
        corr.update(ta, tb, t)  # type: ignore[arg-type]
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
        solved.append(corr._solved_s != before)
    w, c, s = np.array(wall[skip:]), np.array(cpu[skip:]), np.array(solved[skip:])
    ta, tb, _ = tables[-1]
    truth_a = dict(zip(ta.track_id, ta.truth_id, strict=True))  # type: ignore[attr-defined]
    truth_b = dict(zip(tb.track_id, tb.truth_id, strict=True))  # type: ignore[attr-defined]
    conf = [p for p in corr.pairs() if p.status == "confirmed"]
    ok = sum(truth_a.get(p.track_a) == truth_b.get(p.track_b) for p in conf)
    print(f"module tree: {os.path.dirname(os.path.dirname(sc_mod.__file__))}")
    print(f"steady-state pair update, {len(ta)} x {len(tb)} tracks (svd-topology), updates {skip}..{updates}")
    print(
        f"  registered: {corr.registered}; confirmed pairs: {len(conf)} "
        f"({ok} correct, {len(conf) - ok} false)"
    )
    kept = getattr(corr, "last_reverified", 0)
    print(
        f"  last update: {kept} confirmed pairs kept by the re-check, "
        f"{len(corr.last_decisions) - kept} candidates decided in full; {len(corr.memory)} remembered rows"
    )
    for label, x in (("wall", w), ("cpu", c)):
        print(
            f"  {label:>4} ms  p50 {np.percentile(x, 50):6.2f}  p90 {np.percentile(x, 90):6.2f}  "
            f"p99 {np.percentile(x, 99):6.2f}  max {x.max():6.2f}"
        )
    if s.any():
        print(
            f"  wall ms without re-solve: p50 {np.percentile(w[~s], 50):6.2f}  max {w[~s].max():6.2f}; "
            f"with the re-solve ({int(s.sum())} updates): p50 {np.percentile(w[s], 50):6.2f}  "
            f"max {w[s].max():6.2f}"
        )
    print(f"  load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    args = [int(x) for x in sys.argv[1:3]]
    bench_steady_state(*args)
