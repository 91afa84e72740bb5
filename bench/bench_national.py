"""National-scale benchmark: the ``national`` scenario (12 radars, 1 500 aircraft) through the engine.

Prints figures, never asserts.  The simulated stream is generated before any clock starts
(the simulator's cost is excluded; ``--cache FILE`` keeps it between runs).  Modes:

* default, in process: the stream through one ``Engine(EngineConfig())`` as fast as it goes,
  with ``engine.snapshot()`` taken every ``--snapshot-every`` messages as the service node's
  worker does when it lags (service/transport/node.py).  Side by side in the same run, the same
  stream through an engine whose correlation stage never runs (``max_site_distance_m=0``: no
  two sites overlap, and the scenario has no AIS source), so the ratio full / tracking alone
  is what correlation and bias estimation cost.  ``--repeat N`` interleaves the two
  (A, B, A, B, ...) because the machine is noisy.
* ``--zenoh``: a ``ServiceNode`` in router mode on a free loopback port (multicast scouting
  off) and a client session publishing the stream with ``CongestionControl.BLOCK`` as fast as
  the node takes it (as a replay at ``--speed 0`` does), until the node has processed every
  message; ``--subscribe`` adds a subscriber to its tracks, pairs and errors.
* ``--profile``: the in-process run under cProfile; top functions by cumulative and own time.
* ``--soak-minutes M``: a never-ending stream, generated in chunks, fed in process for M wall
  minutes; one line per minute (RSS, window, tracks, pairs) and the RSS slope at the end;
  ``--trace-memory`` adds where the Python heap grew over the second half (tracemalloc).

Accuracy (evaluation only: the simulator's ``truth_id`` on the final tracks, which no
algorithm reads): share of confirmed pairs whose two tracks follow the same aircraft, track
completeness (aircraft a radar has seen for more than 30 s and still sees that have a
confirmed track of that radar), pair completeness (aircraft with confirmed tracks on both
radars of a correlated pair that have a correct confirmed pair), and each radar's bias
estimate against the simulator's bias.

Run: .venv/bin/python bench/bench_national.py [--duration 120] [--seed 1] [--repeat 1]
     [--cache FILE] [--zenoh [--subscribe] | --profile | --soak-minutes 30 [--trace-memory]]
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import gc
import hashlib
import itertools
import json
import os
import pickle
import pstats
import resource
import socket
import sys
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from service.engine import Engine, EngineConfig, Snapshot
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import Scenario, wire_messages

Stream = list[tuple[str, bytes]]

#: An aircraft counts for track completeness when a radar has seen it for longer than this.
SEEN_FOR_S = 30.0
#: ... and saw it within this many of its scan periods before the end of the stream.
STILL_SEEN_SCANS = 3.0
PROGRESS_PERIOD_S = 10.0
#: Slowest ingest calls listed per run.
SLOWEST = 5
#: Data time origin of the scenario (its start_time_s), for message times in the report.
T0 = get_scenario("national").start_time_s


# -- the stream and what the simulator knows ---------------------------------------------------
@dataclass
class Truth:
    """Per radar and aircraft: first and last data time of its plots (evaluation only)."""

    seen: dict[str, dict[str, tuple[float, float]]] = field(default_factory=dict)
    end_time_s: float = -np.inf
    plots: int = 0
    payload_bytes: int = 0


def scenario(duration_s: float | None) -> Scenario:
    return replace(get_scenario("national"), duration_s=duration_s)


def make_stream(sc: Scenario, seed: int, cache: Path | None) -> Stream:
    """The whole stream in memory; ``cache`` keeps it keyed by the scenario and seed.

    The key does not cover the simulator's code: delete the file after changing it.
    """
    tag = hashlib.sha256(repr((sc, seed)).encode()).hexdigest()[:16]
    if cache is not None and cache.exists():
        with cache.open("rb") as f:
            stored_tag, stream = pickle.load(f)
        if stored_tag == tag:
            return list(stream)
    t0 = time.perf_counter()
    stream = list(wire_messages(sc, seed))
    print(
        f"# generated {len(stream)} messages in {time.perf_counter() - t0:.1f} s (not timed below)",
        file=sys.stderr,
    )
    if cache is not None:
        with cache.open("wb") as f:
            pickle.dump((tag, stream), f)
    return stream


def survey(stream: Stream) -> Truth:
    truth = Truth()
    for key, payload in stream:
        truth.payload_bytes += len(payload)
        if not key.endswith("/plots"):
            continue
        body = json.loads(payload)
        plots = body["plots"]
        truth.plots += len(plots["time_s"])
        seen = truth.seen.setdefault(body["radar_id"], {})
        for t, tid in zip(plots["time_s"], plots["truth_id"], strict=True):
            if tid is None:
                continue
            first, last = seen.get(tid, (t, t))
            seen[tid] = (min(first, t), max(last, t))
            truth.end_time_s = max(truth.end_time_s, t)
    return truth


# -- memory ------------------------------------------------------------------------------------
def rss_mb() -> float:
    """Resident set size now (Linux ``statm``; 0 where unavailable)."""
    try:
        resident = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0.0
    return resident * os.sysconf("SC_PAGE_SIZE") / 1e6


def peak_rss_mb() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1e3 if sys.platform != "darwin" else kb / 1e6  # kB on Linux, bytes on macOS


# -- probes on the engine (bench only; fall back to the snapshot's figures) --------------------
def correlation_stage(engine: Engine) -> Any:
    """The engine's correlation stage (an attribute with ``update``, ``updates``, ``timings_ms``)."""
    for name in ("correlation", "_correlation"):
        stage = getattr(engine, name, None)
        if all(hasattr(stage, a) for a in ("update", "updates", "timings_ms")):
            return stage
    return None


def tracking_alone_config() -> EngineConfig:
    """An EngineConfig whose correlation stage never pairs two radars.

    ``max_site_distance_m = 0``: no two sites are that close, so no radar pair is ever
    correlated (the scenario has no AIS source).  The field sits on the config or on one of its
    nested parameter blocks depending on the engine's version; the run checks afterwards that
    no correlation update happened.
    """
    base: Any = EngineConfig()
    off = {"max_site_distance_m": 0.0}
    if any(f.name in off for f in fields(base)):
        config: EngineConfig = replace(base, **off)
        return config
    for f in fields(base):
        block: Any = getattr(base, f.name)
        if set(off) <= set(getattr(block, "__dataclass_fields__", ())):
            config = replace(base, **{f.name: replace(block, **off)})
            return config
    raise SystemExit("no max_site_distance_m in EngineConfig: cannot build a tracking-alone engine")


class Probe:
    """Every correlation update's time and the correlation stage's share of the wall time.

    ``snapshot.correlation`` holds p50/p99 over the last 2 048 updates only; the probe keeps
    every update's time, read from the stage's own record right after each call, on the
    thread that made it.  When the engine's stage cannot be found the probe records nothing
    and the report says so.
    """

    def __init__(self, engine: Engine) -> None:
        self.updates_ms: list[float] = []
        self.bias_ms: list[float] = []
        self.stage_s = float("nan")
        stage = correlation_stage(engine)
        if stage is None:
            return
        self.stage_s = 0.0
        original = stage.update
        # The joint bias solve, where the stage runs it inside an update (part of stage_s).
        solve = getattr(stage, "_solve_biases", None)
        if callable(solve):

            def timed_solve(*a: Any, **k: Any) -> Any:
                t0 = time.perf_counter()
                try:
                    return solve(*a, **k)
                finally:
                    self.bias_ms.append(1e3 * (time.perf_counter() - t0))

            setattr(stage, "_solve_biases", timed_solve)  # noqa: B010 (as below)

        def timed(*a: Any, **k: Any) -> Any:
            before = int(stage.updates)
            t0 = time.perf_counter()
            try:
                return original(*a, **k)
            finally:
                self.stage_s += time.perf_counter() - t0
                new = int(stage.updates) - before
                if new > 0:
                    self.updates_ms.extend(list(stage.timings_ms)[-new:])

        setattr(stage, "update", timed)  # noqa: B010 (an instance attribute over the method)


# -- one in-process run ------------------------------------------------------------------------
@dataclass
class RunResult:
    label: str
    wall_s: float  # ingest + flush + snapshots
    ingest_s: float  # ingest + flush
    snapshot_s: list[float]
    ingest_ms: np.ndarray
    updates_ms: np.ndarray
    bias_ms: np.ndarray
    stage_s: float
    final: Snapshot
    final_snapshot_s: float
    rss_before_mb: float
    rss_after_mb: float
    corr_updates: int


def feed(
    engine: Engine,
    stream: Stream,
    snapshot_every: int,
    label: str,
    data_s: float,
) -> RunResult:
    probe = Probe(engine)
    rss_before = rss_mb()
    ingest_ms = np.empty(len(stream))
    snaps: list[float] = []
    ingest_s = 0.0
    last_progress = time.monotonic()
    t_start = time.perf_counter()
    for i, (key, payload) in enumerate(stream):
        t0 = time.perf_counter()
        engine.ingest(key, payload, receive_time_s=0.0)
        dt = time.perf_counter() - t0
        ingest_ms[i] = dt * 1e3
        ingest_s += dt
        if snapshot_every > 0 and (i + 1) % snapshot_every == 0:
            t0 = time.perf_counter()
            engine.snapshot()
            snaps.append(time.perf_counter() - t0)
        if time.monotonic() - last_progress >= PROGRESS_PERIOD_S:
            last_progress = time.monotonic()
            elapsed = time.perf_counter() - t_start
            print(
                f"# {label}: {i + 1}/{len(stream)} msgs, "
                f"~{data_s * (i + 1) / len(stream):.0f}/{data_s:.0f} data s "
                f"in {elapsed:.0f} s",
                file=sys.stderr,
                flush=True,
            )
    t0 = time.perf_counter()
    try:
        engine.flush()
    except Exception as exc:  # an engine bug at the end must not lose the run's figures
        print(f"  WARNING: engine.flush() raised {type(exc).__name__}: {exc}", flush=True)
    ingest_s += time.perf_counter() - t0
    wall = time.perf_counter() - t_start
    t0 = time.perf_counter()
    final = engine.snapshot()
    final_snapshot_s = time.perf_counter() - t0
    return RunResult(
        label=label,
        wall_s=wall,
        ingest_s=ingest_s,
        snapshot_s=snaps,
        ingest_ms=ingest_ms,
        updates_ms=np.asarray(probe.updates_ms),
        bias_ms=np.asarray(probe.bias_ms),
        stage_s=probe.stage_s,
        final=final,
        final_snapshot_s=final_snapshot_s,
        rss_before_mb=rss_before,
        rss_after_mb=rss_mb(),
        corr_updates=int(final.correlation.get("updates", 0)),
    )


def pct(x: np.ndarray | list[float], q: float) -> float:
    a = np.asarray(x, dtype=float)
    return float(np.percentile(a, q)) if a.size else float("nan")


def describe(message: tuple[str, bytes]) -> str:
    """A message as ``radar@data time`` (seconds from the scenario's start)."""
    key, payload = message
    body = json.loads(payload)
    t = body.get("time_s")
    source = body.get("radar_id") or body.get("source_id") or key
    return f"{source}@{t - T0:.1f}s" if isinstance(t, float | int) else str(source)


def report_run(r: RunResult, data_s: float, truth: Truth, stream: Stream) -> None:
    messages = len(stream)
    snaps = np.asarray(r.snapshot_s)
    print(f"[{r.label}]")
    print(
        f"  real time x{data_s / r.wall_s:.2f} with snapshots, x{data_s / r.ingest_s:.2f} engine only "
        f"({r.wall_s:.1f} s wall for {data_s:.0f} data s); {truth.plots / r.wall_s:,.0f} plots/s, "
        f"{messages / r.wall_s:.0f} msgs/s"
    )
    print(
        f"  ingest per message: p50 {pct(r.ingest_ms, 50):.2f} ms, p99 {pct(r.ingest_ms, 99):.1f} ms, "
        f"max {r.ingest_ms.max():.1f} ms"
    )
    slowest = np.argsort(r.ingest_ms)[::-1][:SLOWEST]
    print(
        "  slowest ingests: " + ", ".join(f"{describe(stream[i])} {r.ingest_ms[i]:.0f} ms" for i in slowest)
    )
    corr = r.final.correlation
    if r.corr_updates:
        stage = (
            f"{r.stage_s:.1f} s = {100 * r.stage_s / r.wall_s:.0f}% of wall"
            if np.isfinite(r.stage_s)
            else "n/a"
        )
        print(
            f"  correlation: {r.corr_updates} updates; per update (all, probe) p50 "
            f"{pct(r.updates_ms, 50):.2f} ms, "
            f"p99 {pct(r.updates_ms, 99):.1f} ms, max {pct(r.updates_ms, 100):.1f} ms "
            f"(snapshot's last 2048: p50 {corr.get('p50_ms')} ms, p99 {corr.get('p99_ms')} ms); "
            f"stage total {stage}"
        )
        if r.bias_ms.size:
            print(
                f"  bias solves (inside the stage): {r.bias_ms.size}, p50 {pct(r.bias_ms, 50):.0f} ms, "
                f"max {r.bias_ms.max():.0f} ms, total {r.bias_ms.sum() / 1e3:.1f} s"
            )
    else:
        print("  correlation: no update (as intended for tracking alone)")
    if snaps.size:
        print(
            f"  snapshots: {snaps.size}, mean "
            f"{1e3 * snaps.mean():.1f} ms, p99 {1e3 * pct(snaps, 99):.1f} ms, max "
            f"{1e3 * snaps.max():.1f} ms, "
            f"total {snaps.sum():.1f} s = {100 * snaps.sum() / r.wall_s:.0f}% of wall; "
            f"final snapshot {1e3 * r.final_snapshot_s:.0f} ms"
        )
    core = r.final.status_core()
    tracks = sum(x["tracks_confirmed"] + x["tracks_tentative"] for x in core["radars"])
    confirmed = sum(x["tracks_confirmed"] for x in core["radars"])
    window = sum(x["window_plots"] for x in core["radars"])
    print(
        f"  end: {confirmed} confirmed / {tracks} tracks, {window} window plots, "
        f"{core['pairs_confirmed']} confirmed + {core['pairs_tentative']} tentative pairs, "
        f"rejected {core['rejected'] or 0}"
    )
    print(
        f"  RSS {r.rss_before_mb:.0f} -> {r.rss_after_mb:.0f} MB over the run; peak so far "
        f"{peak_rss_mb():.0f} MB"
    )


# -- accuracy (evaluation only: truth_id) --------------------------------------------------------
def accuracy(snap: Snapshot, sc: Scenario, truth: Truth) -> None:
    truth_of: dict[tuple[str, str], str | None] = {}
    confirmed_truths: dict[str, set[str]] = {}
    for batch in snap.track_batches("all"):
        rid = batch["radar_id"]
        confirmed_truths[rid] = set()
        for t in batch["tracks"]:
            truth_of[(rid, t["track_id"])] = t["truth_id"]
            if t["status"] == "confirmed" and t["truth_id"] is not None:
                confirmed_truths[rid].add(t["truth_id"])

    correct = wrong = unknown = 0
    paired: dict[tuple[str, str], set[str]] = {}
    pair_sets = snap.pair_sets(status="confirmed")
    for ps in pair_sets:
        a, b = ps["radar_a"], ps["radar_b"]
        good = paired.setdefault((a, b), set())
        for p in ps["pairs"]:
            ka, kb = (a, p["track_a"]), (b, p["track_b"])
            if ka not in truth_of or kb not in truth_of:
                unknown += 1  # a track no longer in the radar's table
                continue
            ta, tb = truth_of[ka], truth_of[kb]
            if ta is not None and ta == tb:
                correct += 1
                good.add(ta)
            else:
                wrong += 1
    judged = correct + wrong
    print(
        f"  pairs: {correct + wrong + unknown} confirmed; correct {correct} "
        f"({100 * correct / max(judged, 1):.1f}%), "
        f"false {wrong} ({100 * wrong / max(judged, 1):.1f}%), tracks gone {unknown}"
    )
    common = found = 0
    for (a, b), good in paired.items():
        both = confirmed_truths.get(a, set()) & confirmed_truths.get(b, set())
        common += len(both)
        found += len(both & good)
    print(
        f"  pair completeness: {found}/{common} ({100 * found / max(common, 1):.1f}%) of the aircraft with "
        f"confirmed tracks on both radars of the {len(paired)} correlated pairs have a correct confirmed pair"
    )

    periods = {r.radar_id: r.scan_period_s for r in sc.radars}
    rows = []
    for rid in sorted(truth.seen):
        recent = truth.end_time_s - STILL_SEEN_SCANS * periods.get(rid, 5.0)
        eligible = {
            tid
            for tid, (first, last) in truth.seen[rid].items()
            if last - first > SEEN_FOR_S and last >= recent
        }
        have = len(eligible & confirmed_truths.get(rid, set()))
        rows.append((rid, have, len(eligible)))
    have_all = sum(h for _, h, _ in rows)
    elig_all = sum(e for _, _, e in rows)
    worst = min(rows, key=lambda x: x[1] / max(x[2], 1)) if rows else ("-", 0, 0)
    print(
        f"  track completeness: {have_all}/{elig_all} ({100 * have_all / max(elig_all, 1):.1f}%) of "
        "the aircraft "
        f"seen > {SEEN_FOR_S:.0f} s and still seen have a confirmed track of that radar "
        f"(worst radar {worst[0]}: {100 * worst[1] / max(worst[2], 1):.1f}%)"
    )

    est = {b["radar_id"]: b for b in snap.biases()}
    print(
        "  biases (estimate - truth): radar  range m  az deg  el deg   | truth range m  az deg  el deg  pairs"
    )
    errs = []
    for r in sc.radars:
        b = est.get(r.radar_id)
        true = (r.range_bias_m, r.azimuth_bias_deg, r.elevation_bias_deg)
        if b is None:
            print(f"    {r.radar_id:>5}  no estimate")
            continue
        e = (
            b["range_bias_m"] - true[0],
            b["azimuth_bias_deg"] - true[1],
            b["elevation_bias_deg"] - true[2],
        )
        errs.append(e)
        print(
            f"    {r.radar_id:>5} {e[0]:8.0f} {e[1]:7.3f} {e[2]:7.3f}   | {true[0]:13.0f} {true[1]:7.2f} "
            f"{true[2]:7.2f} {b['pairs_used']:6d}"
        )
    if errs:
        rms = np.sqrt(np.mean(np.square(errs), axis=0))
        print(f"    RMS   {rms[0]:8.0f} {rms[1]:7.3f} {rms[2]:7.3f}   over {len(errs)} radars")


# -- modes -------------------------------------------------------------------------------------
def header(sc: Scenario, stream: Stream, truth: Truth, seed: int, what: str) -> float:
    data_s = float(sc.duration_s or 0.0)
    periods = sorted({r.scan_period_s for r in sc.radars})
    print(
        f"national: {len(sc.radars)} radars (scans {periods[0]:g}-{periods[-1]:g} s), {sc.targets} aircraft, "
        f"{data_s:.0f} data s, seed {seed}: {len(stream)} msgs, {truth.plots:,} plots "
        f"({truth.plots / max(data_s, 1e-9):,.0f} plots/s), {truth.payload_bytes / 1e6:.0f} MB of "
        "JSON held in memory"
    )
    print(
        f"measured: {what}; the simulator's cost is excluded; cpus {os.cpu_count()}, python "
        f"{sys.version.split()[0]}"
    )
    return data_s


def run_inprocess(args: argparse.Namespace) -> None:
    sc = scenario(args.duration)
    stream = make_stream(sc, args.seed, args.cache)
    truth = survey(stream)
    data_s = header(
        sc,
        stream,
        truth,
        args.seed,
        f"one Engine in this process fed as fast as it goes, snapshot every {args.snapshot_every} msgs "
        f"(as the node's worker when it lags); full pipeline vs tracking alone (max_site_distance_m=0), "
        f"interleaved x{args.repeat}",
    )
    print(f"RSS after generating the stream: {rss_mb():.0f} MB")
    configs: list[tuple[str, EngineConfig]] = [
        ("full pipeline", EngineConfig()),
        ("tracking alone", tracking_alone_config()),
    ]
    if args.full_only:
        configs = configs[:1]
    results: dict[str, list[RunResult]] = {}
    for rep in range(args.repeat):
        for label, config in configs:
            gc.collect()
            r = feed(Engine(config), stream, args.snapshot_every, f"{label} #{rep + 1}", data_s)
            report_run(r, data_s, truth, stream)
            if label == "full pipeline" and rep == args.repeat - 1:
                accuracy(r.final, sc, truth)
            elif label == "tracking alone" and r.corr_updates:
                print("  WARNING: the correlation stage ran; tracking alone is not alone")
            results.setdefault(label, []).append(r)
            r.final = None  # type: ignore[assignment]  # free the engine's state before the next run
            gc.collect()
    if len(results) == 2:
        full, alone = results["full pipeline"], results["tracking alone"]
        ratio_wall = [f.wall_s / a.wall_s for f, a in zip(full, alone, strict=True)]
        ratio_ingest = [f.ingest_s / a.ingest_s for f, a in zip(full, alone, strict=True)]
        print(
            f"full / tracking alone: wall {', '.join(f'{x:.2f}' for x in ratio_wall)}; "
            f"engine only {', '.join(f'{x:.2f}' for x in ratio_ingest)}"
        )
    print(f"peak RSS {peak_rss_mb():.0f} MB (this process, stream included)")


def run_profile(args: argparse.Namespace) -> None:
    sc = scenario(args.duration)
    stream = make_stream(sc, args.seed, args.cache)
    truth = survey(stream)
    data_s = header(
        sc,
        stream,
        truth,
        args.seed,
        "the full pipeline in process under cProfile (slower than without), snapshot every "
        f"{args.snapshot_every} msgs",
    )
    engine = Engine(EngineConfig())
    profiler = cProfile.Profile()
    profiler.enable()
    r = feed(engine, stream, args.snapshot_every, "profile", data_s)
    profiler.disable()
    report_run(r, data_s, truth, stream)
    for order in ("cumulative", "tottime"):
        print(f"--- top {args.top} by {order} ---")
        pstats.Stats(profiler, stream=sys.stdout).strip_dirs().sort_stats(order).print_stats(args.top)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(predicate: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


def run_zenoh(args: argparse.Namespace) -> None:
    import zenoh

    from service.transport.node import ServiceNode
    from service.transport.session import ZenohOptions, open_session

    sc = scenario(args.duration)
    stream = make_stream(sc, args.seed, args.cache)
    truth = survey(stream)
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    data_s = header(
        sc,
        stream,
        truth,
        args.seed,
        f"a ServiceNode in router mode on {endpoint} (multicast scouting off), a client session publishing "
        "with CongestionControl.BLOCK as fast as the node takes it; wall from the first put to the last "
        "message processed; snapshots as the node takes them (after each message while it keeps up)",
    )
    node = ServiceNode(EngineConfig(), ZenohOptions(mode="router", listen=(endpoint,)))
    snaps: list[float] = []
    original_snapshot = node.engine.snapshot

    def timed_snapshot() -> Snapshot:
        t0 = time.perf_counter()
        try:
            return original_snapshot()
        finally:
            snaps.append(time.perf_counter() - t0)

    setattr(node.engine, "snapshot", timed_snapshot)  # noqa: B010 (an instance attribute over the method)
    probe = Probe(node.engine)
    node.start()
    client = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
    publishers: dict[str, Any] = {}
    subscribers: list[Any] = []
    outputs: dict[str, list[int]] = {}  # output kind -> [messages, bytes] received by the client
    try:
        if args.subscribe:
            # The node encodes and puts an output only when a subscriber matches its key: without
            # one, that part of its work is not measured.
            keys = node.keys
            for kind, expr in (
                ("tracks", keys.tracks("*")),
                ("pairs", keys.pairs_all),
                ("errors", keys.errors),
            ):
                counter = outputs.setdefault(kind, [0, 0])

                def on_sample(sample: Any, counter: list[int] = counter) -> None:
                    counter[0] += 1
                    counter[1] += len(sample.payload.to_bytes())

                subscribers.append(client.declare_subscriber(expr, on_sample))
            time.sleep(1.0)  # let the subscriptions reach the node through the router
        first_key = stream[0][0]
        publishers[first_key] = client.declare_publisher(
            first_key,
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        if not _wait(lambda: bool(publishers[first_key].matching_status.matching), 15.0):
            print("the node's subscriber never matched; giving up")
            return
        rss_before = rss_mb()
        last_progress = time.monotonic()
        t_start = time.perf_counter()
        for i, (key, payload) in enumerate(stream):
            pub = publishers.get(key)
            if pub is None:
                pub = publishers[key] = client.declare_publisher(
                    key,
                    encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    reliability=zenoh.Reliability.RELIABLE,
                )
            pub.put(payload)
            if time.monotonic() - last_progress >= PROGRESS_PERIOD_S:
                last_progress = time.monotonic()
                print(
                    f"# zenoh: published {i + 1}/{len(stream)}, node processed {node.processed}, "
                    f"queue {node.queue.qsize()}",
                    file=sys.stderr,
                    flush=True,
                )
        published_s = time.perf_counter() - t_start

        def done() -> bool:
            if time.monotonic() - done_progress[0] >= PROGRESS_PERIOD_S:
                done_progress[0] = time.monotonic()
                print(f"# zenoh: node processed {node.processed}/{len(stream)}", file=sys.stderr, flush=True)
            return node.processed >= len(stream) and node.queue.empty()

        done_progress = [time.monotonic()]
        finished = _wait(done, 24 * 3600.0)
        wall = time.perf_counter() - t_start
        node.stop(timeout_s=600.0)  # flushes the engine and takes the final snapshot
        status = node.status()
        if subscribers:  # the last outputs are on their way: wait until the counts settle
            settled = [-1]

            def quiet() -> bool:
                total = sum(c[0] for c in outputs.values())
                time.sleep(0.5)
                was, settled[0] = settled[0], total
                return total == was

            _wait(quiet, 30.0)
    finally:
        for sub in subscribers:
            with contextlib.suppress(Exception):  # session already gone: nothing to undeclare
                sub.undeclare()
        for pub in publishers.values():
            with contextlib.suppress(Exception):  # session already gone: nothing to undeclare
                pub.undeclare()
        client.close()
        node.stop()
    final = node.snapshot
    snap_a = np.asarray(snaps)
    print(f"[zenoh] {'all' if finished else 'NOT all'} {len(stream)} messages processed")
    print(
        f"  real time x{data_s / wall:.2f} through Zenoh ({wall:.1f} s wall for {data_s:.0f} data "
        "s; the publisher "
        f"was done after {published_s:.1f} s); {truth.plots / wall:,.0f} plots/s, "
        f"{len(stream) / wall:.0f} msgs/s"
    )
    ms = np.asarray(probe.updates_ms)
    print(
        f"  correlation: {final.correlation.get('updates')} updates; per update (all, probe) p50 "
        f"{pct(ms, 50):.2f} ms, "
        f"p99 {pct(ms, 99):.1f} ms; stage total {probe.stage_s:.1f} s = "
        f"{100 * probe.stage_s / wall:.0f}% of wall"
    )
    if snap_a.size:
        print(
            f"  snapshots: {snap_a.size} taken by the node, mean {1e3 * snap_a.mean():.1f} ms, p99 "
            f"{1e3 * pct(snap_a, 99):.1f} ms, total {snap_a.sum():.1f} s = "
            f"{100 * snap_a.sum() / wall:.0f}% of wall"
        )
    q = status["queue"]
    print(f"  queue: high water {q['high_water']}/{q['capacity']}, dropped {q['dropped']}")
    if args.subscribe:
        received = ", ".join(f"{n} {kind} ({b / 1e6:.1f} MB)" for kind, (n, b) in outputs.items())
        print(f"  outputs received by a subscriber: {received}")
    else:
        print("  outputs: no subscriber (the node skips encoding them; --subscribe to count them)")
    core = final.status_core()
    print(
        f"  end: {core['pairs_confirmed']} confirmed pairs, rejected {core['rejected'] or 0}; RSS "
        f"{rss_before:.0f} -> {rss_mb():.0f} MB, peak {peak_rss_mb():.0f} MB (node, client and "
        "stream in one process)"
    )
    accuracy(final, sc, truth)


def run_soak(args: argparse.Namespace) -> None:
    sc = scenario(None)
    minutes = float(args.soak_minutes)
    print(
        f"national soak: {len(sc.radars)} radars, {sc.targets} aircraft, never-ending stream (seed "
        f"{args.seed}) generated {args.chunk} msgs at a time, fed to one Engine in process as fast "
        f"as it goes for {minutes:g} wall minutes, snapshot every {args.snapshot_every} msgs; one "
        "line per wall minute ('x rt': data s per wall s of the engine, generation excluded)"
        + ("; tracemalloc on (slows the engine)" if args.trace_memory else "")
    )
    print(
        f"{'min':>5} {'data s':>8} {'x rt':>6} {'RSS MB':>8} {'peak MB':>8} {'window':>9} "
        f"{'tracks':>7} {'pairs':>7}"
    )
    engine = Engine(EngineConfig())
    messages = wire_messages(sc, args.seed)  # lazy: the generator keeps no history
    start = time.monotonic()
    next_line = start + 60.0
    count = 0
    series: list[tuple[float, float]] = []  # (elapsed minutes, RSS MB)
    last_data, last_engine_s, engine_s = 0.0, 0.0, 0.0
    traced: Any = None
    if args.trace_memory:
        # traced from the start: a block allocated before tracing and freed later would not
        # count as a decrease, and the growth would be overstated
        tracemalloc.start(1)

    def data_time() -> float:
        clocks = [r["last_time_s"] for r in engine.snapshot().status_core()["radars"] if r["last_time_s"]]
        return max(clocks) - sc.start_time_s if clocks else 0.0

    while time.monotonic() - start < 60.0 * minutes:
        chunk = list(itertools.islice(messages, args.chunk))
        t0 = time.monotonic()
        for key, payload in chunk:
            engine.ingest(key, payload, receive_time_s=0.0)
            count += 1
            if args.snapshot_every > 0 and count % args.snapshot_every == 0:
                engine.snapshot()
        now = time.monotonic()
        engine_s += now - t0
        if args.trace_memory and traced is None and now - start >= 30.0 * minutes:
            traced = tracemalloc.take_snapshot()
        if now >= next_line:
            next_line += 60.0
            core = engine.snapshot().status_core()
            data = data_time()
            rt = (data - last_data) / max(engine_s - last_engine_s, 1e-9)
            last_data, last_engine_s = data, engine_s
            rss = rss_mb()
            elapsed = (now - start) / 60.0
            series.append((elapsed, rss))
            window = sum(r["window_plots"] for r in core["radars"])
            tracks = sum(r["tracks_confirmed"] + r["tracks_tentative"] for r in core["radars"])
            print(
                f"{elapsed:5.1f} {data:8.0f} {rt:6.2f} {rss:8.0f} {peak_rss_mb():8.0f} {window:9d} "
                f"{tracks:7d} {core['pairs_confirmed']:7d}",
                flush=True,
            )
    print("RSS series (min, MB): " + ", ".join(f"({m:.0f}, {r:.0f})" for m, r in series))
    half = [(m, r) for m, r in series if m >= minutes / 2]
    if len(half) >= 2:
        x, y = np.array(half).T
        slope = np.polyfit(x, y, 1)[0] * 60.0
        print(f"RSS slope over the second half: {slope:+.1f} MB/h ({len(half)} points)")
    else:
        print("RSS slope: too few points in the second half (run longer)")
    if traced is not None:
        growth = tracemalloc.take_snapshot().compare_to(traced, "lineno")
        total = sum(g.size_diff for g in growth) / 1e6
        print(f"Python heap growth over the second half (tracemalloc): {total:+.1f} MB; top lines:")
        for g in growth[:10]:
            print(f"  {g.size_diff / 1e6:+8.1f} MB {g.count_diff:+8d} blocks  {g.traceback[0]}")
    if args.trace_memory:
        tracemalloc.stop()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--duration", type=float, default=120.0, help="data seconds of the stream (default 120)"
    )
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cache", type=Path, help="pickle file keeping the generated stream between runs")
    parser.add_argument("--repeat", type=int, default=1, help="full / tracking-alone pairs, interleaved")
    parser.add_argument("--full-only", action="store_true", help="skip the tracking-alone run")
    parser.add_argument("--snapshot-every", type=int, default=64, help="messages between snapshots (0: none)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--zenoh", action="store_true", help="through a ServiceNode over Zenoh on loopback")
    parser.add_argument("--subscribe", action="store_true", help="zenoh: a subscriber to the node's outputs")
    mode.add_argument("--profile", action="store_true", help="the in-process full pipeline under cProfile")
    mode.add_argument(
        "--soak-minutes", type=float, help="feed a never-ending stream for this many wall minutes"
    )
    parser.add_argument("--top", type=int, default=25, help="functions listed per profile order")
    parser.add_argument("--chunk", type=int, default=512, help="messages generated at a time in the soak")
    parser.add_argument(
        "--trace-memory", action="store_true", help="soak: where the Python heap grows over the second half"
    )
    args = parser.parse_args()
    if args.zenoh:
        run_zenoh(args)
    elif args.profile:
        run_profile(args)
    elif args.soak_minutes is not None:
        run_soak(args)
    else:
        run_inprocess(args)


if __name__ == "__main__":
    main()
