"""Scale-out benchmark: the ``national`` scenario (``--scenario continental`` for sizing: 45 radars,
5 500 aircraft) through 1 and N partitioned workers on Zenoh.

Prints figures, never asserts.  Each run starts a Zenoh router (a router-mode session in this
process, on a free loopback port, multicast scouting off) and ``N`` workers as the operator
runs them (``topofusion run --partition K/N`` subprocesses, clients of the router, as the
service's default runs them: one worker with its correlation process, a partitioned worker in
one process; ``--one-process`` or ``--correlation-process`` gives every worker the one form),
announces the sites, then publishes the
stream as fast as the workers take it (``CongestionControl.BLOCK``, as a replay at
``--speed 0``, and waiting while a worker's queue is half full, so that none drops a
message).  A client subscribed to ``{prefix}/pairs/**`` stamps every PairSet it receives.
The run ends when worker 1's ``/status`` (the whole network's) counts every batch, every
worker's queue is empty and its merge has reached the network's release clock, and no PairSet
came for two seconds; its wall time is from the first plot batch put to the last PairSet
received.  Configurations run side by side, interleaved (``--workers 1,2`` with
``--repeat R``: 1, 2, 1, 2, ...), because the machine is noisy.

Per run: x real time (data seconds over wall seconds), CPU seconds of each worker's process
tree (worker and correlation process) and of this process (router and publisher), peak RSS of
every worker process, and accuracy from worker 1's HTTP port (the whole network): share of
confirmed pairs whose two tracks follow the same aircraft (the simulator's ``truth_id``,
evaluation only) and pair completeness; and the system tracks every worker serves (worker 1
draws them), scored as the system-track study scores them: purity, duplicated aircraft and
coverage (``topofusion_lab.evaluation.system``).  Then per worker: CPU seconds per data second
(process tree) and peak RSS, and the ratio of its CPU to one worker's (the first count of
``--workers``) on the same stream.  ``--traffic`` also subscribes to ``{prefix}/**`` and
reports messages and bytes per data second by key kind, and each worker's payload bytes sent
and received per data second (by who publishes and who subscribes to each key kind; the
subscriber makes every output be sent, so those runs are slower: their speed is not
comparable).  ``--pace X`` publishes no faster than ``X`` data seconds a wall second (each
message at its data time over ``X``), so that every configuration runs below the machine's
limit: the CPU a worker pays at a live rate, where it idles between messages.  With
``--repeat R`` it ends with every repeat's busiest-worker and total CPU ratios and their medians.
``--in-process`` runs the engines alone instead, every count's side by side in this process,
message by message (:func:`in_process`): the division of the engines' own work, which a drift
of the machine's speed between runs cannot move; ``--breakdown`` splits each engine's CPU by
what it was for (:class:`Breakdown`).  ``--no-aid`` runs every worker with the aid of
association off (``tracking.aid.enabled``, on by default; ``--aid``, the default, stays for
the commands of earlier measurements).

Run: .venv/bin/python bench/bench_partition.py [--duration 300] [--seed 1] [--scenario national]
     [--workers 1,2] [--repeat 1] [--one-process | --correlation-process] [--balance | --salt S] [--pace X]
     [--traffic] [--no-aid] [--in-process [--breakdown]]
     [--cache FILE] [--compare] [--logs DIR]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path
from statistics import median
from typing import Any

import httpx
import zenoh
from checkout import warn_if_elsewhere

from service.config import EngineConfig, without_aid
from service.engine import Engine
from service.pipeline.partition import PAIR_KM, Partition, balanced_salt, candidate_pairs, pair_name
from service.transport.session import ZenohOptions, open_session
from service.wire.keys import Keys, parse_key
from topofusion_lab.demo_workers import descendants
from topofusion_lab.evaluation.system import score
from topofusion_lab.pacing import Pacer
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import wire_messages

TOPOFUSION = str(Path(sys.executable).parent / "topofusion")
PREFIX = "fusion"
#: The publisher looks at the workers' queues every this many messages, and waits while one
#: holds more than PACE_DEPTH (half the default queue).
PACE_EVERY = 256
PACE_DEPTH = 2048
#: How often the benchmark asks the workers' /status while it waits (s).  Every call costs the
#: worker a status build (about a millisecond on the national network), which counts in its
#: CPU: ten a second from the first worker's status, all through a run, would be a cost no
#: deployment has.
POLL_S = 0.5
TICK = os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait(predicate: Any, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            if predicate():
                return
        except (httpx.HTTPError, KeyError, ValueError):
            pass
        time.sleep(POLL_S)
    raise SystemExit(f"timed out waiting for {what}")


# -- processes -------------------------------------------------------------------------------
def tree(pid: int) -> list[int]:
    """``pid`` and every process below it."""
    return [pid, *descendants(pid)]


def cpu_s(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / TICK


def peak_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


@dataclass
class Worker:
    index: int
    count: int
    port: int
    proc: subprocess.Popen[bytes]
    cpu0: dict[int, float] = field(default_factory=dict)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def get(self, path: str, **params: Any) -> Any:
        return httpx.get(self.url + path, params=params, timeout=30).json()

    def tree_cpu(self) -> float:
        return sum(self.cpus())

    def cpus(self) -> list[float]:
        """CPU s of the worker process and each of its children since the run started."""
        return [cpu_s(p) - self.cpu0.get(p, 0.0) for p in tree(self.proc.pid)]


def process_setting(args: argparse.Namespace) -> bool | None:
    """``TOPOFUSION_CORRELATION_PROCESS`` for every worker (None: the service's default)."""
    return True if args.correlation_process else False if args.one_process else None


def start_workers(
    n: int,
    endpoint: str,
    process: bool | None,
    log_dir: Path | None = None,
    salt: int = 0,
    aid: bool = True,
) -> list[Worker]:
    workers = []
    for k in range(1, n + 1):
        port = free_port()
        env = {key: v for key, v in os.environ.items() if not key.startswith("TOPOFUSION_")}
        env.update(
            TOPOFUSION_PARTITION=f"{k}/{n}",
            TOPOFUSION_PARTITION_SALT=str(salt),
            TOPOFUSION_ZENOH_MODE="client",
            TOPOFUSION_ZENOH_CONNECT=endpoint,
            TOPOFUSION_HTTP_PORT=str(port),
            TOPOFUSION_PREFIX=PREFIX,
            TOPOFUSION_LOG_LEVEL="WARNING",
        )
        if process is not None:  # (None: the service's default)
            env["TOPOFUSION_CORRELATION_PROCESS"] = "true" if process else "false"
        if not aid:  # the aid of association off (on by default)
            env["TOPOFUSION_ENGINE__TRACKING__AID__ENABLED"] = "false"
        # --logs DIR keeps each worker's log (e.g. "worker 2/2 left" when a session flaps)
        log_path = Path(log_dir) / f"worker-{k}-of-{n}.log" if log_dir else Path(os.devnull)
        with log_path.open("w") as log:
            proc = subprocess.Popen([TOPOFUSION, "run"], env=env, stdout=subprocess.DEVNULL, stderr=log)
        workers.append(Worker(k, n, port, proc))
    for w in workers:
        wait(lambda w=w: httpx.get(w.url + "/readyz", timeout=2).status_code == 200, 60, f"worker {w.index}")
    if n > 1:
        wait(lambda: workers[0].get("/status")["partition"]["missing"] == [], 30, "every worker alive")
    return workers


def stop_workers(workers: list[Worker]) -> None:
    for w in workers:
        w.proc.send_signal(signal.SIGTERM)
    for w in workers:
        try:
            w.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            w.proc.kill()
            w.proc.wait()


# -- the stream and its truth ----------------------------------------------------------------
def make_stream(scenario: str, duration_s: float, seed: int, cache: Path | None) -> list[tuple[str, bytes]]:
    sc = replace(get_scenario(scenario), duration_s=duration_s)
    tag = hashlib.sha256(repr((sc, seed)).encode()).hexdigest()[:16]
    if cache is not None and cache.exists():
        with cache.open("rb") as f:
            stored, stream = pickle.load(f)
        if stored == tag:
            return list(stream)
    stream = list(wire_messages(sc, seed, PREFIX))
    if cache is not None:
        with cache.open("wb") as f:
            pickle.dump((tag, stream), f)
    return stream


def labels(w: Worker, radars: list[str]) -> tuple[dict[tuple[str, str], str | None], dict[str, set[str]]]:
    """Each radar track's aircraft (``truth_id``), and each radar's aircraft with a confirmed
    track, from the whole network's tracks."""
    truth: dict[tuple[str, str], str | None] = {}
    confirmed: dict[str, set[str]] = {}
    for rid in radars:
        batch = w.get(f"/radars/{rid}/tracks", status="all")
        confirmed[rid] = set()
        for t in batch["tracks"]:
            truth[(rid, t["track_id"])] = t["truth_id"]
            if t["status"] == "confirmed" and t["truth_id"] is not None:
                confirmed[rid].add(t["truth_id"])
    return truth, confirmed


def system_accuracy(workers: list[Worker], radars: list[str]) -> tuple[int, float, float, float, bool]:
    """(confirmed system tracks, purity, duplicated aircraft, coverage) of worker 1's system
    tracks, and whether every other worker serves the same."""
    truth, confirmed = labels(workers[0], radars)
    bodies = [w.get("/system-tracks", status="all") for w in workers]
    seen = set().union(*confirmed.values())
    s = score(bodies[0], truth, seen, {}, lambda aircraft, time_s: None)
    return s.tracks, s.purity, s.duplicates, s.coverage, all(b == bodies[0] for b in bodies[1:])


def accuracy(w: Worker, radars: list[str]) -> tuple[int, int, int, int]:
    """(correct, false, found, common) from the whole network's pairs and tracks."""
    truth, confirmed = labels(w, radars)
    correct = false = found = common = 0
    for ps in w.get("/pairs", status="confirmed"):
        a, b = ps["radar_a"], ps["radar_b"]
        good = set()
        for p in ps["pairs"]:
            ta, tb = truth.get((a, p["track_a"])), truth.get((b, p["track_b"]))
            if ta is not None and ta == tb:
                correct += 1
                good.add(ta)
            elif (a, p["track_a"]) in truth and (b, p["track_b"]) in truth:
                false += 1
        both = confirmed.get(a, set()) & confirmed.get(b, set())
        common += len(both)
        found += len(both & good)
    return correct, false, found, common


# -- one run -----------------------------------------------------------------------------------
@dataclass
class Result:
    workers: int
    x_real_time: float
    wall_s: float
    cpu_workers: list[float]
    cpu_bench: float
    peaks: list[list[float]]
    correct: int
    false: int
    found: int
    common: int
    pair_sets: int
    traffic: dict[str, list[float]]
    sequences: dict[str, list[bytes]]
    data_s: float = 0.0
    #: Confirmed system tracks, purity, duplicated aircraft, coverage, served alike by all.
    system: tuple[int, float, float, float, bool] = (0, 0.0, 0.0, 0.0, False)
    #: Payload bytes each worker sent and received per data second (``--traffic``).
    sent: list[float] = field(default_factory=list)
    received: list[float] = field(default_factory=list)
    #: Radars and radar pairs (of those with a pair set) each worker owns.
    shares: list[tuple[int, int]] = field(default_factory=list)
    salt: int = 0


def endpoints(kind: str, ids: tuple[str, ...], n: int) -> tuple[int | None, list[int]]:
    """Who publishes a key of ``kind`` (None: an input or output of no worker's) and which
    workers take it (by their subscriptions: every plot goes to every worker)."""
    part = Partition(1, n)
    everyone = list(range(1, n + 1))
    if kind in ("plots", "site"):
        return None, everyone
    if kind in ("track_states", "tracks"):
        k = part.owner(ids[0])
        return k, [j for j in everyone if j != k] if kind == "track_states" else []
    if kind in ("registration", "links", "pairs"):
        k = part.owner(pair_name(ids[0], ids[1]))
        return k, [1] if kind != "pairs" and k != 1 else []
    if kind in ("worker_clock", "worker_progress", "worker_status"):
        k = int(ids[0])
        return k, [j for j in everyone if j != k]
    if kind == "biases":
        return 1, everyone[1:]
    if kind == "system_tracks":
        return 1, []
    return None, []


def balanced(n: int, stream: list[tuple[str, bytes]]) -> int:
    """The salt ``topofusion partition --balance`` gives for the stream's sites and N workers."""
    sites = [json.loads(p) for k, p in stream if k.endswith("/site")]
    positions = {s["radar_id"]: (s["latitude_deg"], s["longitude_deg"]) for s in sites}
    return balanced_salt(n, sorted(positions), candidate_pairs(sorted(positions), positions, PAIR_KM * 1e3))


def worker_salt(n: int, stream: list[tuple[str, bytes]], args: argparse.Namespace) -> int:
    """The salt N > 1 workers are given: ``--salt``, else ``--balance``'s, else 0."""
    if n == 1:
        return 0
    if args.salt is not None:
        return int(args.salt)
    return balanced(n, stream) if args.balance else 0


def one_run(n: int, stream: list[tuple[str, bytes]], data_s: float, args: argparse.Namespace) -> Result:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohOptions(mode="router", listen=(endpoint,)))
    salt = worker_salt(n, stream, args)
    workers = start_workers(n, endpoint, process_setting(args), args.logs, salt, not args.no_aid)
    client = open_session(ZenohOptions(mode="client", connect=(endpoint,)))
    last_pairs = [0.0, 0]
    lock = threading.Lock()
    traffic: dict[str, list[float]] = defaultdict(lambda: [0, 0])
    sent, received = [0.0] * (n + 1), [0.0] * (n + 1)

    sequences: dict[str, list[bytes]] = defaultdict(list)

    def on_pairs(sample: zenoh.Sample) -> None:
        with lock:
            last_pairs[0] = time.perf_counter()
            last_pairs[1] += 1
            sequences[str(sample.key_expr)].append(sample.payload.to_bytes())

    def on_any(sample: zenoh.Sample) -> None:
        kind, ids = parse_key(str(sample.key_expr), PREFIX)
        size = len(sample.payload.to_bytes())
        by, to = endpoints(kind, ids, n)
        with lock:
            t = traffic[kind]
            t[0] += 1
            t[1] += size
            if by is not None:
                sent[by] += size
            for k in to:
                received[k] += size

    subs = [client.declare_subscriber(f"{PREFIX}/pairs/**", on_pairs)]
    if args.traffic:
        subs.append(client.declare_subscriber(f"{PREFIX}/**", on_any))
    pubs: dict[str, Any] = {}

    def put(key: str, payload: bytes) -> None:
        pub = pubs.get(key)
        if pub is None:
            pub = pubs[key] = client.declare_publisher(
                key,
                encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
        pub.put(payload)

    try:
        time.sleep(1.0)
        sites = [(k, p) for k, p in stream if k.endswith("/site")]
        radars = sorted(json.loads(p)["radar_id"] for _, p in sites)
        for key, payload in sites:
            put(key, payload)
        for w in workers:
            wait(lambda w=w: len(w.get("/radars")) == len(radars), 30, f"sites at worker {w.index}")
        n_batches = sum(k.endswith("/plots") for k, _ in stream)
        for w in workers:
            w.cpu0 = {p: cpu_s(p) for p in tree(w.proc.pid)}
        rest = stream[len(sites) :]
        # each message's data time (None: it has none), read before the clock starts; [] unpaced
        due = [json.loads(payload).get("time_s") for _, payload in rest] if args.pace > 0 else []
        pacer = Pacer(args.pace, threading.Event())
        bench_cpu0 = time.process_time()
        t0 = time.perf_counter()
        progress = time.monotonic()
        for i, (key, payload) in enumerate(rest):
            if due and isinstance(due[i], (int, float)):  # ``pace`` data seconds a wall second
                pacer.due(float(due[i]))
            put(key, payload)
            if i % PACE_EVERY == PACE_EVERY - 1:
                # a worker's queue drops what does not fit (its capacity, 4 096 samples): keep
                # every worker's backlog under half of it, so that nothing is lost
                while max(w.get("/status")["queue"]["depth"] for w in workers) > PACE_DEPTH:
                    time.sleep(POLL_S)
            if time.monotonic() - progress > 10:
                progress = time.monotonic()
                print(f"#   published {i}/{len(stream)}", file=sys.stderr, flush=True)

        def batches() -> int:
            return sum(r["batches"] for r in workers[0].get("/status")["radars"])

        wait(lambda: batches() == n_batches, 3600, "every batch counted")

        def caught_up() -> bool:
            """Every queue empty and every worker's merge at the network's release clock."""
            statuses = [w.get("/status") for w in workers]
            if any(st["queue"]["depth"] for st in statuses):
                return False
            if n == 1:
                return True
            progress = [st["partition"]["progress"] for st in statuses]
            released = min(p["released_s"] or 0.0 for p in progress)
            return all((p["merged_s"] or 0.0) >= released for p in progress)

        def quiet() -> bool:
            with lock:
                silent = time.perf_counter() - last_pairs[0] > 2.0
            return silent and caught_up()

        wait(quiet, 3600, "the last pair updates")
        wall = last_pairs[0] - t0
        cpu_workers = [w.tree_cpu() for w in workers]
        print(f"#   CPU s by process: {[[round(c, 1) for c in w.cpus()] for w in workers]}", file=sys.stderr)
        cpu_bench = time.process_time() - bench_cpu0
        peaks = [[peak_mb(p) for p in tree(w.proc.pid)] for w in workers]
        correct, false, found, common = accuracy(workers[0], radars)
        system = system_accuracy(workers, radars)
        held = workers[0].get("/pairs", status="all")
        pair_sets = len(held)
        shares = [
            (
                sum(Partition(k, n, salt).owns(r) for r in radars),
                sum(Partition(k, n, salt).owns_pair(ps["radar_a"], ps["radar_b"]) for ps in held),
            )
            for k in range(1, n + 1)
        ]
        print(f"#   status: {workers[0].get('/status')['pairs_confirmed']} confirmed pairs", file=sys.stderr)
    finally:
        for s in subs:
            s.undeclare()
        client.close()
        stop_workers(workers)
        router.close()
    return Result(
        n,
        data_s / wall,
        wall,
        cpu_workers,
        cpu_bench,
        peaks,
        correct,
        false,
        found,
        common,
        pair_sets,
        {k: [v[0] / data_s, v[1] / data_s] for k, v in traffic.items()},
        dict(sequences),
        data_s,
        system,
        [b / data_s for b in sent[1:]] if args.traffic else [],
        [b / data_s for b in received[1:]] if args.traffic else [],
        shares,
        salt,
    )


def report(r: Result, one: Result | None = None) -> None:
    """One run's figures (``one``: the run of the first worker count, for the CPU ratios)."""
    judged = max(r.correct + r.false, 1)
    peaks = "; ".join("+".join(f"{p:.0f}" for p in w) for w in r.peaks)
    salted = f" (salt {r.salt})" if r.salt else ""
    print(
        f"  {r.workers} worker(s){salted}: {r.x_real_time:5.1f}x real time (wall {r.wall_s:.1f} s); "
        f"CPU s per worker {', '.join(f'{c:.1f}' for c in r.cpu_workers)} (bench process "
        f"{r.cpu_bench:.1f}); peak RSS MB per worker (process+children) {peaks}"
    )
    print(
        f"    pairs: {r.correct + r.false} confirmed in {r.pair_sets} radar pairs, correct {r.correct} "
        f"({100 * r.correct / judged:.2f}%), false {r.false}; completeness {r.found}/{r.common} "
        f"({100 * r.found / max(r.common, 1):.1f}%)"
    )
    tracks, purity, duplicates, coverage, same = r.system
    print(
        f"    system tracks (worker 1's): {tracks} confirmed, purity {100 * purity:.2f}%, duplicated "
        f"aircraft {100 * duplicates:.2f}%, coverage {100 * coverage:.2f}%; "
        f"{'every worker serves the same' if same else 'NOT the same on every worker'}"
    )
    base = sum(one.cpu_workers) if one is not None else None
    for k, (cpu, peak) in enumerate(zip(r.cpu_workers, r.peaks, strict=True), start=1):
        ratio = f", {cpu / base:.2f}x one worker's" if base else ""
        owns = f"owns {r.shares[k - 1][0]} radars, {r.shares[k - 1][1]} pairs; " if r.shares else ""
        io = (
            f"; payload sent {r.sent[k - 1] / 1e3:.1f} kB/s, received {r.received[k - 1] / 1e3:.1f} kB/s"
            if r.sent
            else ""
        )
        print(
            f"    worker {k}/{r.workers}: {owns}CPU {cpu / r.data_s:.3f} s per data s{ratio}; peak RSS "
            f"{'+'.join(f'{p:.0f}' for p in peak)} MB{io}"
        )
    if base:
        print(f"    total CPU {sum(r.cpu_workers) / base:.2f}x one worker's")
    if r.traffic:
        print("    Zenoh traffic per data second, by key kind (messages, kB):")
        for kind, (msgs, nbytes) in sorted(r.traffic.items(), key=lambda kv: -kv[1][1]):
            print(f"      {kind:14s} {msgs:8.1f} msg/s {nbytes / 1e3:9.1f} kB/s")


def in_process(
    counts: list[int], stream: list[tuple[str, bytes]], data_s: float, args: argparse.Namespace
) -> None:
    """``--in-process``: one engine per worker of every count, all in this process (no Zenoh, no
    correlation process, no HTTP), fed message by message side by side: each input goes to
    every count's engines (a partitioned one takes only its own radars' plots, as its
    subscription's filter does), and what an engine puts for the other workers reaches them
    before the next input.  Each engine's CPU is its thread's time in ``ingest`` (and in
    encoding what it puts for the others and its pair sets), so a drift of the machine's speed
    weighs on every count alike: the division of the engines' own work, without the costs of
    transport, pipes and status, which the process figures add."""
    keys = Keys(PREFIX)
    split = Breakdown() if args.breakdown else None
    groups: list[list[tuple[Partition, Engine]]] = []
    for n in counts:
        salt = worker_salt(n, stream, args)
        parts = [Partition(k, n, salt) for k in range(1, n + 1)]
        base = without_aid(EngineConfig(prefix=PREFIX)) if args.no_aid else EngineConfig(prefix=PREFIX)
        groups.append([(part, Engine(replace(base, partition=part))) for part in parts])
    cpu = [[0.0] * len(g) for g in groups]
    waiting: list[list[list[tuple[str, bytes]]]] = [[[] for _ in g] for g in groups]

    def run(c: int, j: int, items: list[tuple[str, bytes]]) -> None:
        engine = groups[c][j][1]
        if split is not None:
            split.engine = (c, j)
        t = time.thread_time()
        out = [o for key, payload in items for o in engine.ingest(key, payload)]
        peer = [(o.key, o.payload) for o in out if keys.classify_peer(o.key) is not None]
        pairs = time.thread_time()
        for o in out:
            if "/pairs/" in o.key:
                o.payload  # noqa: B018  (encoded, as for the benchmark's subscriber)
        end = time.thread_time()
        cpu[c][j] += end - t
        if split is not None:
            split.add("pairs", end - pairs)
        for other in range(len(groups[c])):
            if other != j:
                waiting[c][other] += peer

    step = max(1, len(stream) // 10)
    for i, (key, payload) in enumerate(stream):
        kind, ids = parse_key(key, PREFIX)
        for c, group in enumerate(groups):
            for j, (part, _) in enumerate(group):
                items, waiting[c][j] = waiting[c][j], []
                if not (kind == "plots" and not part.owns(ids[0])):
                    items.append((key, payload))
                run(c, j, items)
        if (i + 1) % step == 0:
            print(f"#   {i + 1}/{len(stream)} messages", file=sys.stderr, flush=True)
    while any(w for ws in waiting for w in ws):  # the last messages between the workers
        for c, group in enumerate(groups):
            for j in range(len(group)):
                items, waiting[c][j] = waiting[c][j], []
                run(c, j, items)
    one = sum(cpu[0])
    for n, group, spent in zip(counts, groups, cpu, strict=True):
        each = ", ".join(
            f"{x / data_s:.3f}" + (f" ({x / one:.2f}x)" if n != counts[0] else "") for x in spent
        )
        print(f"  {n} engine(s): CPU s per data s {each}")
        if n != counts[0]:
            print(f"    busiest {max(spent) / one:.2f}x, total {sum(spent) / one:.2f}x one engine's")
        if split is not None:
            split.report(counts.index(n), spent, one)
        for _, engine in group:
            engine.close()
    if split is not None:
        split.close()


class Breakdown:
    """``--breakdown``: each engine's CPU split by what it was for, as shares of one engine's
    whole CPU (the first count's): tracking its radars' batches, its pairs' correlation (the
    pair updates and decisions, and encoding their pair sets), taking what the other workers
    send (decoding and applying their track states, links, rows and progress), and the rest
    (each table's bookkeeping in the correlation stage, the merge, the picture and the biases,
    publication).  It times the
    engine's own functions from outside (wrapped here, for the run); the rest is what they
    leave of the engine's thread time."""

    WRAPPED: tuple[tuple[str, str, str, str], ...] = (
        ("tracking", "service.pipeline.tracking_stage", "TrackingStage", "update"),
        ("pairs", "service.correlation.correlator", "PairCorrelator", "update"),
        ("pairs", "service.correlation.correlator", "PairCorrelator", "decide_new"),
        ("from the others", "service.pipeline.peers", "Peers", "ingest"),
    )
    KINDS = ("tracking", "pairs", "from the others")

    def __init__(self) -> None:
        import importlib

        self.engine = (0, 0)
        self.spent: dict[tuple[int, int], dict[str, float]] = defaultdict(
            lambda: dict.fromkeys(self.KINDS, 0.0)
        )
        self._restore: list[tuple[Any, str, Any]] = []
        for kind, module, cls_name, name in self.WRAPPED:
            cls = getattr(importlib.import_module(module), cls_name)
            self._restore.append((cls, name, getattr(cls, name)))
            setattr(cls, name, self._timed(kind, getattr(cls, name)))

    def _timed(self, kind: str, f: Any) -> Any:
        def timed(*a: Any, **k: Any) -> Any:
            t = time.thread_time()
            try:
                return f(*a, **k)
            finally:
                self.add(kind, time.thread_time() - t)

        return timed

    def add(self, kind: str, seconds: float) -> None:
        self.spent[self.engine][kind] += seconds

    def report(self, c: int, spent: list[float], one: float) -> None:
        for j, total in enumerate(spent):
            parts = self.spent[(c, j)]
            rest = total - sum(parts.values())
            shares = ", ".join(f"{k} {v / one:.3f}" for k, v in (*parts.items(), ("rest", rest)))
            print(f"    engine {j + 1}: {shares} of one engine's CPU")

    def close(self) -> None:
        for cls, name, f in self._restore:
            setattr(cls, name, f)


def main() -> None:
    warn_if_elsewhere()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--duration", type=float, default=300.0, help="data seconds (default 300)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument(
        "--scenario", default="national", help="national (default), or continental for sizing (45 radars)"
    )
    p.add_argument("--workers", default="1,2", help="worker counts, side by side (default 1,2)")
    p.add_argument("--repeat", type=int, default=1)
    form = p.add_mutually_exclusive_group()
    form.add_argument("--one-process", action="store_true", help="every worker without a correlation process")
    form.add_argument(
        "--correlation-process", action="store_true", help="every worker with its correlation process"
    )
    p.add_argument(
        "--balance",
        action="store_true",
        help="give the workers the salt `topofusion partition --balance` finds for the sites",
    )
    p.add_argument(
        "--salt",
        type=int,
        help="give the workers this salt (TOPOFUSION_PARTITION_SALT) instead of --balance's: "
        "other assignments of the same network, to measure what a radar and a pair cost",
    )
    p.add_argument(
        "--pace",
        type=float,
        default=0.0,
        help="publish no faster than this many data seconds a wall second (default 0: as fast as "
        "the workers take it); below the machine's limit every configuration runs unsaturated",
    )
    p.add_argument("--traffic", action="store_true", help="count every message by key kind (slower)")
    aid = p.add_mutually_exclusive_group()
    aid.add_argument(
        "--aid",
        action="store_true",
        help="every worker with the aid of association on (tracking.aid.enabled), as by default",
    )
    aid.add_argument(
        "--no-aid",
        action="store_true",
        help="every worker with the aid of association off: what the aid costs",
    )
    p.add_argument(
        "--in-process",
        action="store_true",
        help="the engines alone, side by side in this process: their division free of the machine's drift",
    )
    p.add_argument(
        "--breakdown",
        action="store_true",
        help="with --in-process: each engine's CPU by what it was for (tracking, its pairs, what "
        "the other workers send, the rest)",
    )
    p.add_argument("--cache", type=Path, help="keep the generated stream in this file")
    p.add_argument(
        "--compare",
        action="store_true",
        help="(kept for old command lines: the radar pairs whose updates differ are always listed)",
    )
    p.add_argument("--logs", type=Path, help="write each worker's log into this folder")
    args = p.parse_args()
    counts = [int(x) for x in args.workers.split(",")]
    stream = make_stream(args.scenario, args.duration, args.seed, args.cache)
    plots = sum(len(json.loads(pl)["plots"]["time_s"]) for k, pl in stream if k.endswith("/plots"))
    times = [json.loads(pl)["time_s"] for k, pl in stream if k.endswith("/plots")]
    data_s = max(times) - min(times)
    how = (
        "engines in this process"
        if args.in_process
        else {
            None: "one worker with its correlation process, partitioned workers in one process each "
            "(the service's default)",
            True: "every worker with its correlation process",
            False: "every worker in one process",
        }[process_setting(args)]
    )
    print(
        f"# {args.scenario} scenario, {args.duration:g} s of data (seed {args.seed}): "
        f"{len(stream)} messages, {plots} plots; {how}; {os.cpu_count()} cores"
    )
    print(f"# command: {' '.join(sys.argv)}")
    if args.in_process:
        in_process(counts, stream, data_s, args)
        return
    results: dict[int, list[Result]] = defaultdict(list)
    for rep in range(args.repeat):
        for n in counts:
            print(f"# run {rep + 1}/{args.repeat}: {n} worker(s)", file=sys.stderr, flush=True)
            r = one_run(n, stream, data_s, args)
            results[n].append(r)
            report(r, results[counts[0]][-1] if n != counts[0] else None)
    base = counts[0]
    for n in counts[1:]:
        for rep, (one, many) in enumerate(zip(results[base], results[n], strict=True), start=1):
            same, differ = compare_sequences(one.sequences, many.sequences)
            print(
                f"# pair update sequences equal to {base} worker(s)'s: {same}/{len(one.sequences)} radar "
                f"pairs" + (f" (run {rep})" if args.repeat > 1 else "")
            )
            for line in differ:
                print(f"#   {line}")
        ratios = [b.x_real_time / a.x_real_time for a, b in zip(results[base], results[n], strict=True)]
        print(
            f"# {n} workers / {base}: {', '.join(f'{x:.2f}' for x in ratios)} "
            f"(median {sorted(ratios)[len(ratios) // 2]:.2f})"
        )
    if args.repeat > 1:
        cpu_ratios(results, counts)


def compare_sequences(a: dict[str, list[bytes]], b: dict[str, list[bytes]]) -> tuple[int, list[str]]:
    """How many radar pairs of ``a`` (one worker's PairSets by key, in order of arrival) ``b``
    published alike, and a line for each other: where the two first differ, or how many
    updates ``b`` lacks at the end.  The newest update of a pair may be held back at the end
    of a run (the merge waits for the partner's next release), so ``b`` may lack one."""
    same, differ = 0, []
    for k in sorted(a):
        x, y = a[k], b.get(k, [])
        d = next((i for i in range(min(len(x), len(y))) if x[i] != y[i]), None)
        if d is None and len(y) >= len(x) - 1:
            same += 1
        elif d is None:
            differ.append(f"{k}: {len(x)} vs {len(y)} updates, the last {len(x) - len(y)} missing")
        else:
            differ.append(
                f"{k}: {len(x)} vs {len(y)} updates, first difference at {d}: "
                f"{json.loads(x[d])['time_s']} / {json.loads(y[d])['time_s']}"
            )
    return same, differ


def cpu_ratios(results: dict[int, list[Result]], counts: list[int]) -> None:
    """The CPU ratios of every repeat side by side, and their medians: on a noisy machine one
    run's ratio can be off by a sixth (the first count's own CPU varies as much)."""
    base = counts[0]
    ones = [sum(r.cpu_workers) / r.data_s for r in results[base]]
    print(
        f"# {base} worker(s), CPU s per data s: {', '.join(f'{x:.3f}' for x in ones)} "
        f"(median {median(ones):.3f})"
    )
    for n in counts[1:]:
        pairs = list(zip(results[base], results[n], strict=True))
        busiest = [max(b.cpu_workers) / sum(a.cpu_workers) for a, b in pairs]
        total = [sum(b.cpu_workers) / sum(a.cpu_workers) for a, b in pairs]
        print(
            f"# {n} workers against the {base}-worker run beside each: busiest "
            f"{', '.join(f'{x:.2f}' for x in busiest)} (median {median(busiest):.2f}); total "
            f"{', '.join(f'{x:.2f}' for x in total)} (median {median(total):.2f})"
        )


if __name__ == "__main__":
    main()
