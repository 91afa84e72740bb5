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

``--national [seconds] [cache.pickle]``: the engine on the ``national`` scenario (12 radars,
66 radar pairs) instead, the full pipeline and tracking alone (``max_site_distance_m = 0``:
no pair) run on the same messages in turns A/B/A/B (a shared machine is noisy), each over
the second half of the stream.  Printed: the wall time of each run, the ratio full /
tracking alone, the per-update times of the last 1 000 pair updates (p50 / p99), the share
of confirmed pairs whose tracks follow one target (truth labels, evaluation only) and, with
``--profile``, the cumulative profile of the full pipeline's second half.  The messages are
simulated once and kept in ``cache.pickle`` when a path is given.
"""

from __future__ import annotations

import cProfile
import os
import pickle
import pstats
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


def _national_messages(duration_s: float, cache: str | None) -> list[tuple[str, bytes]]:
    from dataclasses import replace

    from topofusion_lab.scenarios.catalog import get_scenario
    from topofusion_lab.scenarios.simulator import wire_messages

    if cache and os.path.exists(cache):
        with open(cache, "rb") as f:
            cached: list[tuple[str, bytes]] = pickle.load(f)
        return cached
    msgs = list(wire_messages(replace(get_scenario("national"), duration_s=duration_s), 1))
    if cache:
        with open(cache, "wb") as f:
            pickle.dump(msgs, f)
    return msgs


def _run_engine(msgs: list[tuple[str, bytes]], tracking_only: bool, profile: bool) -> tuple[float, object]:
    """Seconds spent on the second half of ``msgs``, and the engine."""
    from service.engine import Engine, EngineConfig
    from service.pipeline.correlation_stage import CadenceParams

    cfg = EngineConfig(cadence=CadenceParams(max_site_distance_m=0)) if tracking_only else EngineConfig()
    e = Engine(cfg)
    h = len(msgs) // 2
    for k, p in msgs[:h]:
        e.ingest(k, p)
    pr = cProfile.Profile() if profile else None
    t0 = time.perf_counter()
    if pr is not None:
        pr.enable()
    for k, p in msgs[h:]:
        e.ingest(k, p)
    if pr is not None:
        pr.disable()
    wall = time.perf_counter() - t0
    if pr is not None:
        pstats.Stats(pr).sort_stats("cumulative").print_stats("service", 40)
    return wall, e


def _confirmed_accuracy(e: object) -> tuple[int, int, int]:
    """Confirmed pairs judged, those whose two tracks carry one truth label, pairs of a gone track."""
    snap = e.snapshot()  # type: ignore[attr-defined]
    truth: dict[tuple[str, str], str | None] = {}
    for batch in snap.track_batches("all"):
        for t in batch["tracks"]:
            truth[(batch["radar_id"], t["track_id"])] = t["truth_id"]
    judged = ok = gone = 0
    for ps in snap.pair_sets(status="confirmed"):
        for p in ps["pairs"]:
            ka, kb = (ps["radar_a"], p["track_a"]), (ps["radar_b"], p["track_b"])
            if ka not in truth or kb not in truth:
                gone += 1
                continue
            judged += 1
            ok += truth[ka] is not None and truth[ka] == truth[kb]
    return judged, ok, gone


def bench_national(duration_s: float = 300.0, cache: str | None = None, profile: bool = False) -> None:
    msgs = _national_messages(duration_s, cache)
    print(f"national scenario, {duration_s:.0f} s of data, {len(msgs)} messages (second half timed)")
    walls: dict[str, list[float]] = {"full": [], "tracking": []}
    for turn in range(2):
        for label in ("full", "tracking"):
            wall, e = _run_engine(msgs, label == "tracking", profile and turn == 0 and label == "full")
            walls[label].append(wall)
            print(f"  {label:>8}: {wall:6.2f} s")
            if label == "full" and turn == 1:
                t = np.asarray(list(e.correlation.timings_ms)[-1000:])  # type: ignore[attr-defined]
                print(
                    f"  pair updates: {e.correlation.updates}; last {len(t)}: "  # type: ignore[attr-defined]
                    f"p50 {np.percentile(t, 50):.2f} ms  p99 {np.percentile(t, 99):.2f} ms"
                )
                judged, ok, gone = _confirmed_accuracy(e)
                print(
                    f"  confirmed pairs: {judged} judged, same target: {ok} "
                    f"({100.0 * ok / max(judged, 1):.2f} %); {gone} of a track gone"
                )
    ratio = min(walls["full"]) / min(walls["tracking"])
    print(f"  full / tracking alone (best of 2 each): {ratio:.2f}; load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--national":
        rest = [x for x in sys.argv[2:] if x != "--profile"]
        bench_national(
            float(rest[0]) if rest else 300.0, rest[1] if len(rest) > 1 else None, "--profile" in sys.argv
        )
    else:
        args = [int(x) for x in sys.argv[1:3]]
        bench_steady_state(*args)
