"""National-scale benchmark: the ``national`` scenario (12 radars, 1 500 aircraft) through the engine.

Prints figures, never asserts.  The simulated stream is generated before any clock starts
(the simulator's cost is excluded; ``--cache FILE`` keeps it between runs).  Modes:

* default, in process: the stream through an ``Engine`` as fast as it goes, with
  ``engine.snapshot()`` taken every ``--snapshot-every`` messages as the service node's worker
  does when it lags (service/transport/node.py); each run in a fresh process of its own (this
  file with a hidden option, reading the stream from ``--cache`` or a temporary file), so that
  a run's peak RSS is its own.  Three variants side by side in the same run, interleaved (A,
  B, C, A, B, C, ... with ``--repeat N``) because the machine is noisy: A, tracking alone
  (``max_site_distance_m=0``: no two sites are that close and the scenario has no AIS source,
  so no pair is ever correlated); B, the full pipeline in one process; C, the full pipeline
  with the correlation stage in a child process (``Engine(config, correlation_process=True)``,
  as the service node runs it by default).  Per variant: x real time, plots/s, the time of
  full / tracking alone, correlation update p50/p99 (B: every update, timed by a probe on the
  stage; C: the child's own figures in ``snapshot.correlation``, its last 2 048 updates),
  peak RSS of the run (C: parent and child), CPU time, and the cores other jobs took.  Then
  the accuracy of the last B run, whether C found the same pairs and biases, and a block of
  rows for the performance table of docs/results.md.
* ``--zenoh``: a ``ServiceNode`` in router mode on a free loopback port (multicast scouting
  off), its correlation in a child process as the service runs it (``--one-process``: in the
  node's process), and a client session publishing the stream with ``CongestionControl.BLOCK``
  as fast as the node takes it (as a replay at ``--speed 0`` does), until the node has
  processed every message; per message, its ingest stall (the time in ``Engine.ingest`` on the
  node's worker, waits for the correlation process included: p50, p99, max), and the CPU of
  correlation and fusion (the correlation process and the system tracks drawn on the node)
  over the rest of the node's, over the whole run and over its settled part;
  ``--subscribe`` adds a subscriber to its tracks, pairs and errors.
* ``--profile``: the in-process run (B) under cProfile; top functions by cumulative and own time.
* ``--breakdown``: the in-process run (B) with a wall-clock timer on each part of the stages
  (no profiler's overhead): where the settled part's time goes (prompt decisions, full pair
  updates, system-track rebuilds, bias solves, cycles, views; tracking), seconds, calls and
  milliseconds a call, and the process's CPU over the settled part.
* ``--soak-minutes M``: a never-ending stream, generated in chunks, fed for M wall minutes to an
  engine with its correlation process (``--one-process``: without).  The stream is the national
  scenario with ``respawn="uniform"``: with the scenario's own respawn at the area's edge the
  aircraft gather towards the centre over the first hour (more of them within radar cover, more
  tracks and pairs: a drift that looks like a leak), with it the load is stationary.  One line
  per minute (RSS of the process and of the correlation process, window, tracks, pairs, the
  cores other jobs took) and the RSS slopes over the second half.  ``--census`` adds the size of
  the registration memories every minute (rows remembered, buffer written, buffer allocated);
  ``--trace-memory`` also where the Python heap grew over the second half (tracemalloc, in both
  processes) and the C allocator's counts (glibc).  Both run the correlation process's main
  function inside a bench-only wrapper (``traced_serve``) that answers signals with these.

Accuracy (evaluation only: the simulator's ``truth_id`` on the final tracks, which no
algorithm reads): share of confirmed pairs whose two tracks follow the same aircraft, track
completeness (aircraft a radar has seen for more than 30 s and still sees that have a
confirmed track of that radar), pair completeness (aircraft with confirmed tracks on both
radars of a correlated pair that have a correct confirmed pair), and each radar's bias
estimate against the simulator's bias.  ``--explain-false`` records which aircraft's plots
joined each track over time (slows the runs) and classifies every false pair.

Run: .venv/bin/python bench/bench_national.py [--duration 120] [--seed 1] [--repeat 1]
     [--cache FILE] [--explain-false]
     [--zenoh [--subscribe] [--one-process] | --profile | --soak-minutes 30 [--one-process]
     [--census] [--trace-memory]]
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import ctypes
import ctypes.util
import gc
import hashlib
import itertools
import json
import os
import pickle
import pstats
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from checkout import warn_if_elsewhere

from service.config import without_aid
from service.engine import Engine, EngineConfig, Snapshot
from topofusion_lab.evaluation.promptness import OutputMonitor, PromptnessReport, watch_engine
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
#: Where the repository is (paths in the report are printed relative to it).
ROOT = Path(__file__).resolve().parents[1]
#: Set for the correlation process by ``--trace-memory``: where it writes its heap snapshots.
TRACE_DIR_ENV = "TOPOFUSION_BENCH_TRACE_DIR"


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


def settle_index(stream: Stream, start_s: float, settle_s: float) -> int:
    """The first message at or after ``settle_s`` of data time: from it on a run is settled
    (every aircraft of the start tracked and paired; what follows is the steady work)."""
    for i, (_key, payload) in enumerate(stream):
        if json.loads(payload).get("time_s", -np.inf) >= start_s + settle_s:
            return i
    return len(stream)


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


# -- memory and CPU of this process and of the correlation process -----------------------------
def rss_mb() -> float:
    """Resident set size now (Linux ``statm``; 0 where unavailable)."""
    try:
        resident = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0.0
    return resident * os.sysconf("SC_PAGE_SIZE") / 1e6


def peak_rss_mb() -> float:
    """Peak RSS of this process over its whole life so far."""
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb * 1024 / 1e6 if sys.platform != "darwin" else kb / 1e6  # KiB on Linux, bytes on macOS


def proc_status_mb(pid: int | str, key: str) -> float:
    """``VmRSS`` (now) or ``VmHWM`` (peak) of a process from Linux's ``status``; nan if unknown."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024 / 1e6  # kB (KiB)
    except (OSError, IndexError, ValueError):
        pass
    return float("nan")


def reset_peak() -> bool:
    """Reset this process's peak RSS (``VmHWM``) to its RSS now, so a run's peak is its own.

    Linux: writing 5 to ``clear_refs`` resets the high-water mark and nothing else.
    """
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def cpu_s(pid: int | str = "self") -> float:
    """User + system CPU seconds of a process (all its threads) from Linux's ``stat``."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        utime, stime = stat.rsplit(")", 1)[1].split()[11:13]
    except (OSError, IndexError, ValueError):
        return float("nan")
    return (int(utime) + int(stime)) / os.sysconf("SC_CLK_TCK")


def machine_busy_s() -> float:
    """CPU seconds all processes of the machine have used (Linux ``/proc/stat``; nan if unknown).

    Less this benchmark's own CPU time over a run: what other jobs took from it.
    """
    try:
        ticks = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except (OSError, ValueError):
        return float("nan")
    idle = ticks[3] + ticks[4]  # idle, iowait
    return (sum(ticks[:8]) - idle) / os.sysconf("SC_CLK_TCK")  # up to steal; guest is in user


def child_pid(engine: Engine) -> int | None:
    """The pid of the engine's correlation process, None when correlation runs in this one."""
    process = getattr(getattr(engine, "correlation", None), "_process", None)
    pid = getattr(process, "pid", None)
    return pid if isinstance(pid, int) else None


def wait_ready(engine: Engine) -> float:
    """Wait until the correlation process (if any) answers; the seconds it took.

    A fresh interpreter imports the service before it reads its pipe: that start-up is not part
    of the throughput.  An empty engine's ``flush`` releases nothing and asks the stage to
    finish (nothing to solve), which the child answers once it runs.
    """
    t0 = time.perf_counter()
    if child_pid(engine) is not None:
        engine.flush()
    return time.perf_counter() - t0


# -- probes on the engine (bench only; fall back to the snapshot's figures) --------------------
def correlation_stage(engine: Engine) -> Any:
    """The engine's correlation stage when it runs in this process (an attribute with
    ``update``, ``updates``, ``timings_ms``), else None."""
    stage = getattr(engine.correlation, "stage", None)
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
    thread that made it.  When the stage runs in a child process (or cannot be found) the probe
    records nothing and the report takes the snapshot's figures, saying so.
    """

    def __init__(self, engine: Engine) -> None:
        self.updates_ms: list[float] = []
        self.bias_ms: list[float] = []
        self.system_ms: list[float] = []
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
        # The system tracks' rebuild (contract 4.4): drawn as the engine takes the stage's
        # answers (service/pipeline/system_stage.py SystemDrawer), part of stage_s too.
        drawer = getattr(engine.correlation, "drawer", None)
        draw = getattr(drawer, "draw", None)
        if callable(draw):

            def timed_draw(*a: Any, **k: Any) -> Any:
                t0 = time.perf_counter()
                try:
                    return draw(*a, **k)
                finally:
                    dt = time.perf_counter() - t0
                    self.system_ms.append(1e3 * dt)
                    self.stage_s += dt

            setattr(drawer, "draw", timed_draw)  # noqa: B010 (as below)

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


class Backpressure:
    """How long the engine's thread waited for the correlation process.

    The engine sends the child at most a fixed number of messages it has not answered yet; when
    correlation falls behind, the next send waits (service/pipeline/correlation_process.py).
    The probe times those waits (bench only: it wraps the bound's ``acquire``); nan when the
    correlation runs in this process.
    """

    def __init__(self, engine: Engine) -> None:
        self.wait_s = float("nan")
        self.waits = 0
        slots = getattr(getattr(engine, "correlation", None), "_slots", None)
        original = getattr(slots, "acquire", None)
        if child_pid(engine) is None or not callable(original):
            return
        self.wait_s = 0.0

        def acquire(*a: Any, **k: Any) -> Any:
            if original(False):  # a free slot: no wait
                return True
            t0 = time.perf_counter()
            try:
                return original(*a, **k)
            finally:
                self.wait_s += time.perf_counter() - t0
                self.waits += 1

        setattr(slots, "acquire", acquire)  # noqa: B010 (an instance attribute over the method)


# -- the truth of each track over time (evaluation only, --explain-false) ----------------------
def record_truth_history() -> bool:
    """Record, per tracker and track uid, the runs of plots of one aircraft that joined it.

    Wraps the tally of ``truth_id`` labels (service/evaluation/truth.py: outside the tracker, which
    never reads them): after each update, each track's joined plots extend its runs
    ``[truth_id, first time, last time, plots]``, kept on the tracker object.
    """
    try:
        from service.evaluation.truth import TruthLabelledTracker
    except ImportError:
        return False
    original = TruthLabelledTracker.update

    def update(self: Any, plots: Any, time_s: float) -> None:
        original(self, plots, time_s)
        runs: dict[int, list[list[Any]]] = self.__dict__.setdefault("bench_truth_runs", {})
        for uid, joined in self.inner.joined:
            order = np.argsort(joined.time_s, kind="stable")
            for u, tid, t in zip(
                np.asarray(uid)[order].tolist(),
                joined.truth_id[order].tolist(),
                joined.time_s[order].tolist(),
                strict=True,
            ):
                track = runs.setdefault(u, [])
                if track and track[-1][0] == tid:
                    track[-1][2] = t
                    track[-1][3] += 1
                else:
                    track.append([tid, t, t, 1])

    setattr(TruthLabelledTracker, "update", update)  # noqa: B010 (the class's method, bench only)
    return True


# -- one in-process run ------------------------------------------------------------------------
@dataclass(frozen=True)
class Variant:
    key: str
    label: str
    config: EngineConfig
    process: bool


def no_history_config() -> EngineConfig:
    """The full pipeline without the pairs' history evidence (every update decides alone)."""
    cfg = EngineConfig()
    corr = replace(cfg.correlation, evidence=replace(cfg.correlation.evidence, enabled=False))
    return replace(cfg, correlation=corr)


def unaided_config() -> EngineConfig:
    """The full pipeline with the aid of association off (``tracking.aid``, on by default)."""
    return without_aid(EngineConfig())


def all_variants() -> list[Variant]:
    return [
        Variant("A", "tracking alone", tracking_alone_config(), False),
        Variant("B", "full, one process", EngineConfig(), False),
        Variant("C", "full, correlation process", EngineConfig(), True),
        Variant("H", "full, one process, no history evidence", no_history_config(), False),
        Variant("E", "full, correlation process, no aid of association", unaided_config(), True),
    ]


def variants(full_only: bool, history_ab: bool = False, aid_ab: bool = False) -> list[Variant]:
    """The runs compared side by side; ``history_ab``: B against H, the same without the
    history evidence (what the evidence costs and gives); ``aid_ab``: C against E, the same
    without the aid of association (what the aid costs and gives)."""
    out = all_variants()
    if history_ab:
        return [out[1], out[3]]
    if aid_ab:
        return [out[2], out[4]]
    return out[1:3] if full_only else out[:3]


@dataclass
class RunResult:
    label: str
    process: bool
    wall_s: float  # ingest + flush + snapshots
    ingest_s: float  # ingest + flush
    drain_s: float  # the final flush (C: waiting for the child's last answers)
    startup_s: float  # C: the child's start-up, not timed
    snapshot_s: list[float]
    ingest_ms: np.ndarray
    updates_ms: np.ndarray
    bias_ms: np.ndarray
    system_ms: np.ndarray
    stage_s: float
    wait_s: float  # C: the engine waiting for the child (bounded messages in flight)
    waits: int
    final: Snapshot
    final_snapshot_s: float
    rss_before_mb: float
    rss_after_mb: float
    peak_mb: float  # this process over the run (or its whole life, where it cannot be reset)
    peak_is_run: bool
    child_peak_mb: float
    child_rss_mb: float
    cpu_s: float
    child_cpu_s: float
    #: CPU s of the system-track rebuilds in this process (the engine's thread; with the
    #: correlation process they are drawn here, beside its pair updates).
    draw_cpu_s: float
    others_cpu_s: float  # other processes of the machine over the run
    corr_updates: int
    correlation: dict[str, Any]  # the final snapshot's timings
    restarts: int = 0
    settled_wall_s: float = float("nan")  # from the settle message to the end (flush included)
    settled_data_s: float = float("nan")

    def corr_p(self) -> tuple[float, float, str]:
        """Correlation per update p50, p99 and where they come from."""
        if self.updates_ms.size:
            return (
                pct(self.updates_ms, 50),
                pct(self.updates_ms, 99),
                f"probe, all {self.updates_ms.size} updates",
            )
        corr = self.correlation
        n = min(self.corr_updates, 2048)
        return (
            float(corr.get("p50_ms", np.nan)),
            float(corr.get("p99_ms", np.nan)),
            f"{'child' if self.process else 'stage'}'s snapshot.correlation, last {n} updates",
        )


def result_digest(snap: Snapshot) -> str:
    """The confirmed pairs and the biases, to compare two runs' results."""
    pairs = sorted(
        (ps["radar_a"], ps["radar_b"], p["track_a"], p["track_b"])
        for ps in snap.pair_sets(status="confirmed")
        for p in ps["pairs"]
    )
    names = ("radar_id", "range_bias_m", "azimuth_bias_deg", "elevation_bias_deg")
    biases = sorted(tuple(b[n] for n in names) for b in snap.biases())
    return hashlib.sha256(repr((pairs, biases)).encode()).hexdigest()[:16]


def feed(
    engine: Engine,
    stream: Stream,
    snapshot_every: int,
    label: str,
    data_s: float,
    process: bool,
    startup_s: float = 0.0,
    settle: tuple[int, float] = (0, 0.0),
) -> RunResult:
    """``settle``: the message index from which the run is settled, and its data time left."""
    probe = Probe(engine)
    waits = Backpressure(engine)
    pid = child_pid(engine)
    rss_before = rss_mb()
    peak_is_run = reset_peak()
    cpu0, child_cpu0, busy0 = cpu_s(), cpu_s(pid) if pid else 0.0, machine_busy_s()
    ingest_ms = np.empty(len(stream))
    snaps: list[float] = []
    ingest_s = 0.0
    last_progress = time.monotonic()
    t_start = time.perf_counter()
    t_settled = t_start
    for i, (key, payload) in enumerate(stream):
        if i == settle[0]:
            t_settled = time.perf_counter()
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
    drain_s = time.perf_counter() - t0
    ingest_s += drain_s
    wall = time.perf_counter() - t_start
    t0 = time.perf_counter()
    final = engine.snapshot()
    final_snapshot_s = time.perf_counter() - t0
    # The child answered every message (flush waits for it): its peak is the run's.
    child_peak = proc_status_mb(pid, "VmHWM") if pid else float("nan")
    child_rss = proc_status_mb(pid, "VmRSS") if pid else float("nan")
    child_cpu = cpu_s(pid) - child_cpu0 if pid else 0.0
    own_cpu = cpu_s() - cpu0
    others = machine_busy_s() - busy0 - own_cpu - child_cpu
    return RunResult(
        label=label,
        process=process,
        wall_s=wall,
        ingest_s=ingest_s,
        drain_s=drain_s,
        startup_s=startup_s,
        snapshot_s=snaps,
        ingest_ms=ingest_ms,
        updates_ms=np.asarray(probe.updates_ms),
        bias_ms=np.asarray(probe.bias_ms),
        system_ms=np.asarray(probe.system_ms),
        stage_s=probe.stage_s,
        wait_s=waits.wait_s,
        waits=waits.waits,
        final=final,
        final_snapshot_s=final_snapshot_s,
        rss_before_mb=rss_before,
        rss_after_mb=rss_mb(),
        peak_mb=proc_status_mb("self", "VmHWM") if peak_is_run else peak_rss_mb(),
        peak_is_run=peak_is_run,
        child_peak_mb=child_peak,
        child_rss_mb=child_rss,
        cpu_s=own_cpu,
        child_cpu_s=child_cpu,
        draw_cpu_s=float(getattr(getattr(engine.correlation, "drawer", None), "cpu_s", 0.0)),
        others_cpu_s=max(others, 0.0),
        corr_updates=int(final.correlation.get("updates", 0)),
        correlation=dict(final.correlation),
        restarts=int(getattr(engine.correlation, "restarts", 0)),
        settled_wall_s=time.perf_counter() - t_settled - final_snapshot_s,
        settled_data_s=settle[1],
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


def memory_line(r: RunResult) -> str:
    peak = f"peak {r.peak_mb:.0f} MB" + ("" if r.peak_is_run else " (this process's life so far)")
    line = f"  RSS {r.rss_before_mb:.0f} -> {r.rss_after_mb:.0f} MB over the run, {peak}"
    if r.process:
        line += (
            f"; correlation process: peak {r.child_peak_mb:.0f} MB, {r.child_rss_mb:.0f} MB at the end; "
            f"together {r.peak_mb + r.child_peak_mb:.0f} MB at most"
        )
    return line + " (the stream in memory included)"


def report_run(r: RunResult, data_s: float, truth: Truth, stream: Stream) -> None:
    messages = len(stream)
    snaps = np.asarray(r.snapshot_s)
    print(f"[{r.label}]")
    print(
        f"  real time x{data_s / r.wall_s:.2f} with snapshots, x{data_s / r.ingest_s:.2f} engine only "
        f"({r.wall_s:.1f} s wall for {data_s:.0f} data s); {truth.plots / r.wall_s:,.0f} plots/s, "
        f"{messages / r.wall_s:.0f} msgs/s"
    )
    if np.isfinite(r.settled_data_s) and r.settled_data_s > 0:
        print(
            f"  settled: x{r.settled_data_s / r.settled_wall_s:.2f} real time over the last "
            f"{r.settled_data_s:.0f} data s ({r.settled_wall_s:.1f} s wall)"
        )
    if r.updates_ms.size and np.isfinite(r.stage_s) and r.stage_s < r.wall_s:
        print(
            f"  CPU of correlation and fusion over the rest (tracking, decoding): "
            f"{r.stage_s / (r.wall_s - r.stage_s):.2f} "
            f"(stage {r.stage_s:.1f} s, rest {r.wall_s - r.stage_s:.1f} s)"
        )
    elif r.process and r.cpu_s > r.draw_cpu_s:
        fusion, rest = r.child_cpu_s + r.draw_cpu_s, r.cpu_s - r.draw_cpu_s
        print(
            f"  CPU of correlation and fusion (the correlation process, and the system-track "
            f"rebuilds here) over the rest (tracking, decoding): {fusion / rest:.2f} "
            f"({r.child_cpu_s:.1f} + {r.draw_cpu_s:.1f} s / {rest:.1f} s)"
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
        p50, p99, source = r.corr_p()
        if r.updates_ms.size:
            stage = (
                f"{r.stage_s:.1f} s = {100 * r.stage_s / r.wall_s:.0f}% of wall"
                if np.isfinite(r.stage_s)
                else "n/a"
            )
            print(
                f"  correlation: {r.corr_updates} updates; per update ({source}) p50 {p50:.2f} ms, "
                f"p99 {p99:.1f} ms, max {pct(r.updates_ms, 100):.1f} ms "
                f"(snapshot's last 2048: p50 {corr.get('p50_ms')} ms, p99 {corr.get('p99_ms')} ms); "
                f"stage total {stage}"
            )
        else:
            print(
                f"  correlation: {r.corr_updates} updates; per update ({source}) p50 {p50:.2f} ms, "
                f"p99 {p99:.1f} ms"
            )
        if r.bias_ms.size:
            print(
                f"  bias solves (inside the stage): {r.bias_ms.size}, p50 {pct(r.bias_ms, 50):.0f} ms, "
                f"max {r.bias_ms.max():.0f} ms, total {r.bias_ms.sum() / 1e3:.1f} s"
            )
        if r.system_ms.size:
            n_sys = len(r.final.system.number) if r.final.system is not None else 0
            print(
                f"  system track rebuilds (drawn as the answers are taken): {r.system_ms.size}, p50 "
                f"{pct(r.system_ms, 50):.1f} ms, max {r.system_ms.max():.1f} ms, total "
                f"{r.system_ms.sum() / 1e3:.1f} s; {n_sys} system tracks at the end"
            )
    else:
        print("  correlation: no update (as intended for tracking alone)")
    if r.process:
        print(
            f"  correlation process: started in {r.startup_s:.1f} s (not timed); the engine waited "
            f"{r.wait_s:.1f} s for it ({r.waits} times at the bound of messages in flight) and "
            f"{r.drain_s:.1f} s for its last answers at the end; restarts {r.restarts}"
        )
    cpu = f"  CPU: this process {r.cpu_s:.1f} s"
    if r.process:
        cpu += f", correlation process {r.child_cpu_s:.1f} s"
    print(
        f"{cpu} over {r.wall_s:.1f} s wall ({(r.cpu_s + r.child_cpu_s) / r.wall_s:.2f} cores busy); "
        f"other jobs on the machine {r.others_cpu_s / r.wall_s:.2f} cores"
    )
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
    print(memory_line(r))


# -- accuracy (evaluation only: truth_id) --------------------------------------------------------
def accuracy(snap: Snapshot, sc: Scenario, truth: Truth) -> dict[str, Any]:
    """Prints the accuracy section; returns its headline figures."""
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
    rms = np.full(3, np.nan)
    if errs:
        rms = np.sqrt(np.mean(np.square(errs), axis=0))
        print(f"    RMS   {rms[0]:8.0f} {rms[1]:7.3f} {rms[2]:7.3f}   over {len(errs)} radars")
    return {
        "pairs": correct + wrong + unknown,
        "correct_pct": 100 * correct / max(judged, 1),
        "false": wrong,
        "pair_completeness_pct": 100 * found / max(common, 1),
        "track_completeness_pct": 100 * have_all / max(elig_all, 1),
        "bias_rms": tuple(float(x) for x in rms),
    }


def explain_false(engine: Engine, snap: Snapshot, sc: Scenario) -> None:
    """Each false confirmed pair: which aircraft's plots joined each of its two tracks, when.

    A track's ``truth_id`` is the aircraft with the most plots in it over its whole life, so a
    pair can be judged false although both tracks follow the same aircraft now (one of them
    followed another aircraft for longer before), or right although they no longer do.  The
    classes, from the runs of plots recorded by ``record_truth_history``:

    * same aircraft now: the last plot of both tracks is of the same aircraft (an artefact of
      the majority label);
    * coasting: a track had no plot for more than 3 of its radar's scans (its aircraft left the
      radar's cover or another track took its plots) and the other follows another aircraft;
    * swapped: both tracks follow one aircraft each now, different ones, and one of the two
      followed the other's aircraft at some point (a crossing);
    * different aircraft: neither track ever had a plot of the other's aircraft.
    """
    periods = {r.radar_id: r.scan_period_s for r in sc.radars}
    end = max((t for t, _ in snap.tracks.values()), default=0.0)
    tracks: dict[tuple[str, str], tuple[list[list[Any]], np.ndarray, float]] = {}
    for rid, radar in engine.tracking.tracked.items():
        tracker: Any = radar.tracker
        runs = getattr(tracker, "__dict__", {}).get("bench_truth_runs") if tracker is not None else None
        if runs is None:
            continue
        table = tracker.tracks()
        for tid, uid, pos in zip(
            table.track_id.tolist(), tracker.inner.uids.tolist(), table.position_ecef_m, strict=True
        ):
            track_runs = runs.get(uid, [])
            last = track_runs[-1][2] if track_runs else -np.inf
            tracks[(rid, tid)] = (track_runs, pos, last)
    if not tracks:
        print("  false pairs: no truth history recorded (--explain-false records it)")
        return
    labels = {
        (b["radar_id"], t["track_id"]): t["truth_id"] for b in snap.track_batches("all") for t in b["tracks"]
    }
    by_truth: dict[tuple[str, str | None], list[str]] = {}
    for (rid, tid), lab in labels.items():
        by_truth.setdefault((rid, lab), []).append(tid)

    def runs_text(runs: list[list[Any]]) -> str:
        shown = [
            f"{r[0] or 'clutter'} x{r[3]} {r[1] - T0:.0f}-{r[2] - T0:.0f}s" for r in runs[-4:] if r[3] >= 1
        ]
        return ("... " if len(runs) > 4 else "") + ", ".join(shown)

    classes: dict[str, int] = {}
    lines = []
    for ps in snap.pair_sets(status="confirmed"):
        a, b = ps["radar_a"], ps["radar_b"]
        for p in ps["pairs"]:
            ka, kb = (a, p["track_a"]), (b, p["track_b"])
            la, lb = labels.get(ka), labels.get(kb)
            if ka not in labels or kb not in labels or (la is not None and la == lb):
                continue
            (runs_a, pos_a, last_a), (runs_b, pos_b, last_b) = tracks[ka], tracks[kb]
            now_a = runs_a[-1][0] if runs_a else None
            now_b = runs_b[-1][0] if runs_b else None
            stale_a = end - last_a > STILL_SEEN_SCANS * periods.get(a, 5.0)
            stale_b = end - last_b > STILL_SEEN_SCANS * periods.get(b, 5.0)
            ever_a = {r[0] for r in runs_a}
            ever_b = {r[0] for r in runs_b}
            if now_a is not None and now_a == now_b and not stale_a and not stale_b:
                what = "same aircraft now"
            elif stale_a or stale_b:
                what = "coasting"
            elif (now_b in ever_a) or (now_a in ever_b):
                what = "swapped"
            else:
                what = "different aircraft"
            classes[what] = classes.get(what, 0) + 1
            # radar b's track labelled with radar a's track's aircraft, if any (the pair the
            # labels call right) and how far it is
            right = by_truth.get((b, la), [])
            right_km = (
                min(np.linalg.norm(tracks[(b, t)][1] - pos_a) for t in right if (b, t) in tracks) / 1e3
                if right
                else float("nan")
            )
            lines.append(
                f"    {a}/{p['track_a']} ({la}) ~ {b}/{p['track_b']} ({lb}): {what}; tracks "
                f"{np.linalg.norm(pos_a - pos_b) / 1e3:.1f} km apart"
                + (
                    f", {b}'s track labelled {la} {right_km:.1f} km from {a}'s"
                    if right
                    else f", no track of {b} labelled {la}"
                )
                + f"; last plot {end - last_a:.0f} / {end - last_b:.0f} s before the end\n"
                f"      {a}: {runs_text(runs_a)}\n      {b}: {runs_text(runs_b)}"
            )
    print(
        f"  false pairs explained ({sum(classes.values())}): "
        + (", ".join(f"{n} {k}" for k, n in sorted(classes.items(), key=lambda x: -x[1])) or "none")
    )
    for line in lines:
        print(line)


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
        f"{sys.version.split()[0]}, load average {os.getloadavg()[0]:.2f} at the start"
    )
    return data_s


def command() -> str:
    """The command line that runs this benchmark as it was run."""
    return " ".join(["bench/bench_national.py", *sys.argv[1:]])


def spread(values: list[float], fmt: str) -> str:
    """The median, and the range when there are several values."""
    if len(values) == 1:
        return format(values[0], fmt)
    return f"{format(float(np.median(values)), fmt)} [{format(min(values), fmt)}-{format(max(values), fmt)}]"


def rounded(x: float, digits: int = 2) -> str:
    """A figure for the docs: ``digits`` significant digits, thousands separated by spaces."""
    if not np.isfinite(x):
        return "n/a"
    places = digits - 1 - int(np.floor(np.log10(abs(x)))) if x else 0
    return f"{round(x, places):,.{max(places, 0)}f}".replace(",", " ")


def grouped(n: int) -> str:
    """An integer with its thousands separated by spaces (as the docs write them)."""
    return f"{n:,}".replace(",", " ")


@dataclass
class Summary:
    """What the side-by-side table and the docs rows need of one run (sent as JSON by the
    process that made the run)."""

    key: str
    wall_s: float
    stream_mb: float  # RSS of the run's process once it held the stream, before the engine
    peak_mb: float
    peak_is_run: bool
    child_peak_mb: float
    p50_ms: float
    p99_ms: float
    corr_source: str
    others_cpu_s: float
    digest: str
    accuracy: dict[str, Any] = field(default_factory=dict)
    settled_rt: float = float("nan")


def settle_s(args: argparse.Namespace) -> float:
    """Data time before a run counts as settled (``--settle-s``; default half the stream)."""
    return float(args.settle_s) if args.settle_s is not None else 0.5 * float(args.duration)


def one_run(args: argparse.Namespace) -> None:
    """One variant's run in this (fresh) process; prints its report, then its ``Summary``.

    Each run gets a process of its own so that its peak RSS is its own (a process keeps much
    of the memory a previous engine freed) and no run works on another's leftover heap.
    """
    v = next(x for x in all_variants() if x.key == args.one_run)
    sc = scenario(args.duration)
    stream = make_stream(sc, args.seed, args.cache)
    truth = survey(stream)
    data_s = float(sc.duration_s or 0.0)
    if args.explain_false and not record_truth_history():
        print("--explain-false: no truth tally to record in this engine")
    gc.collect()
    stream_mb = rss_mb()
    engine = Engine(v.config, correlation_process=v.process)
    try:
        startup = wait_ready(engine)
        r = feed(
            engine,
            stream,
            args.snapshot_every,
            f"{v.key} {v.label} #{args.round}",
            data_s,
            v.process,
            startup,
            (settle_index(stream, sc.start_time_s, settle_s(args)), data_s - settle_s(args)),
        )
    finally:
        engine.close()
    report_run(r, data_s, truth, stream)
    if v.key == "A" and r.corr_updates:
        print("  WARNING: the correlation stage ran; tracking alone is not alone")
    figures: dict[str, Any] = {}
    if args.accuracy:
        figures = accuracy(r.final, sc, truth)
        if args.explain_false:
            explain_false(engine, r.final, sc)
    p50, p99, source = r.corr_p()
    summary = Summary(
        key=v.key,
        wall_s=r.wall_s,
        stream_mb=stream_mb,
        peak_mb=r.peak_mb,
        peak_is_run=r.peak_is_run,
        child_peak_mb=r.child_peak_mb,
        p50_ms=p50,
        p99_ms=p99,
        corr_source=source,
        others_cpu_s=r.others_cpu_s,
        digest=result_digest(r.final) if v.key != "A" else "",
        accuracy=figures,
        settled_rt=r.settled_data_s / r.settled_wall_s if r.settled_data_s > 0 else float("nan"),
    )
    print(SUMMARY_TAG + json.dumps(summary.__dict__), flush=True)


#: Marks the line of a run's process that carries its ``Summary``.
SUMMARY_TAG = "@summary "


def run_inprocess(args: argparse.Namespace) -> None:
    sc = scenario(args.duration)
    with contextlib.ExitStack() as stack:
        cache = args.cache
        if cache is None:  # the runs' processes read the stream from a file
            cache = Path(stack.enter_context(tempfile.TemporaryDirectory())) / "stream.pickle"
        stream = make_stream(sc, args.seed, cache)
        truth = survey(stream)
        chosen = variants(args.full_only, args.history_ab, args.aid_ab)
        data_s = header(
            sc,
            stream,
            truth,
            args.seed,
            f"an Engine fed as fast as it goes, each run in a fresh process of its own, snapshot every "
            f"{args.snapshot_every} msgs (as the node's worker when it lags); "
            + ", ".join(f"{v.key}: {v.label}" for v in chosen)
            + f", interleaved x{args.repeat}",
        )
        del stream
        results: dict[str, list[Summary]] = {}
        accuracy_figures: dict[str, Any] = {}
        judged = "B" if any(v.key == "B" for v in chosen) else "C"
        for rep in range(args.repeat):
            for v in chosen:
                last = rep == args.repeat - 1
                command_line = [
                    sys.executable,
                    str(Path(__file__).resolve()),
                    *("--one-run", v.key, "--round", str(rep + 1), "--cache", str(cache)),
                    *("--duration", str(args.duration), "--seed", str(args.seed)),
                    *("--snapshot-every", str(args.snapshot_every), "--settle-s", str(settle_s(args))),
                    *(["--accuracy"] if last and v.key in (judged, "H") else []),
                    *(["--explain-false"] if last and v.key == judged and args.explain_false else []),
                ]
                done = subprocess.run(command_line, stdout=subprocess.PIPE, text=True, check=False)
                summary = None
                for line in done.stdout.splitlines():
                    if line.startswith(SUMMARY_TAG):
                        summary = Summary(**json.loads(line[len(SUMMARY_TAG) :]))
                    else:
                        print(line)
                if summary is None:
                    raise SystemExit(f"run {v.key} #{rep + 1} failed (exit code {done.returncode})")
                if v.key == "C" and "B" in results and len(results["B"]) == rep + 1:
                    same = "the same" if summary.digest == results["B"][rep].digest else "NOT the same"
                    print(f"  confirmed pairs and biases: {same} as B's in this round")
                if summary.accuracy and v.key == judged:
                    accuracy_figures = summary.accuracy
                results.setdefault(v.key, []).append(summary)
        side_by_side(chosen, results, data_s, truth, args)
        readme_rows(results, data_s, truth, accuracy_figures, sc)
        if not args.no_promptness:
            promptness(sc, make_stream(sc, args.seed, cache))


def side_by_side(
    chosen: list[Variant], results: dict[str, list[Summary]], data_s: float, truth: Truth, args: Any
) -> None:
    n = args.repeat
    rounds = f"median [min-max] over {n} interleaved rounds" if n > 1 else "one round"
    print(f"\nside by side ({rounds}; {data_s:.0f} data s, {truth.plots:,} plots):")
    print(
        f"  {'variant':<30} {'x real time':>19} {'settled':>10} {'plots/s':>23} {'time / A':>19}   "
        f"{'corr per update p50 / p99 ms':<30} peak RSS MB (stream alone)"
    )
    alone = results.get("A")
    for v in chosen:
        rs = results[v.key]
        rt = [data_s / r.wall_s for r in rs]
        rate = [truth.plots / r.wall_s for r in rs]
        ratio = (
            spread([r.wall_s / a.wall_s for r, a in zip(rs, alone, strict=True)], ".2f")
            if alone and v.key != "A"
            else "1"
            if alone
            else "-"
        )
        corr = "-"
        if v.key != "A":
            corr = f"{spread([r.p50_ms for r in rs], '.1f')} / {spread([r.p99_ms for r in rs], '.0f')}"
        peak = f"{spread([r.peak_mb for r in rs], '.0f')} ({spread([r.stream_mb for r in rs], '.0f')})"
        if v.process:
            peak += f" + child {spread([r.child_peak_mb for r in rs], '.0f')}"
        print(
            f"  {v.key} {v.label:<28} {spread(rt, '.2f'):>19} "
            f"{spread([r.settled_rt for r in rs], '.2f'):>10} "
            f"{spread(rate, ',.0f'):>23} {ratio:>19}   "
            f"{corr:<30} {peak}"
        )
    print("  time / A: the wall time over tracking alone's in the same round; correlation per update:")
    for v in chosen:
        if v.key != "A":
            print(f"    {v.key}: {results[v.key][-1].corr_source}")
    if not all(r.peak_is_run for rs in results.values() for r in rs):
        print("  (this system cannot reset a process's peak RSS: each peak is the process's so far)")
    others = [r.others_cpu_s / r.wall_s for rs in results.values() for r in rs]
    print(
        f"  other jobs on the machine took {np.mean(others):.2f} cores on average over the runs "
        f"(at most {max(others):.2f} in one run)"
        + ("" if max(others) < 0.1 else ": not an idle machine's figures")
    )


def readme_rows(
    results: dict[str, list[Summary]],
    data_s: float,
    truth: Truth,
    acc: dict[str, Any],
    sc: Scenario,
) -> None:
    """Rows for the performance table of docs/results.md, each figure with the command that printed it."""

    def rt(key: str) -> str:
        values = [data_s / r.wall_s for r in results[key]]
        lo, hi = rounded(min(values), 3), rounded(max(values), 3)
        return f"{lo}×" if lo == hi else f"{lo}–{hi}×"

    def ratio(key: str) -> str:
        values = [r.wall_s / a.wall_s for r, a in zip(results[key], results["A"], strict=True)]
        return rounded(float(np.median(values)), 2)

    cmd = f"`{command()}`"
    rate = truth.plots / data_s
    print(f"\ndocs/results.md rows (performance table; {os.cpu_count()} cpus, {time.strftime('%Y-%m-%d')}):")
    title = (
        f"national network, {len(sc.radars)} radars × {grouped(sc.targets)} aircraft, "
        f"{rounded(rate, 3)} plots/s, {data_s:.0f} data s ({cmd})"
    )
    parts = []
    if "A" in results:
        plots = rounded(float(np.median([truth.plots / r.wall_s for r in results["A"]])), 3)
        parts.append(f"tracking alone {rt('A')} real time ({plots} plots/s)")
    full = []
    for key, how in (("B", "in one process"), ("C", "with the correlation process")):
        if key in results:
            times = f" ({ratio(key)}× the time of tracking alone)" if "A" in results else ""
            full.append(f"{rt(key)} {how}{times}")
    if full:
        parts.append("full pipeline " + ", ".join(full))
    for key in ("B", "C"):
        if key in results:
            r = results[key][-1]
            parts.append(f"correlation update p50 {rounded(r.p50_ms)} ms, p99 {rounded(r.p99_ms)} ms")
            break
    peaks = []
    for key, how in (("A", "tracking alone"), ("B", "one process")):
        if key in results:
            peaks.append(f"{rounded(max(r.peak_mb for r in results[key]))} MB {how}")
    if "C" in results:
        c = results["C"]
        peaks.append(
            f"{rounded(max(r.peak_mb for r in c))} + {rounded(max(r.child_peak_mb for r in c))} MB "
            "with the correlation process"
        )
    if peaks:
        stream = rounded(float(np.median([r.stream_mb for rs in results.values() for r in rs])))
        parts.append("peak RSS " + ", ".join(peaks) + f" ({stream} MB of it the stream held in memory)")
    print(f"| {title} | {'; '.join(parts)} |")
    if acc:
        rms = acc["bias_rms"]
        figures = (
            f"{acc['correct_pct']:.1f} % of {grouped(acc['pairs'])} confirmed pairs correct "
            f"({acc['false']} false); pair completeness {acc['pair_completeness_pct']:.1f} %, track "
            f"completeness {acc['track_completeness_pct']:.1f} %; bias error RMS {rms[0]:.0f} m, "
            f"{rms[1]:.3f}° azimuth, {rms[2]:.3f}° elevation"
        )
        print(f"| national network accuracy, same run ({cmd}) | {figures} |")


def promptness(sc: Scenario, stream: Stream) -> PromptnessReport:
    """Time to pair and dangling references from the outputs as published, in publish order
    (an untimed pass: the engine in this process, every output built and read, as a subscriber
    to every key would; the correlation in process gives the same outputs in data time as the
    correlation process)."""
    monitor = OutputMonitor({r.radar_id: r.scan_period_s for r in sc.radars})
    report = watch_engine(Engine(EngineConfig()), stream, monitor)
    print("[outputs as published, untimed pass in process]")
    for line in report.lines():
        print(f"  {line}")
    return report


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
    r = feed(engine, stream, args.snapshot_every, "profile", data_s, False)
    profiler.disable()
    report_run(r, data_s, truth, stream)
    if args.profile_out:
        profiler.dump_stats(args.profile_out)
        print(f"profile written to {args.profile_out} (python -m pstats {args.profile_out})")
    for order in ("cumulative", "tottime"):
        print(f"--- top {args.top} by {order} ---")
        pstats.Stats(profiler, stream=sys.stdout).strip_dirs().sort_stats(order).print_stats(args.top)


#: The parts ``--breakdown`` times: (module, class, method); nested parts are timed inside
#: their callers too (a prompt decision inside the stage's update).
BREAKDOWN = (
    ("service.engine", "Engine", "ingest"),
    ("service.pipeline.tracking_stage", "TrackingStage", "update"),
    ("service.pipeline.correlation_stage", "CorrelationStage", "update"),
    ("service.correlation.correlator", "PairCorrelator", "decide_new"),
    ("service.correlation.correlator", "PairCorrelator", "update"),
    ("service.pipeline.system_stage", "SystemStage", "due"),
    ("service.pipeline.correlation_stage", "CorrelationStage", "_solve_due"),
    ("service.pipeline.cycle_links", "CycleLinks", "implied"),
    ("service.pipeline.system_stage", "SystemDrawer", "draw"),
    ("service.pipeline.correlation_stage", "CorrelationStage", "_changed"),
)


def run_breakdown(args: argparse.Namespace) -> None:
    """The in-process pipeline with a timer on each part of :data:`BREAKDOWN`, counted over
    the settled part of the stream (``--settle-s``)."""
    import importlib

    sc = scenario(args.duration)
    stream = make_stream(sc, args.seed, args.cache)
    start_s = min(json.loads(p).get("time_s", np.inf) for _, p in stream)
    first = settle_index(stream, start_s, settle_s(args))
    spent: dict[str, float] = {}
    calls: dict[str, int] = {}
    counting = [False]
    restore = []

    def timed(label: str, f: Callable[..., Any]) -> Callable[..., Any]:
        def wrapper(*a: Any, **k: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                if counting[0]:
                    spent[label] = spent.get(label, 0.0) + time.perf_counter() - t0
                    calls[label] = calls.get(label, 0) + 1

        return wrapper

    for module, cls_name, method in BREAKDOWN:
        cls = getattr(importlib.import_module(module), cls_name)
        original = getattr(cls, method)
        restore.append((cls, method, original))
        setattr(cls, method, timed(f"{cls_name}.{method}", original))
    engine = Engine(EngineConfig())
    try:
        for i, (key, payload) in enumerate(stream):
            if i == first:
                counting[0], cpu0 = True, time.process_time()
            engine.ingest(key, payload)
        engine.flush()
        cpu = time.process_time() - cpu0 if counting[0] else float("nan")
    finally:
        engine.close()
        for cls, method, original in restore:
            setattr(cls, method, original)
    data_s = float(sc.duration_s or 0.0) - settle_s(args)
    print(f"[breakdown, in process, the settled {data_s:.0f} data s: messages {first}..{len(stream)}]")
    print(f"  CPU of the process over the settled part: {cpu:.2f} s")
    stage = spent.get("CorrelationStage.update", float("nan"))
    print(f"  {'part':<34} {'s':>8} {'calls':>7} {'ms/call':>8} {'of stage':>9}")
    for label in sorted(spent, key=lambda k: -spent[k]):
        sec, n = spent[label], calls[label]
        print(f"  {label:<34} {sec:8.2f} {n:7d} {1e3 * sec / n:8.3f} {sec / stage:9.0%}")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def drawer_cpu_s(node: Any) -> float:
    """CPU seconds the node's worker spent drawing system tracks (0: no drawer)."""
    return float(getattr(getattr(node.engine.correlation, "drawer", None), "cpu_s", 0.0))


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
    process = not args.one_process
    placement = (
        "its correlation in a child process (the service's default)"
        if process
        else "its correlation in its own process (--one-process)"
    )
    data_s = header(
        sc,
        stream,
        truth,
        args.seed,
        f"a ServiceNode in router mode on {endpoint} (multicast scouting off), {placement}, a client session "
        "publishing with CongestionControl.BLOCK as fast as the node takes it; wall from the first put to "
        "the last message processed; snapshots as the node takes them (after each message while it keeps up)",
    )
    if args.explain_false and not record_truth_history():
        print("--explain-false: no truth tally to record in this engine")
    node = ServiceNode(
        EngineConfig(), ZenohOptions(mode="router", listen=(endpoint,)), correlation_process=process
    )
    startup = wait_ready(node.engine)
    pid = child_pid(node.engine)
    snaps: list[float] = []
    original_snapshot = node.engine.snapshot

    def timed_snapshot() -> Snapshot:
        t0 = time.perf_counter()
        try:
            return original_snapshot()
        finally:
            snaps.append(time.perf_counter() - t0)

    setattr(node.engine, "snapshot", timed_snapshot)  # noqa: B010 (an instance attribute over the method)
    # The node closes its engine (and so stops the correlation process) when it stops: read the
    # child's peak and CPU time just before.
    child: dict[str, float] = {}
    child_cpu0 = cpu_s(pid) if pid else 0.0
    original_close = node.engine.close

    def close_after_reading() -> None:
        if pid is not None:
            child.update(peak=proc_status_mb(pid, "VmHWM"), cpu=cpu_s(pid) - child_cpu0)
        original_close()

    setattr(node.engine, "close", close_after_reading)  # noqa: B010 (as above)
    # Each message's time in Engine.ingest on the node's worker thread, waits for the correlation
    # process at its bound included: the stall a message's arrival meets (the issue's p99 goal).
    ingest_s: list[float] = []
    original_ingest = node.engine.ingest
    # When the outputs became complete through the settle time (``Engine.outputs_time_s``, read
    # on the worker's thread after each message): the settled window measured by the outputs at
    # both ends, as a client reading ``outputs_time_s`` in ``/status`` would measure it.
    settled_through = sc.start_time_s + settle_s(args)
    outputs_settled_t: list[float] = []

    def timed_ingest(*a: Any, **k: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return original_ingest(*a, **k)
        finally:
            t1 = time.perf_counter()
            ingest_s.append(t1 - t0)
            if not outputs_settled_t:
                through = node.engine.outputs_time_s
                if through is not None and through >= settled_through:
                    outputs_settled_t.append(t1)

    setattr(node.engine, "ingest", timed_ingest)  # noqa: B010 (as above)
    probe = Probe(node.engine)
    waits = Backpressure(node.engine)
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
        peak_is_run = reset_peak()
        cpu0, busy0 = cpu_s(), machine_busy_s()
        child_cpu0 = cpu_s(pid) if pid else 0.0
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

        settle_at = settle_index(stream, sc.start_time_s, settle_s(args))
        settled_t = [t_start]
        # CPU (this process, the correlation process, the drawer) when the run became settled
        settled_cpu = [(cpu0, child_cpu0, 0.0)]

        def done() -> bool:
            if time.monotonic() - done_progress[0] >= PROGRESS_PERIOD_S:
                done_progress[0] = time.monotonic()
                print(f"# zenoh: node processed {node.processed}/{len(stream)}", file=sys.stderr, flush=True)
            if node.processed <= settle_at:
                settled_t[0] = time.perf_counter()
                settled_cpu[0] = (cpu_s(), cpu_s(pid) if pid else 0.0, drawer_cpu_s(node))
            # ... and the outputs of the last one published: the correlation process answered
            return node.processed >= len(stream) and node.queue.empty() and not node.engine.answers_pending

        done_progress = [time.monotonic()]
        finished = _wait(done, 24 * 3600.0)
        t_end = time.perf_counter()
        wall = t_end - t_start
        settled_wall = t_end - settled_t[0]
        outputs_wall = t_end - outputs_settled_t[0] if outputs_settled_t else float("nan")
        node.stop(grace_s=600.0)  # flushes the engine, takes the final snapshot, stops the child
        cpu = cpu_s() - cpu0
        busy = machine_busy_s() - busy0
        span = time.perf_counter() - t_start  # the interval of busy and cpu (wall, then stop)
        peak = proc_status_mb("self", "VmHWM") if peak_is_run else peak_rss_mb()
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
    print(
        f"[zenoh, {'correlation process' if process else 'one process'}] "
        f"{'all' if finished else 'NOT all'} {len(stream)} messages processed"
    )
    settled_data = data_s - settle_s(args)
    print(
        f"  settled: x{settled_data / settled_wall:.2f} real time through Zenoh over the last "
        f"{settled_data:.0f} data s ({settled_wall:.1f} s wall, until the outputs of the last batch "
        "were published)"
    )
    print(
        f"  settled by the outputs: x{settled_data / outputs_wall:.2f} real time (from the outputs "
        f"complete through the settle time, outputs_time_s, to those of the last batch: "
        f"{outputs_wall:.1f} s wall; the line above starts when the node took the settle message, "
        "with the correlation process's backlog of messages in flight still to answer)"
    )
    print(
        f"  real time x{data_s / wall:.2f} through Zenoh ({wall:.1f} s wall for {data_s:.0f} data "
        "s; the publisher "
        f"was done after {published_s:.1f} s); {truth.plots / wall:,.0f} plots/s, "
        f"{len(stream) / wall:.0f} msgs/s"
    )
    ms = np.asarray(probe.updates_ms)
    corr = final.correlation
    updates = int(corr.get("updates", 0))
    if ms.size:
        p50, p99 = pct(ms, 50), pct(ms, 99)
        source = f"probe, all {ms.size} updates"
        stage = f"; stage total {probe.stage_s:.1f} s = {100 * probe.stage_s / wall:.0f}% of wall"
    else:
        p50, p99 = float(corr.get("p50_ms", np.nan)), float(corr.get("p99_ms", np.nan))
        source = (
            f"{'child' if process else 'stage'}'s snapshot.correlation, last {min(updates, 2048)} updates"
        )
        stage = ""
    print(
        f"  correlation: {updates} updates; per update ({source}) p50 {p50:.2f} ms, p99 {p99:.1f} ms{stage}"
    )
    stalls = 1000.0 * np.asarray(ingest_s)
    if stalls.size:
        print(
            f"  ingest stall per message (the worker's Engine.ingest, waits for the correlation process "
            f"included): p50 {pct(stalls, 50):.2f} ms, p99 {pct(stalls, 99):.1f} ms, "
            f"max {stalls.max():.0f} ms over {stalls.size} messages"
        )
    if process:
        print(
            f"  correlation process: started in {startup:.1f} s (before the first put); the node's worker "
            f"waited {waits.wait_s:.1f} s for it ({waits.waits} times at the bound of messages in flight); "
            f"restarts {getattr(node.engine.correlation, 'restarts', 0)}"
        )
    child_cpu = child.get("cpu", 0.0)
    draw_cpu = drawer_cpu_s(node)
    if process and cpu > draw_cpu:
        print(
            f"  CPU of correlation and fusion (the correlation process, and the system-track rebuilds "
            f"on the node's worker) over the rest of the node's (Zenoh, decoding, tracking): "
            f"{(child_cpu + draw_cpu) / (cpu - draw_cpu):.2f} ({child_cpu:.1f} + {draw_cpu:.1f} s / "
            f"{cpu - draw_cpu:.1f} s)"
        )
        # the same over the settled part alone: the cold start (every aircraft appears at once and
        # is paired on every radar pair) left out, as for the settled real-time factor
        node_s = cpu0 + cpu - settled_cpu[0][0]
        child_s = child_cpu0 + child_cpu - settled_cpu[0][1]
        draw_s = draw_cpu - settled_cpu[0][2]
        if node_s > draw_s:
            print(
                f"  the same over the settled last {settled_data:.0f} data s: "
                f"{(child_s + draw_s) / (node_s - draw_s):.2f} ({child_s:.1f} + {draw_s:.1f} s / "
                f"{node_s - draw_s:.1f} s)"
            )
    print(
        f"  CPU: this process (node, client, Zenoh) {cpu:.1f} s"
        + (f", correlation process {child_cpu:.1f} s" if process else "")
        + f" over {wall:.1f} s wall ({(cpu + child_cpu) / wall:.2f} cores busy); other jobs on the "
        f"machine {max(busy - cpu - child_cpu, 0.0) / span:.2f} cores"
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
    memory = (
        f"RSS {rss_before:.0f} -> {rss_mb():.0f} MB, peak {peak:.0f} MB"
        + ("" if peak_is_run else " (this process's life so far)")
        + " (node, client and stream in one process)"
    )
    if process:
        memory += f"; correlation process peak {child.get('peak', float('nan')):.0f} MB"
    print(f"  end: {core['pairs_confirmed']} confirmed pairs, rejected {core['rejected'] or 0}; {memory}")
    acc = accuracy(final, sc, truth)
    if args.explain_false:
        explain_false(node.engine, final, sc)
    how = "with the correlation process" if process else "in one process"
    print(f"\ndocs/results.md row ({os.cpu_count()} cpus, {time.strftime('%Y-%m-%d')}):")
    print(
        f"| national network through Zenoh, {how} (`{command()}`) | {rounded(data_s / wall, 3)}× real time "
        f"({rounded(truth.plots / wall, 3)} plots/s); correlation update p50 {rounded(p50)} ms, "
        f"p99 {rounded(p99)} ms; {acc['correct_pct']:.1f} % of confirmed pairs correct "
        f"({acc['false']} false) |"
    )
    if not args.no_promptness:
        print()
        promptness(sc, stream)


# -- soak ----------------------------------------------------------------------------------------
class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2``."""

    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


def _malloc_counts() -> dict[str, int]:
    """glibc's counts of the C heap (``mallinfo2``): bytes in use, free but kept, mmapped."""
    name = ctypes.util.find_library("c")
    if name is None:
        return {}
    try:
        libc = ctypes.CDLL(name)
        libc.mallinfo2.restype = _MallInfo2
        info = libc.mallinfo2()
    except (OSError, AttributeError):
        return {}
    return {
        "heap": int(info.arena),
        "in use": int(info.uordblks),
        "free": int(info.fordblks),
        "mmapped": int(info.hblkhd),
    }


def registration_census() -> dict[str, float]:
    """The registration memories of this process's pair correlators: rows and bytes.

    Each memory keeps its rows in one buffer per column (service/correlation/registration.py):
    ``live`` rows are those remembered, ``written`` those between the buffer's start and its end
    mark (the pages written since the buffer was made: an upper bound of what of it is
    resident), ``allocated`` its capacity.  Found among the objects the garbage collector
    tracks (bench only: no handle on the stage is needed).
    """
    out = dict.fromkeys(("pairs", "rows live", "MB live", "MB written", "MB allocated"), 0.0)
    for obj in gc.get_objects():
        if type(obj).__name__ != "RegistrationMemory":
            continue
        buf = getattr(obj, "_buf", None)
        if not buf:
            continue
        capacity = next(iter(buf.values())).shape[0]
        row_bytes = sum(b.nbytes for b in buf.values()) / max(capacity, 1)
        live = len(obj)
        out["pairs"] += 1
        out["rows live"] += live
        out["MB live"] += live * row_bytes / 1e6
        out["MB written"] += getattr(obj, "_end", 0) * row_bytes / 1e6
        out["MB allocated"] += capacity * row_bytes / 1e6
    return out


#: What a heap dump holds: a tracemalloc snapshot (or None), the C heap's counts, RSS MB, the
#: registration census.
HeapDump = tuple[Any, dict[str, int], float, dict[str, float]]


def heap_dump(full: bool) -> HeapDump:
    snapshot = tracemalloc.take_snapshot() if full and tracemalloc.is_tracing() else None
    return snapshot, _malloc_counts(), rss_mb(), registration_census()


def traced_serve(*args: Any) -> None:
    """The correlation process's main function under ``--trace-memory`` or ``--census`` (bench
    only): serves as the service's child does, and at each signal writes a ``heap_dump`` to the
    directory in the environment variable ``TRACE_DIR_ENV`` (SIGUSR1: with a tracemalloc
    snapshot, SIGUSR2: without).  Runs in the child: the spawned interpreter imports this file
    to find it.
    """
    from service.pipeline import correlation_process

    directory = Path(os.environ[TRACE_DIR_ENV])
    if os.environ.get(TRACE_DIR_ENV + "_MALLOC") == "1":
        # traced from the start: a block allocated before tracing and freed later would not
        # count as a decrease, and the growth would be overstated
        tracemalloc.start(1)
    count = itertools.count()

    def on_signal(signum: int, frame: Any) -> None:
        path = directory / f"child-{next(count)}.pickle"
        tmp = path.with_suffix(".tmp")
        with tmp.open("wb") as f:
            pickle.dump(heap_dump(signum == signal.SIGUSR1), f)
        tmp.rename(path)

    signal.signal(signal.SIGUSR1, on_signal)
    signal.signal(signal.SIGUSR2, on_signal)
    correlation_process._serve(*args)


class ChildHeap:
    """Asks the correlation process (run by ``traced_serve``) for heap dumps, one at a time."""

    def __init__(self, pid: int, directory: Path) -> None:
        self.pid, self.directory, self.taken = pid, directory, 0

    def take(self, full: bool, timeout_s: float = 300.0) -> Path | None:
        """The file of a new dump (read it with ``load`` once this process's heap is measured:
        loading it here would count as growth of this process's heap)."""
        path = self.directory / f"child-{self.taken}.pickle"
        self.taken += 1
        os.kill(self.pid, signal.SIGUSR1 if full else signal.SIGUSR2)
        return path if _wait(path.exists, timeout_s) else None

    @staticmethod
    def load(path: Path | None) -> HeapDump | None:
        if path is None:
            return None
        with path.open("rb") as f:
            dump: HeapDump = pickle.load(f)
        return dump


def where(frame: Any) -> str:
    """A traceback frame as ``file:line``, the file relative to site-packages or the repository."""
    path = Path(frame.filename)
    for base in (*(p for p in map(Path, sys.path) if p.name == "site-packages"), ROOT):
        with contextlib.suppress(ValueError):
            return f"{path.relative_to(base)}:{frame.lineno}"
    return f"{'/'.join(path.parts[-3:])}:{frame.lineno}"


def heap_growth(name: str, before: HeapDump, after: HeapDump) -> None:
    """Where a process's Python heap grew between two tracemalloc snapshots, and its C heap."""
    (snap0, malloc0, rss0, census0), (snap1, malloc1, rss1, census1) = before, after
    if snap0 is not None and snap1 is not None:
        growth = snap1.compare_to(snap0, "lineno")
        traced0 = sum(s.size for s in snap0.statistics("filename")) / 1e6
        traced1 = sum(s.size for s in snap1.statistics("filename")) / 1e6
        print(
            f"{name}: RSS {rss0:.0f} -> {rss1:.0f} MB; Python heap (tracemalloc) {traced0:.0f} -> "
            f"{traced1:.0f} MB; top lines:"
        )
        for g in growth[:10]:
            print(f"  {g.size_diff / 1e6:+8.1f} MB {g.count_diff:+8d} blocks  {where(g.traceback[0])}")
    if malloc0 and malloc1:
        print(
            f"{name}: C heap (glibc) "
            + ", ".join(f"{k} {malloc0[k] / 1e6:.0f} -> {malloc1[k] / 1e6:.0f} MB" for k in malloc0)
        )
    if census1.get("pairs"):
        print(
            f"{name}: registration memories ({census1['pairs']:.0f}) "
            + ", ".join(f"{k} {census0[k]:,.0f} -> {census1[k]:,.0f}" for k in census1 if k != "pairs")
        )


def registration_memory_s() -> float:
    """How much data time of pairs registration remembers (its parameters' default)."""
    try:
        from service.correlation.registration import RegistrationParams
    except ImportError:
        return float("nan")
    return float(getattr(RegistrationParams(), "memory_s", float("nan")))


def run_soak(args: argparse.Namespace) -> None:
    sc = replace(get_scenario("national"), duration_s=None, respawn="uniform")
    minutes = float(args.soak_minutes)
    process = not args.one_process
    census = args.census or args.trace_memory
    print(
        f"national soak: {len(sc.radars)} radars, {sc.targets} aircraft, never-ending stream (seed "
        f"{args.seed}) generated {args.chunk} msgs at a time, fed to one Engine "
        + ("with its correlation process" if process else "in one process")
        + f" as fast as it goes for {minutes:g} wall minutes, snapshot every {args.snapshot_every} msgs"
        + ("; tracemalloc on in both processes (slows them)" if args.trace_memory else "")
    )
    print(
        "stream: the national scenario with respawn='uniform' (an aircraft leaving the area is "
        "replaced by one entering it as a uniformly spread population's would, so the number in "
        "radar cover stays the same; the scenario's own 'edge' respawn gathers them towards the "
        "centre over the first hour)"
    )
    print(
        "one line per wall minute; 'x rt': data s per wall s of the engine (generation excluded; "
        + (
            "the correlation process keeps working while this one generates, so this is no throughput "
            "figure); RSS: this process (engine and generator), the correlation process, both"
            if process
            else "not the in-process mode's throughput); RSS: this process"
        )
        + ("; reg MB: the registration memories' rows live / written / allocated" if census else "")
    )
    print(
        f"{'min':>5} {'data s':>8} {'x rt':>6} {'RSS MB':>7} {'child':>6} {'both':>6} {'window':>8} "
        f"{'tracks':>7} {'pairs':>7} {'others':>6}"
        + (f" {'reg MB live/written/alloc':>26}" if census else "")
        + "   (others: cores other jobs on the machine took)"
    )
    trace_dir: tempfile.TemporaryDirectory[str] | None = None
    if args.trace_memory:
        tracemalloc.start(1)  # from the start (see traced_serve)
    if census and process:
        from service.pipeline import correlation_process

        trace_dir = tempfile.TemporaryDirectory()
        os.environ[TRACE_DIR_ENV] = trace_dir.name
        os.environ[TRACE_DIR_ENV + "_MALLOC"] = "1" if args.trace_memory else "0"
        correlation_process._serve = traced_serve  # type: ignore[assignment]
    engine = Engine(EngineConfig(), correlation_process=process)
    wait_ready(engine)
    pid = child_pid(engine)
    child_heap = ChildHeap(pid, Path(trace_dir.name)) if trace_dir is not None and pid else None
    messages = wire_messages(sc, args.seed)  # lazy: the generator keeps no history
    start = time.monotonic()
    next_line = start + 60.0
    count = 0
    series: list[tuple[float, float, float]] = []  # (elapsed minutes, RSS MB, child RSS MB)
    load: list[tuple[float, int, int, int]] = []  # (data s, window plots, tracks, confirmed pairs)
    last_data, last_engine_s, engine_s = 0.0, 0.0, 0.0
    last_busy, last_cpu, last_line = machine_busy_s(), cpu_s() + (cpu_s(pid) if pid else 0.0), start
    mid: HeapDump | None = None  # this process's, at half time
    child_mid: Path | None = None
    child_end: Path | None = None

    def data_time() -> float:
        clocks = [r["last_time_s"] for r in engine.snapshot().status_core()["radars"] if r["last_time_s"]]
        return max(clocks) - sc.start_time_s if clocks else 0.0

    def registration() -> dict[str, float] | None:
        """The census of the process that runs the correlation stage."""
        if not census:
            return None
        if child_heap is None:
            return registration_census()
        dump = ChildHeap.load(child_heap.take(full=False))
        return dump[3] if dump is not None else None

    try:
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
            if args.trace_memory and mid is None and now - start >= 30.0 * minutes:
                mid = heap_dump(full=True)
                child_mid = child_heap.take(full=True) if child_heap is not None else None
            if now >= next_line:
                next_line += 60.0
                core = engine.snapshot().status_core()
                data = data_time()
                rt = (data - last_data) / max(engine_s - last_engine_s, 1e-9)
                last_data, last_engine_s = data, engine_s
                rss = rss_mb()
                child = proc_status_mb(pid, "VmRSS") if pid else 0.0
                elapsed = (now - start) / 60.0
                series.append((elapsed, rss, child))
                busy, ours = machine_busy_s(), cpu_s() + (cpu_s(pid) if pid else 0.0)
                others = max(busy - last_busy - (ours - last_cpu), 0.0) / (now - last_line)
                last_busy, last_cpu, last_line = busy, ours, now
                window = sum(r["window_plots"] for r in core["radars"])
                tracks = sum(r["tracks_confirmed"] + r["tracks_tentative"] for r in core["radars"])
                load.append((data, window, tracks, core["pairs_confirmed"]))
                reg = registration()
                reg_text = (
                    f" {reg['MB live']:8.0f}/{reg['MB written']:.0f}/{reg['MB allocated']:.0f}".ljust(27)
                    if reg is not None
                    else ""
                )
                print(
                    f"{elapsed:5.1f} {data:8.0f} {rt:6.2f} {rss:7.0f} {child:6.0f} {rss + child:6.0f} "
                    f"{window:8d} {tracks:7d} {core['pairs_confirmed']:7d} {others:6.2f}{reg_text}",
                    flush=True,
                )
        if child_heap is not None and child_mid is not None:
            child_end = child_heap.take(full=True)
        restarts = int(getattr(engine.correlation, "restarts", 0))
        end = heap_dump(full=True) if mid is not None else None
    finally:
        engine.close()
    print(
        "RSS series (min, MB this process"
        + (" + correlation process" if process else "")
        + "): "
        + ", ".join(f"({m:.0f}, {r:.0f}" + (f" + {c:.0f})" if process else ")") for m, r, c in series)
    )
    memory_s = registration_memory_s()
    full = next((m for (m, _, _), (d, *_) in zip(series, load, strict=True) if d >= memory_s), None)
    print(
        f"registration memory: {memory_s:.0f} data s, "
        + (f"full from minute {full:.0f} on" if full is not None else "never full in this run")
    )
    half = [row for row in series if row[0] >= minutes / 2]
    second = np.array([row for (m, *_), row in zip(series, load, strict=True) if m >= minutes / 2])
    if len(second) >= 2:
        print(
            "load over the second half (min-max): "
            + ", ".join(
                f"{name} {int(second[:, i].min()):,}-{int(second[:, i].max()):,}"
                for i, name in ((1, "window plots"), (2, "tracks"), (3, "confirmed pairs"))
            )
        )
    slope_both = float("nan")
    if len(half) >= 2:
        x, parent, child_mb = np.array(half).T
        slopes = [("this process", parent)]
        if process:
            slopes += [("correlation process", child_mb), ("both", parent + child_mb)]
        slope_both = float(np.polyfit(x, slopes[-1][1], 1)[0] * 60.0)
        print(
            f"RSS slope over the second half ({len(half)} points, {x[0]:.0f}-{x[-1]:.0f} min): "
            + ", ".join(f"{name} {np.polyfit(x, y, 1)[0] * 60.0:+.1f} MB/h" for name, y in slopes)
        )
        print(
            "RSS change over the second half: "
            + ", ".join(f"{name} {y[-1] - y[0]:+.0f} MB" for name, y in slopes)
        )
    else:
        print("RSS slope: too few points in the second half (run longer)")
    if process:
        print(f"correlation process restarts: {restarts}")
    if mid is not None and end is not None:
        heap_growth("this process, second half", mid, end)
    child_dumps = ChildHeap.load(child_mid), ChildHeap.load(child_end)
    if child_dumps[0] is not None and child_dumps[1] is not None:
        heap_growth("correlation process, second half", child_dumps[0], child_dumps[1])
    if args.trace_memory:
        tracemalloc.stop()
    if trace_dir is not None:
        trace_dir.cleanup()
    if series and np.isfinite(slope_both):
        print(f"\ndocs/results.md row ({os.cpu_count()} cpus, {time.strftime('%Y-%m-%d')}):")
        print(
            f"| national soak, {minutes:g} min "
            + ("with the correlation process" if process else "in one process")
            + f", stationary traffic (`{command()}`) | {series[-1][1] + series[-1][2]:.0f} MB RSS at the end"
            + (f" ({series[-1][1]:.0f} + {series[-1][2]:.0f})" if process else "")
            + f", {slope_both:+.0f} MB/h over the second half ({last_data / 3600:.1f} data hours in all) |"
        )


def main() -> None:
    warn_if_elsewhere()
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--duration", type=float, default=120.0, help="data seconds of the stream (default 120)"
    )
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cache", type=Path, help="pickle file keeping the generated stream between runs")
    parser.add_argument("--repeat", type=int, default=1, help="rounds of the variants, interleaved")
    parser.add_argument("--full-only", action="store_true", help="skip the tracking-alone run")
    parser.add_argument(
        "--history-ab",
        action="store_true",
        help="compare the full pipeline with and without the pairs' history evidence (B against H)",
    )
    parser.add_argument(
        "--aid-ab",
        action="store_true",
        help="compare the full pipeline, correlation process, with and without the aid of association (C, E)",
    )
    parser.add_argument("--snapshot-every", type=int, default=64, help="messages between snapshots (0: none)")
    parser.add_argument(
        "--explain-false",
        action="store_true",
        help="record each track's aircraft over time; explain false pairs",
    )
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--zenoh", action="store_true", help="through a ServiceNode over Zenoh on loopback")
    parser.add_argument("--subscribe", action="store_true", help="zenoh: a subscriber to the node's outputs")
    parser.add_argument(
        "--one-process", action="store_true", help="zenoh, soak: correlation in the engine's process"
    )
    mode.add_argument("--profile", action="store_true", help="the in-process full pipeline under cProfile")
    mode.add_argument(
        "--breakdown", action="store_true", help="where the settled part's time goes, by part of the stages"
    )
    mode.add_argument(
        "--soak-minutes", type=float, help="feed a never-ending stream for this many wall minutes"
    )
    # a run of the in-process mode, in a process of its own (see one_run)
    parser.add_argument("--one-run", choices=("A", "B", "C", "H", "E"), help=argparse.SUPPRESS)
    parser.add_argument("--round", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--accuracy", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--top", type=int, default=25, help="functions listed per profile order")
    parser.add_argument("--profile-out", type=Path, help="with --profile: also write the raw profile here")
    parser.add_argument("--chunk", type=int, default=512, help="messages generated at a time in the soak")
    parser.add_argument(
        "--trace-memory", action="store_true", help="soak: where the Python heap grows over the second half"
    )
    parser.add_argument(
        "--census", action="store_true", help="soak: the registration memories' sizes every minute"
    )
    parser.add_argument(
        "--settle-s",
        type=float,
        help="data seconds before a run counts as settled (default: half the stream); the settled "
        "real-time factor is measured over the rest",
    )
    parser.add_argument(
        "--no-promptness",
        action="store_true",
        help="skip the untimed pass that measures time to pair and dangling references",
    )
    args = parser.parse_args()
    if args.one_run:
        one_run(args)
    elif args.zenoh:
        run_zenoh(args)
    elif args.profile:
        run_profile(args)
    elif args.breakdown:
        run_breakdown(args)
    elif args.soak_minutes is not None:
        run_soak(args)
    else:
        run_inprocess(args)


if __name__ == "__main__":
    main()
