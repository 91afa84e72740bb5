"""Churn soak: RSS of the service and of its correlation process while radar ids come and go.

Prints figures, never asserts.  A lab scenario (``--scenario``, default ``three-radar``) is
simulated for ``--data-s`` data seconds (default 1 800) before any clock starts, and fed through
Zenoh into a real ``ServiceNode`` (router mode on a free loopback port, multicast scouting off,
its correlation in a child process as the service runs it by default), paced so that the
stream's data time spreads over ``--minutes`` wall minutes (default 10: 3x real time for
1 800 data s).  A client session publishes each message at its data time's wall time with
``CongestionControl.BLOCK``.

Variants (``--variants``, each in a fresh process of its own, one after the other, so that a
run's RSS is its own):

* ``churn``: every ``--churn-every-s`` data seconds (default 37) one radar, in turn, goes on
  under a new id (``A`` -> ``A-1`` -> ``A-2``...): a site message with the new id and the same
  position first, then its batches (``seq`` from 1); the old id falls silent (its publishers
  are undeclared), expires ``source_expiry_s`` (300 s) of data time later and is forgotten
  ``forget_after_s`` (300 s) after that (service/pipeline/sequencer.py).  Three radars over
  1 800 data s: 51 ids.
* ``plain``: the same stream without churn.

Every ``--sample-s`` wall seconds (default 15) one line: RSS (``VmRSS``) of this process (the
node, its engine and the publishing client) and of the correlation process, the data time
published and released by the node's sequencer, how many messages the node is behind the
publisher, the CPU the two processes used, and the sources the engine holds.  At the end the
node must have processed every message; the slope of RSS over the second half (least squares,
MB per wall minute) of each process, against the goal of at most ``GOAL_MB_PER_MIN``.  At half
time and at the end a census of both processes: the lengths of the containers reachable from
the node (this process) and from the correlation stage (the child), and the live Python objects
by type; the largest growths between the two are printed.  ``--trace-memory`` adds tracemalloc
in both processes from the start (slows them) and prints where the Python heap grew over the
second half.  Then, in the parent, the samples and slopes of the variants side by side.

Run: PYTHONPATH=.:lab .venv/bin/python bench/bench_churn_soak.py [--minutes 10] [--data-s 1800]
     [--churn-every-s 37] [--variants churn,plain] [--scenario three-radar] [--seed 1]
     [--sample-s 15] [--trace-memory]
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import math
import os
import pickle
import signal
import socket
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections import Counter, defaultdict, deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from service.engine import EngineConfig
from service.pipeline.sequencer import SequencerParams
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import wire_messages

#: The goal: RSS growth over the second half of each process at most this (MB per wall minute).
GOAL_MB_PER_MIN = 3.0
#: Where the correlation process writes its census (set for it by this file, see census_serve).
CENSUS_DIR_ENV = "TOPOFUSION_BENCH_CHURN_DIR"
#: ... and whether it traces its heap from the start.
TRACE_ENV = "TOPOFUSION_BENCH_CHURN_TRACE"
#: Growths listed per census.
TOP = 12


# -- the stream ------------------------------------------------------------------------------------
@dataclass
class Stream:
    """Messages in data-time order: ``(data time, key, payload)``."""

    messages: list[tuple[float, str, bytes]] = field(default_factory=list)
    #: Radar ids in order of first appearance.
    ids: list[str] = field(default_factory=list)
    #: A new id -> the id it replaces (that one falls silent from the new one's site on).
    replaces: dict[str, str] = field(default_factory=dict)
    start_s: float = 0.0
    end_s: float = 0.0


def build_stream(name: str, data_s: float, seed: int, churn_every_s: float) -> Stream:
    """The scenario's messages; with ``churn_every_s`` finite, radar ids churned in turn.

    Churn event ``j`` (at ``j * churn_every_s`` of data time) gives radar ``j mod R`` (in the
    scenario's order) its next id.  Each radar batch goes under its radar's id at its data time,
    numbered from 1 per id; a new id's first batch is preceded by a copy of its radar's site
    message with the new id.  References (AIS, ADS-B) are left alone.
    """
    sc = replace(get_scenario(name), duration_s=data_s)
    radars = [r.radar_id for r in sc.radars]
    out = Stream(start_s=sc.start_time_s, end_s=sc.start_time_s)
    sites: dict[str, dict[str, Any]] = {}
    seqs: dict[str, int] = {}
    current = {rid: rid for rid in radars}
    time_s = sc.start_time_s
    for key, payload in wire_messages(sc, seed):
        body = json.loads(payload)
        time_s = float(body.get("time_s", time_s))
        kind, rid = _radar_key(key)
        if kind == "site":
            sites[rid] = body
        if kind != "plots":
            out.messages.append((time_s, key, payload))
            if kind == "site" and rid not in out.ids:
                out.ids.append(rid)
            continue
        events = math.floor((time_s - sc.start_time_s) / churn_every_s) if math.isfinite(churn_every_s) else 0
        i = radars.index(rid)
        generation = 0 if events <= i else (events - i - 1) // len(radars) + 1
        new = rid if generation == 0 else f"{rid}-{generation}"
        prefix = key[: -len(f"radar/{rid}/plots")]
        if new not in seqs and new != rid:
            out.replaces[new] = current[rid]
            site = json.dumps({**sites[rid], "radar_id": new}).encode()
            out.messages.append((time_s, f"{prefix}radar/{new}/site", site))
            out.ids.append(new)
        current[rid] = new
        seqs[new] = seqs.get(new, 0) + 1
        body.update(radar_id=new, seq=seqs[new])
        out.messages.append((time_s, f"{prefix}radar/{new}/plots", json.dumps(body).encode()))
    out.end_s = time_s
    return out


def _radar_key(key: str) -> tuple[str, str]:
    """``("site" | "plots", radar id)`` of a radar's key, ``("", "")`` for any other."""
    parts = key.split("/")
    if len(parts) >= 3 and parts[-3] == "radar" and parts[-1] in ("site", "plots"):
        return parts[-1], parts[-2]
    return "", ""


# -- processes ---------------------------------------------------------------------------------------
def rss_mb(pid: int | str = "self") -> float:
    """``VmRSS`` of a process (Linux ``/proc/PID/status``), MB; nan if unknown."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024 / 1e6
    except (OSError, IndexError, ValueError):
        pass
    return float("nan")


def cpu_s(pid: int | str = "self") -> float:
    """User + system CPU seconds of a process (Linux ``/proc/PID/stat``); nan if unknown."""
    try:
        utime, stime = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[11:13]
    except (OSError, IndexError, ValueError):
        return float("nan")
    return (int(utime) + int(stime)) / os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(predicate: Callable[[], bool], timeout_s: float, period_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return predicate()


def slope_mb_per_min(t_s: list[float], mb: list[float]) -> float:
    """Least-squares slope of RSS against wall time, MB per minute (nan: fewer than 2 points)."""
    keep = [(t, m) for t, m in zip(t_s, mb, strict=True) if math.isfinite(m)]
    if len(keep) < 2:
        return float("nan")
    x, y = np.array(keep).T
    return float(np.polyfit(x / 60.0, y, 1)[0])


# -- census: what each process holds -------------------------------------------------------------------
def container_sizes(root: object, name: str, depth: int = 8) -> dict[str, float]:
    """The lengths of the containers (dicts, lists, sets, deques) reachable from ``root``
    through the attributes of the service's own objects, and the kB of its numpy arrays
    (`` kB``), summed over the items of each container (``[*]``), to ``depth`` levels.  Read
    from another thread than the one that changes them: a container changing while it is
    read is counted as it was seen, or skipped."""
    sizes: dict[str, float] = defaultdict(float)
    seen: set[int] = set()

    def items_of(value: Any) -> list[Any]:
        for _ in range(3):
            with contextlib.suppress(RuntimeError):  # changed size during the copy
                return list(value.values()) if isinstance(value, dict) else list(value)
        return []

    def attributes(obj: object) -> list[tuple[str, Any]]:
        found = items_of(vars(obj).items()) if hasattr(obj, "__dict__") else []
        for cls in type(obj).__mro__:
            slots = getattr(cls, "__slots__", ())
            for slot in (slots,) if isinstance(slots, str) else slots:
                if slot not in ("__dict__", "__weakref__") and hasattr(obj, slot):
                    found.append((slot, getattr(obj, slot)))
        return found

    def measure(value: Any, path: str, left: int) -> None:
        if left < 0:
            return
        if isinstance(value, np.ndarray):
            sizes[path + " kB"] += value.nbytes / 1e3
        elif isinstance(value, (dict, list, set, frozenset, deque, tuple)):
            if not isinstance(value, tuple):
                sizes[path] += len(value)
            for item in items_of(value):
                if isinstance(item, (np.ndarray, dict, list, set, frozenset, deque, tuple)) or _own(item):
                    measure(item, path + "[*]", left - 1)
        elif _own(value) and id(value) not in seen:
            seen.add(id(value))
            for attr, inner in attributes(value):
                measure(inner, f"{path}.{attr}", left - 1)

    measure(root, name, depth)
    return dict(sizes)


def _copy(d: dict[Any, Any]) -> list[Any]:
    """The values of a dict another thread may change meanwhile (empty if it keeps changing)."""
    for _ in range(3):
        with contextlib.suppress(RuntimeError):
            return list(d.values())
    return []


def _own(obj: object) -> bool:
    return type(obj).__module__.startswith("service.")


def object_counts() -> dict[str, float]:
    """Live objects the garbage collector tracks, by type."""
    return dict(Counter(type(o).__qualname__ for o in gc.get_objects()))


def census(root: object, name: str, trace: bool) -> dict[str, Any]:
    """RSS, container sizes, objects by type and (``trace``) a tracemalloc snapshot."""
    gc.collect()
    return {
        "rss": rss_mb(),
        "sizes": container_sizes(root, name) if root is not None else {},
        "objects": object_counts(),
        "trace": tracemalloc.take_snapshot() if trace and tracemalloc.is_tracing() else None,
    }


def census_serve(*args: Any) -> None:
    """The correlation process's main function in this bench: serves as the service's child does,
    and at each SIGUSR1 writes a :func:`census` of its correlation stage (found among the
    objects the garbage collector tracks) to the directory in ``CENSUS_DIR_ENV``.  Runs in the
    child: the spawned interpreter imports this file to find it."""
    from service.pipeline import correlation_process

    directory = Path(os.environ[CENSUS_DIR_ENV])
    trace = os.environ.get(TRACE_ENV) == "1"
    if trace:
        tracemalloc.start(1)  # from the start: a block allocated untraced and freed later is no growth
    taken = [0]

    def on_signal(signum: int, frame: Any) -> None:
        stage = next((o for o in gc.get_objects() if type(o).__name__ == "CorrelationStage"), None)
        path = directory / f"child-{taken[0]}.pickle"
        taken[0] += 1
        tmp = path.with_suffix(".tmp")
        with tmp.open("wb") as f:
            pickle.dump(census(stage, "stage", trace), f)
        tmp.rename(path)

    signal.signal(signal.SIGUSR1, on_signal)
    correlation_process._serve(*args)


class ChildCensus:
    """Asks the correlation process (run by :func:`census_serve`) for a census, one at a time."""

    def __init__(self, directory: Path) -> None:
        self.directory, self.taken = directory, 0

    def take(self, pid: int | None, timeout_s: float = 120.0) -> Path | None:
        """The file of a new census (load it once this process's own census is taken)."""
        if pid is None:
            return None
        path = self.directory / f"child-{self.taken}.pickle"
        self.taken += 1
        try:
            os.kill(pid, signal.SIGUSR1)
        except OSError:
            return None
        return path if wait_for(path.exists, timeout_s) else None

    @staticmethod
    def load(path: Path | None) -> dict[str, Any] | None:
        if path is None:
            return None
        with path.open("rb") as f:
            got: dict[str, Any] = pickle.load(f)
        return got


def print_growth(name: str, before: dict[str, Any] | None, after: dict[str, Any] | None) -> None:
    """The largest growths from one census to the next."""
    if before is None or after is None:
        print(f"{name}: no census")
        return
    print(f"{name}: RSS {before['rss']:.0f} -> {after['rss']:.0f} MB")
    for what, unit in (("sizes", "containers (items; ' kB': numpy arrays)"), ("objects", "objects by type")):
        b, a = before[what], after[what]
        grown = sorted(((a.get(k, 0) - b.get(k, 0), k) for k in set(a) | set(b)), reverse=True)
        grown = [(d, k) for d, k in grown if d > 0][:TOP]
        print(f"  {unit}, largest growths:" + ("" if grown else " none"))
        for d, k in grown:
            print(f"    {b.get(k, 0):>12,.0f} -> {a.get(k, 0):>12,.0f} ({d:+,.0f})  {k}")
    if before["trace"] is not None and after["trace"] is not None:
        total = [
            sum(s.size for s in snap.statistics("filename")) / 1e6
            for snap in (before["trace"], after["trace"])
        ]
        print(f"  Python heap (tracemalloc) {total[0]:.0f} -> {total[1]:.0f} MB; top lines:")
        for g in after["trace"].compare_to(before["trace"], "lineno")[:TOP]:
            where = f"{_short(g.traceback[0].filename)}:{g.traceback[0].lineno}"
            print(f"    {g.size_diff / 1e6:+8.2f} MB {g.count_diff:+9d} blocks  {where}")


def _short(filename: str) -> str:
    parts = Path(filename).parts
    for anchor in ("site-packages", "service", "topofusion_lab"):
        if anchor in parts:
            at = len(parts) - 1 - parts[::-1].index(anchor)
            return "/".join(parts[at + (anchor == "site-packages") :])
    return "/".join(parts[-3:])


# -- one variant, in a process of its own ------------------------------------------------------------
@dataclass
class Sample:
    wall_s: float
    published_s: float  # data time published (s since the stream's start)
    released_s: float  # data time the node's sequencer released
    behind: int  # messages published and not yet processed by the node
    rss: float
    child: float
    cpu: float  # cores this process used since the last sample
    child_cpu: float


def child_pid(node: Any) -> int | None:
    """The pid of the node's correlation process (it may change with a restart)."""
    pid = getattr(getattr(node.engine.correlation, "_process", None), "pid", None)
    return pid if isinstance(pid, int) else None


def run_variant(args: argparse.Namespace, variant: str) -> dict[str, Any]:
    from service.pipeline import correlation_process
    from service.recording.publisher import ZenohReplayPublisher
    from service.transport.node import ServiceNode
    from service.transport.session import ZenohOptions, open_session

    every = args.churn_every_s if variant == "churn" else math.inf
    t0 = time.perf_counter()
    stream = build_stream(args.scenario, args.data_s, args.seed, every)
    data_s = stream.end_s - stream.start_s
    speed = data_s / (60.0 * args.minutes)
    seq = SequencerParams()
    print(
        f"[{variant}] {args.scenario}, {data_s:.0f} data s, {len(stream.messages):,} messages, "
        f"{len(stream.ids)} radar ids"
        + (f" (one radar in turn under a new id every {every:g} data s)" if variant == "churn" else "")
        + f", generated in {time.perf_counter() - t0:.1f} s; paced at x{speed:.2f} real time over "
        f"{args.minutes:g} wall min; source_expiry_s {seq.source_expiry_s:g}, forget_after_s "
        f"{seq.forget_after_s:g}",
        flush=True,
    )
    trace_dir = tempfile.TemporaryDirectory()
    os.environ[CENSUS_DIR_ENV] = trace_dir.name
    os.environ[TRACE_ENV] = "1" if args.trace_memory else "0"
    correlation_process._serve = census_serve  # type: ignore[assignment]
    if args.trace_memory:
        tracemalloc.start(1)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    node = ServiceNode(
        EngineConfig(), ZenohOptions(mode="router", listen=(endpoint,)), correlation_process=True
    )
    node.engine.flush()  # the correlation process answers once it has started
    child = ChildCensus(Path(trace_dir.name))
    node.start()
    client = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
    publishers = ZenohReplayPublisher(client)

    samples: list[Sample] = []
    censuses: dict[str, Any] = {}
    published, published_s = 0, 0.0
    last_cpu = [cpu_s(), cpu_s(child_pid(node) or "self"), 0.0]
    max_behind = 0
    print(
        f"[{variant}] {'min':>5} {'data s':>7} {'released':>8} {'behind':>6} {'RSS MB':>7} "
        f"{'child':>6} {'cpu':>5} {'child':>5}  sources held (live/expired), views, tables",
        flush=True,
    )

    def sample(now: float) -> None:
        nonlocal max_behind
        pid = child_pid(node)
        cpu, ccpu = cpu_s(), cpu_s(pid) if pid else float("nan")
        span = max(now - last_cpu[2], 1e-9)
        released = node.engine.sequencer.last_limit - stream.start_s
        s = Sample(
            now,
            published_s,
            released if math.isfinite(released) else 0.0,
            published - node.processed,
            rss_mb(),
            rss_mb(pid) if pid else float("nan"),
            (cpu - last_cpu[0]) / span if samples else 0.0,
            (ccpu - last_cpu[1]) / span if samples else 0.0,
        )
        last_cpu[:] = [cpu, ccpu, now]
        max_behind = max(max_behind, s.behind)
        samples.append(s)
        engine = node.engine
        sources = _copy(engine.sequencer.sources)
        expired = sum(src.expired for src in sources)
        print(
            f"[{variant}] {now / 60:5.2f} {s.published_s:7.0f} {s.released_s:8.0f} {s.behind:6d} "
            f"{s.rss:7.1f} {s.child:6.1f} {s.cpu:5.2f} {s.child_cpu:5.2f}  "
            f"{len(sources) - expired}/{expired}, {len(engine.publication.views)}, "
            f"{len(engine.publication.tables)}",
            flush=True,
        )

    def take_census(when: str) -> None:
        censuses[when] = census(node, "node", args.trace_memory)
        censuses[when + " child"] = child.take(child_pid(node))

    try:
        first = stream.messages[0][1]
        if not wait_for(lambda: bool(publishers.publisher(first).matching_status.matching), 15.0):
            raise SystemExit("the node's subscriber never matched")
        start = time.monotonic()
        next_sample = 0.0
        halfway = 30.0 * args.minutes
        for time_s, key, payload in stream.messages:
            due = (time_s - stream.start_s) / speed
            while True:
                now = time.monotonic() - start
                if now >= next_sample:
                    sample(now)
                    next_sample += args.sample_s
                    if "mid" not in censuses and now >= halfway:
                        take_census("mid")
                if now >= due:
                    break
                time.sleep(max(0.0, min(due, next_sample) - now))
            kind, rid = _radar_key(key)
            if kind == "site" and rid in stream.replaces:  # the old id's publishers go
                old = key[: -len(f"{rid}/site")] + stream.replaces[rid]
                for gone in (f"{old}/site", f"{old}/plots"):
                    publishers.forget(gone)
            publishers.publisher(key).put(payload)
            published += 1
            published_s = time_s - stream.start_s
        publish_end = time.monotonic() - start

        def done() -> bool:
            return node.processed >= published and node.queue.empty() and not node.engine.answers_pending

        finished = wait_for(done, 300.0)
        drained = time.monotonic() - start
        if drained - samples[-1].wall_s >= 1.0:
            sample(drained)
        take_census("end")
        restarts = int(getattr(node.engine.correlation, "restarts", 0))
        dropped = node.queue_status()["dropped"]
        ids_held = len(node.engine.sequencer.sources)
    finally:
        publishers.close()
        client.close()
        node.stop(grace_s=60.0)
    if args.trace_memory:
        tracemalloc.stop()
    late = drained - publish_end
    print(
        f"[{variant}] {'all' if finished else 'NOT all'} {published:,} messages processed "
        f"({late:.1f} s after the last was published; most behind {max_behind}; dropped {dropped}); "
        f"correlation process restarts {restarts}; sources held at the end {ids_held}"
    )
    result = summarise(variant, samples, args.minutes)
    print_growth(f"[{variant}] this process, second half", censuses.get("mid"), censuses.get("end"))
    print_growth(
        f"[{variant}] correlation process, second half",
        ChildCensus.load(censuses.get("mid child")),
        ChildCensus.load(censuses.get("end child")),
    )
    trace_dir.cleanup()
    result.update(
        ids=len(stream.ids),
        data_s=data_s,
        speed=speed,
        kept_up=finished and dropped == 0,
        max_behind=max_behind,
        late_s=late,
    )
    return result


def summarise(variant: str, samples: list[Sample], minutes: float) -> dict[str, Any]:
    """RSS at the start, half time and end, and the slopes over the second half."""
    half = [s for s in samples if s.wall_s >= 30.0 * minutes]
    out: dict[str, Any] = {"variant": variant, "samples": [vars(s) for s in samples]}
    for name, attr in (("this process", "rss"), ("correlation process", "child")):
        series = [getattr(s, attr) for s in samples]
        slope = slope_mb_per_min([s.wall_s for s in half], [getattr(s, attr) for s in half])
        mid = getattr(half[0], attr) if half else float("nan")
        out[name] = {"start": series[0], "mid": mid, "end": series[-1], "slope": slope}
        verdict = "met" if slope <= GOAL_MB_PER_MIN else "NOT met"
        print(
            f"[{variant}] {name}: RSS {series[0]:.0f} MB at the start, {mid:.0f} at half time, "
            f"{series[-1]:.0f} at the end; {slope:+.2f} MB/min over the second half ({len(half)} "
            f"samples; goal <= {GOAL_MB_PER_MIN:g}: {verdict})",
            flush=True,
        )
    return out


# -- the variants side by side ---------------------------------------------------------------------
def side_by_side(results: list[dict[str, Any]]) -> None:
    print("\nRSS (MB) of this process (self) and of the correlation process (child), by wall minute:")
    head = f"{'min':>6}" + "".join(
        f" {r['variant'] + ' self':>12} {r['variant'] + ' child':>12}" for r in results
    )
    print(head)
    rows = max(len(r["samples"]) for r in results)
    for i in range(rows):
        cells, wall = [], float("nan")
        for r in results:
            if i < len(r["samples"]):
                s = r["samples"][i]
                wall = s["wall_s"] / 60 if not math.isfinite(wall) else wall
                cells.append(f" {s['rss']:12.1f} {s['child']:12.1f}")
            else:
                cells.append(" " * 26)
        print(f"{wall:6.2f}" + "".join(cells))
    for label, key in (("start", "start"), ("half", "mid"), ("end", "end")):
        print(
            f"{label:>6}"
            + "".join(
                f" {r['this process'][key]:12.1f} {r['correlation process'][key]:12.1f}" for r in results
            )
        )
    print(
        f"{'MB/min':>6}"
        + "".join(
            f" {r['this process']['slope']:+12.2f} {r['correlation process']['slope']:+12.2f}"
            for r in results
        )
        + f"   (least squares over the second half; goal <= {GOAL_MB_PER_MIN:g})"
    )
    for r in results:
        met = all(r[p]["slope"] <= GOAL_MB_PER_MIN for p in ("this process", "correlation process"))
        print(
            f"{r['variant']}: {r['ids']} radar ids, {r['data_s']:.0f} data s at x{r['speed']:.2f} real time; "
            f"{'kept up' if r['kept_up'] else 'DID NOT keep up'} (most {r['max_behind']} messages "
            f"behind, drained {r['late_s']:.1f} s after the last put); goal "
            + ("met in both processes" if met else "NOT met")
        )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--minutes", type=float, default=10.0, help="wall minutes of each variant (default 10)"
    )
    parser.add_argument(
        "--data-s", type=float, default=1800.0, help="data seconds of the stream (default 1800)"
    )
    parser.add_argument(
        "--churn-every-s", type=float, default=37.0, help="data s between two id changes (default 37)"
    )
    parser.add_argument("--variants", default="churn,plain", help="comma-separated: churn, plain")
    parser.add_argument("--scenario", default="three-radar", help="a lab scenario (default three-radar)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--sample-s", type=float, default=15.0, help="wall s between samples (default 15)")
    parser.add_argument(
        "--trace-memory", action="store_true", help="tracemalloc in both processes (slows them)"
    )
    # one variant, in a process of its own (see main)
    parser.add_argument("--one-variant", choices=("churn", "plain"), help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one_variant:
        result = run_variant(args, args.one_variant)
        if args.result is not None:
            args.result.write_text(json.dumps(result))
        return
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = set(variants) - {"churn", "plain"}
    if unknown or not variants:
        parser.error(f"--variants: churn and/or plain, not {', '.join(sorted(unknown)) or 'nothing'}")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for variant in variants:
            path = Path(tmp) / f"{variant}.json"
            command = [
                sys.executable,
                __file__,
                *sys.argv[1:],
                "--one-variant",
                variant,
                "--result",
                str(path),
            ]
            code = subprocess.run(command, check=False).returncode
            if code != 0 or not path.exists():
                print(f"{variant}: the run failed (exit status {code})")
                continue
            results.append(json.loads(path.read_text()))
    if results:
        side_by_side(results)


if __name__ == "__main__":
    main()
