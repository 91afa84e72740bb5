"""ADS-B reference study: radar-ADS-B pairs and absolute bias estimates under varied conditions.

Entry point :func:`run` (``topofusion evaluate --only adsb``).  Every run is a real stream of
the simulator (:mod:`topofusion_lab.scenarios.simulator`, the bytes of ``wire_messages``)
through the service's :class:`~service.engine.Engine` with its default configuration, in
process: radar plot batches and one ADS-B receiver's ``AdsbBatch`` messages.  The engine
correlates each radar with the ADS-B source (method ``cfar``) and registers it to it, which
makes its bias estimates (``/biases``) absolute.  Nothing of the service is tuned here.

Conditions (:data:`CONDITIONS`), ``runs`` each, every run with its own seed and its own
radar biases drawn per radar: range bias 100-600 m, azimuth bias 0.1-0.5 deg (random signs),
elevation bias uniform in +-0.15 deg.

* *Lone radar*: the two-radar catalog scenario's radar A alone (Mode S: its plots carry the
  aircraft's codes) and an ADS-B receiver hearing every ``stride``-th aircraft; one factor at
  a time from a baseline (equipage, traffic, clutter, reports without height, ADS-B position
  error), and two combinations of the hard settings.
* *Network*: the two-radar scenario's radars A and B, or the three-radar scenario's A, B and
  C, with the ADS-B receiver.

Scoring (evaluation only: by the simulator's truth), per radar, on the final snapshot (after
``Engine.flush``):

* a confirmed radar-ADS-B pair is *correct* when the truth aircraft of its radar track has the
  address ``track_b`` (:func:`~topofusion_lab.scenarios.simulator.identity_of`), otherwise
  *false*;
* *common* aircraft: equipped aircraft heard by the receiver in the last :data:`RECENT_S`
  seconds that hold a confirmed track of the radar; *completeness* = common aircraft with a
  correct confirmed pair / common aircraft;
* *settled*: a common aircraft whose (earliest) confirmed radar track was confirmed and whose
  address was first heard (with a height) at least :data:`SETTLE_S` before the end; a pair is
  settled when its radar track and its address both are that old;
* *precision* = correct / confirmed pairs, *false rate* = false / confirmed pairs (all pairs,
  settled or not);
* bias errors: ``|estimate - truth|`` of the service's ``/biases`` per radar, and relative to
  ``|truth|`` for range and azimuth;
* identity figure: ``status()["identity"]`` (confirmed pairs whose two tracks both carry a
  Mode S address, and the share that agree), radar-ADS-B pairs only.

Through each run the same scoring at every :data:`CHECK_S` of data time gives completeness and
false rate pooled over the run, and against age (time since both the radar track was confirmed
and the address heard) for the figure; every ``cfar`` update of a radar with the ADS-B source
is watched (``Engine.pair_correlators``): how many pairs it decided against the confirmed pairs.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from service.engine import Engine
from service.tracking.base import TrackTable
from service.wire.keys import Keys
from topofusion_lab.evaluation.jobs import ratio, run_jobs
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import AdsbSpec, RadarSpec, Scenario, generate, identity_of

ADSB_ID = "adsb"
PREFIX = "fusion"
LONE = "Lone radar"
NETWORK = "Network"
#: Data seconds of every run.
DURATION_S = 480.0
#: Runs per condition by default.
DEFAULT_RUNS = 12
#: An address counts as heard "now" when reported this recently (data seconds).
RECENT_S = 10.0
#: Age (s) from which a common aircraft or a pair counts as settled.
SETTLE_S = 60.0
#: Radar tracks' first confirmation is looked up this often (data seconds).
POLL_S = 4.0
#: The age curve's scoring interval (data seconds).
CHECK_S = 20.0
AGE_BIN_S = 20.0
GOAL_COMPLETE = 0.95
GOAL_FALSE = 0.02
GOAL_BIAS = 0.10
#: A ``cfar`` update is *short* when it decides fewer than this share of the confirmed pairs.
SHORT_UPDATE = 0.5


@dataclass(frozen=True)
class Condition:
    label: str
    group: str
    #: 1: the lone radar A; 2: A and B of ``two-radar``; 3: A, B, C of ``three-radar``.
    radars: int = 1
    targets: int = 120
    stride: int = 2
    #: Clutter plots per scan of every radar (None: the catalog scenario's own).
    clutter_per_scan: float | None = 0.0
    no_height: float = 0.0
    position_sigma_m: float = 10.0


CONDITIONS: tuple[Condition, ...] = (
    Condition("baseline: 120 aircraft, 1 in 2 equipped", LONE),
    Condition("every aircraft equipped", LONE, stride=1),
    Condition("1 in 4 equipped", LONE, stride=4),
    Condition("40 aircraft", LONE, targets=40),
    Condition("250 aircraft", LONE, targets=250),
    Condition("clutter 30 / scan", LONE, clutter_per_scan=30.0),
    Condition("30 % of reports without height", LONE, no_height=0.3),
    Condition("ADS-B position sigma 30 m", LONE, position_sigma_m=30.0),
    Condition(
        "hard, all equipped: 250 aircraft, clutter 30, 30 % no height, 30 m",
        LONE,
        targets=250,
        stride=1,
        clutter_per_scan=30.0,
        no_height=0.3,
        position_sigma_m=30.0,
    ),
    Condition(
        "hard, 1 in 4 equipped: 250 aircraft, clutter 30, 30 % no height, 30 m",
        LONE,
        targets=250,
        stride=4,
        clutter_per_scan=30.0,
        no_height=0.3,
        position_sigma_m=30.0,
    ),
    Condition("A, B (two-radar) + ADS-B", NETWORK, radars=2, clutter_per_scan=None),
    Condition("A, B, C (three-radar, clutter 20 on A, B) + ADS-B", NETWORK, radars=3, clutter_per_scan=None),
)


@dataclass(frozen=True)
class Job:
    index: int
    condition: Condition
    seed: tuple[int, ...]
    duration_s: float


# -- scene --------------------------------------------------------------------------------


def draw_bias(rng: np.random.Generator) -> dict[str, float]:
    """One radar's biases: range 100-600 m, azimuth 0.1-0.5 deg (random signs), elevation
    uniform in +-0.15 deg."""
    sign = rng.choice([-1.0, 1.0], size=2)
    return {
        "range_bias_m": float(sign[0] * rng.uniform(100.0, 600.0)),
        "azimuth_bias_deg": float(sign[1] * rng.uniform(0.1, 0.5)),
        "elevation_bias_deg": float(rng.uniform(-0.15, 0.15)),
    }


def scenario_of(job: Job) -> tuple[Scenario, int]:
    """The job's scenario (biases drawn from its seed) and the simulator's seed."""
    c = job.condition
    rng = np.random.default_rng(np.random.SeedSequence(list(job.seed)))
    base = get_scenario("three-radar" if c.radars == 3 else "two-radar")
    radars: list[RadarSpec] = []
    for r in base.radars[: c.radars]:
        clutter = r.clutter_per_scan if c.clutter_per_scan is None else c.clutter_per_scan
        radars.append(replace(r, identity=True, clutter_per_scan=clutter, **draw_bias(rng)))  # type: ignore[arg-type]
    adsb = AdsbSpec(ADSB_ID, stride=c.stride, no_height=c.no_height, position_sigma_m=c.position_sigma_m)
    sc = replace(base, radars=tuple(radars), targets=c.targets, duration_s=job.duration_s, adsb=(adsb,))
    return sc, int(rng.integers(2**31))


def stream(sc: Scenario, seed: int) -> Iterator[tuple[float, str, bytes, dict[str, Any]]]:
    """``(data time, key, payload, body)`` of each message: key and payload are those of
    :func:`~topofusion_lab.scenarios.simulator.wire_messages` (the same generator), the body
    and time are kept for scoring."""
    keys = Keys(PREFIX)
    for m in generate(sc, seed):
        yield m.time_s, keys.input(m.kind, m.radar_id), json.dumps(m.body).encode(), m.body


# -- scoring ------------------------------------------------------------------------------


@dataclass
class Heard:
    """What the ADS-B receiver said of one address (reports with a height only for ``first``)."""

    first_s: float
    last_s: float
    lat_deg: float
    lon_deg: float


def hear(heard: dict[str, Heard], body: Mapping[str, Any]) -> None:
    """Absorb one ``AdsbBatch`` body.  An address counts from its first report with a height
    (the service leaves an aircraft out until it has one)."""
    r = body["reports"]
    alts = r.get("altitude_m") or [None] * len(r["time_s"])
    for t, a, lat, lon, h in zip(
        r["time_s"], r["icao24"], r["latitude_deg"], r["longitude_deg"], alts, strict=True
    ):
        got = heard.get(a)
        if got is None:
            if h is None:
                continue
            heard[a] = Heard(t, t, lat, lon)
        elif t >= got.last_s:
            got.last_s, got.lat_deg, got.lon_deg = t, lat, lon


def _distance_km(a: Heard, b: Heard) -> float:
    """Great-circle distance of two last reports (km, spherical Earth)."""
    la, lb = math.radians(a.lat_deg), math.radians(b.lat_deg)
    dlon = math.radians(b.lon_deg - a.lon_deg)
    c = math.sin(la) * math.sin(lb) + math.cos(la) * math.cos(lb) * math.cos(dlon)
    return 6371.0 * math.acos(min(1.0, max(-1.0, c)))


@dataclass
class Counts:
    """One radar's radar-ADS-B scoring at one time."""

    confirmed: int = 0
    correct: int = 0
    common: int = 0
    found: int = 0
    settled_common: int = 0
    settled_found: int = 0
    settled_confirmed: int = 0
    settled_false: int = 0
    #: Settled common aircraft without a correct pair whose tracks and address are in no
    #: confirmed pair at all (the others' track or address is in a false pair).
    settled_unpaired: int = 0

    @property
    def false(self) -> int:
        return self.confirmed - self.correct


@dataclass(frozen=True)
class WrongPair:
    radar_id: str
    track_a: str
    track_b: str
    truth_id: str | None
    #: ``clutter`` (track of no aircraft), ``unequipped`` (its aircraft never heard),
    #: ``other`` (its aircraft heard, paired with another's address).
    cause: str
    #: ``other``: distance between the two aircraft's last ADS-B reports (km).
    distance_km: float = math.nan
    #: Its aircraft holds another confirmed track of the radar (a duplicate track).
    duplicate: bool = False
    settled: bool = False
    #: The radar track's latest Mode S code is ``track_b``: the track now holds the plots of
    #: the address's aircraft (its truth label is the most common aircraft of all its plots).
    code_matches: bool = False
    #: The aircraft of ``track_b`` holds a confirmed track of the radar.
    address_tracked: bool = False
    #: The radar track is no longer in the track table (deleted after the pair set's update).
    gone: bool = False


@dataclass
class Scored:
    counts: Counts
    wrong: list[WrongPair]
    #: (age s, found) per common aircraft and (age s, correct) per confirmed pair.
    aircraft_ages: list[tuple[float, bool]]
    pair_ages: list[tuple[float, bool]]


def score(
    radar_id: str,
    table: TrackTable,
    pairs: Iterable[tuple[str, str]],
    heard: Mapping[str, Heard],
    confirmed_since: Mapping[str, float],
    time_s: float,
    memory: Mapping[str, tuple[Any, Any]] | None = None,
    settle_s: float = SETTLE_S,
    recent_s: float = RECENT_S,
) -> Scored:
    """Score one radar's confirmed radar-ADS-B pairs ``(radar track, address)`` at ``time_s``.

    ``heard``: the receiver's addresses (first report with a height, last report);
    ``confirmed_since``: data time each radar track was first seen confirmed (a confirmed
    track missing from it counts as confirmed at ``time_s``); ``memory``: the last seen
    ``(truth_id, mode_s)`` of tracks no longer in ``table``.  A pair set is updated once per
    scan, the track table at every batch: a pair may name a track deleted since (its
    aircraft left), scored by what the track was.
    """
    memory = memory or {}
    pairs = list(pairs)
    paired = {ta for ta, _ in pairs} | {tb for _, tb in pairs}
    conf = table.confirmed.astype(bool)
    ids = table.track_id[conf].tolist()
    truths = table.truth_id[conf].tolist()
    truth_of = {k: v[0] for k, v in memory.items()}
    truth_of.update(zip(table.track_id.tolist(), table.truth_id.tolist(), strict=True))
    code_of = {k: v[1] for k, v in memory.items()}
    code_of.update(zip(table.track_id.tolist(), table.mode_s.tolist(), strict=True))
    live = set(table.track_id.tolist())
    tracks_of: dict[str, list[str]] = {}
    for tid, t in zip(ids, truths, strict=True):
        if t is not None:
            tracks_of.setdefault(str(t), []).append(tid)

    def since(tid: str) -> float:
        return confirmed_since.get(tid, time_s)

    c = Counts()
    wrong: list[WrongPair] = []
    pair_ages: list[tuple[float, bool]] = []
    right_aircraft: set[str] = set()
    tracked_addresses = {identity_of(t)[1] for t in tracks_of}
    for ta, tb in pairs:
        truth = truth_of.get(ta)
        ok = truth is not None and identity_of(str(truth))[1] == tb
        c.confirmed += 1
        c.correct += ok
        h = heard.get(tb)
        age = time_s - max(since(ta), h.first_s if h is not None else time_s)
        pair_ages.append((age, ok))
        settled = age >= settle_s
        c.settled_confirmed += settled
        if ok:
            right_aircraft.add(str(truth))
            continue
        c.settled_false += settled
        cause, dist, dup = "clutter", math.nan, False
        if truth is not None:
            own = heard.get(identity_of(str(truth))[1])
            dup = len(tracks_of.get(str(truth), [])) > 1
            cause = "unequipped" if own is None else "other"
            if own is not None and h is not None:
                dist = _distance_km(own, h)
        label = None if truth is None else str(truth)
        matches, tracked = code_of.get(ta) == tb, tb in tracked_addresses
        wrong.append(
            WrongPair(radar_id, ta, tb, label, cause, dist, dup, settled, matches, tracked, ta not in live)
        )
    aircraft_ages: list[tuple[float, bool]] = []
    for truth, tids in tracks_of.items():
        h = heard.get(identity_of(truth)[1])
        if h is None or h.last_s < time_s - recent_s:
            continue
        found = truth in right_aircraft
        age = time_s - max(min(since(t) for t in tids), h.first_s)
        c.common += 1
        c.found += found
        if age >= settle_s:
            c.settled_common += 1
            c.settled_found += found
            c.settled_unpaired += not found and paired.isdisjoint([*tids, identity_of(truth)[1]])
        aircraft_ages.append((age, found))
    return Scored(c, wrong, aircraft_ages, pair_ages)


def adsb_pairs(pair_sets: Iterable[Mapping[str, Any]], radar_id: str, adsb_id: str) -> list[tuple[str, str]]:
    """``(radar track, address)`` of the confirmed pairs of ``radar_id`` with ``adsb_id``."""
    out: list[tuple[str, str]] = []
    for ps in pair_sets:
        if {ps["radar_a"], ps["radar_b"]} != {radar_id, adsb_id}:
            continue
        radar_first = ps["radar_a"] == radar_id
        for p in ps["pairs"]:
            if p["status"] == "confirmed":
                out.append((p["track_a"], p["track_b"]) if radar_first else (p["track_b"], p["track_a"]))
    return out


# -- one run ------------------------------------------------------------------------------


@dataclass
class RadarResult:
    radar_id: str
    counts: Counts
    truth_bias: dict[str, float]
    #: The service's estimate (None: no bias estimate for the radar).
    estimate: dict[str, float] | None
    #: The same scoring every :data:`CHECK_S` of data time through the run.
    checkpoints: list[Counts] = field(default_factory=list)
    #: Per ``cfar`` update of the radar with the ADS-B source: the pairs it decided and the
    #: confirmed pairs of the book before it.
    updates: list[tuple[int, int]] = field(default_factory=list)

    def error(self, name: str) -> float:
        return math.nan if self.estimate is None else abs(self.estimate[name] - self.truth_bias[name])

    def relative(self, name: str) -> float:
        return self.error(name) / abs(self.truth_bias[name])


@dataclass
class RunResult:
    index: int
    seed: tuple[int, ...]
    radars: list[RadarResult]
    wrong: list[WrongPair]
    #: Radar-ADS-B confirmed pairs with a Mode S address on both tracks, and those that agree.
    identity_pairs: int
    identity_equal: int
    #: Radar-radar confirmed pairs and the false ones among them (networks).
    radar_pairs: int
    radar_pairs_false: int
    aircraft_ages: list[tuple[float, bool]] = field(default_factory=list)
    pair_ages: list[tuple[float, bool]] = field(default_factory=list)
    seconds: float = 0.0
    errors: int = 0


def run_one(job: Job) -> RunResult:
    """Stream one job's scenario through a default engine and score it."""
    t_start = time.perf_counter()
    sc, sim_seed = scenario_of(job)
    engine = Engine()
    heard: dict[str, Heard] = {}
    since: dict[str, dict[str, float]] = {r.radar_id: {} for r in sc.radars}
    memory: dict[str, dict[str, tuple[Any, Any]]] = {r.radar_id: {} for r in sc.radars}
    checkpoints: dict[str, list[Counts]] = {r.radar_id: [] for r in sc.radars}
    next_poll, next_check = POLL_S, CHECK_S
    aircraft_ages: list[tuple[float, bool]] = []
    pair_ages: list[tuple[float, bool]] = []
    errors = 0
    updates: dict[str, list[tuple[int, int]]] = {r.radar_id: [] for r in sc.radars}
    seen_update: dict[str, tuple[float, int]] = {}

    def watch_updates() -> None:
        """Each radar-ADS-B correlator's updates: decided pairs and the confirmed pairs before."""
        for c in engine.pair_correlators():
            if c.site_b is not None:
                continue
            rid = c.site_a.site_id
            before = seen_update.get(rid, (math.nan, 0))
            if c.time_s != before[0] and np.isfinite(c.time_s):
                updates[rid].append((len(c.last_decisions), before[1]))
            seen_update[rid] = (c.time_s, int(np.count_nonzero(c.book.confirmed)))

    def poll(t: float) -> None:
        """When each track was first seen confirmed, and what each track is."""
        snap = engine.snapshot()
        for rid, got in since.items():
            if rid in snap.tracks:
                table = snap.tracks[rid][1]
                for tid in table.track_id[table.confirmed].tolist():
                    got.setdefault(tid, t)
                ids, truths, codes = table.track_id.tolist(), table.truth_id.tolist(), table.mode_s.tolist()
                memory[rid].update(zip(ids, zip(truths, codes, strict=True), strict=True))

    t0 = sc.start_time_s  # every time below is absolute data time, as the reports' own
    for t, key, payload, body in stream(sc, sim_seed):
        out = engine.ingest(key, payload, receive_time_s=0.0)
        errors += sum(o.key.endswith("/errors") for o in out)
        watch_updates()
        if key.startswith(f"{PREFIX}/adsb/"):
            hear(heard, body)
        if t - t0 >= next_poll:
            poll(t)
            next_poll += POLL_S
        if t - t0 >= next_check:
            snap = engine.snapshot()
            sets = snap.pair_sets(status="confirmed")
            for rid in since:
                if rid in snap.tracks:
                    pairs = adsb_pairs(sets, rid, ADSB_ID)
                    s = score(rid, snap.tracks[rid][1], pairs, heard, since[rid], t, memory[rid])
                    aircraft_ages += s.aircraft_ages
                    pair_ages += s.pair_ages
                    checkpoints[rid].append(s.counts)
            next_check += CHECK_S
    errors += sum(o.key.endswith("/errors") for o in engine.flush())
    watch_updates()
    t_end = t0 + job.duration_s
    poll(t_end)
    snap = engine.snapshot()
    sets = snap.pair_sets(status="confirmed")
    estimates = {b["radar_id"]: b for b in snap.biases()}
    radars: list[RadarResult] = []
    wrong: list[WrongPair] = []
    for r in sc.radars:
        table = snap.tracks[r.radar_id][1] if r.radar_id in snap.tracks else TrackTable.empty()
        pairs = adsb_pairs(sets, r.radar_id, ADSB_ID)
        s = score(r.radar_id, table, pairs, heard, since[r.radar_id], t_end, memory[r.radar_id])
        wrong += s.wrong
        truth_bias = {k: getattr(r, k) for k in ("range_bias_m", "azimuth_bias_deg", "elevation_bias_deg")}
        est = estimates.get(r.radar_id)
        radars.append(
            RadarResult(
                r.radar_id,
                s.counts,
                truth_bias,
                {k: float(est[k]) for k in truth_bias} if est else None,
                checkpoints[r.radar_id],
                updates[r.radar_id],
            )
        )
    ident = snap.status()["identity"]["by_pair"]
    id_rows = [row for row in ident if ADSB_ID in (row["radar_a"], row["radar_b"])]
    rr_pairs = rr_false = 0
    radar_ids = {r.radar_id for r in sc.radars}
    for ps in sets:
        a, b = ps["radar_a"], ps["radar_b"]
        if a in radar_ids and b in radar_ids:
            ta, tb = snap.tracks[a][1], snap.tracks[b][1]
            truth_a = dict(zip(ta.track_id.tolist(), ta.truth_id.tolist(), strict=True))
            truth_b = dict(zip(tb.track_id.tolist(), tb.truth_id.tolist(), strict=True))
            for p in ps["pairs"]:
                x, y = truth_a.get(p["track_a"]), truth_b.get(p["track_b"])
                rr_pairs += 1
                rr_false += x is None or x != y
    return RunResult(
        job.index,
        job.seed,
        radars,
        wrong,
        sum(row["pairs_with_mode_s"] for row in id_rows),
        sum(row["mode_s_equal"] for row in id_rows),
        rr_pairs,
        rr_false,
        aircraft_ages,
        pair_ages,
        time.perf_counter() - t_start,
        errors,
    )


def make_jobs(
    runs: int, seed: int, conditions: Sequence[Condition] = CONDITIONS, duration_s: float = DURATION_S
) -> list[Job]:
    return [Job(i, c, (seed, i, r), duration_s) for r in range(runs) for i, c in enumerate(conditions)]


def _run_all(jobs: list[Job], workers: int, progress: Callable[[str], None]) -> list[RunResult]:
    return sorted(run_jobs(run_one, jobs, workers, progress, "adsb"), key=lambda r: (r.index, r.seed))


# -- summary ------------------------------------------------------------------------------


@dataclass
class RadarRun:
    """One radar of one run: the per-run figures the tables average."""

    complete: float
    complete_settled: float
    precision: float
    false: float
    settled_false: float
    #: Pooled over the run's checkpoints: settled completeness and false rate, and the share
    #: of checkpoints whose settled completeness is below the goal.
    complete_in_run: float
    false_in_run: float
    dips: float
    #: Share of the ``cfar`` updates that decided fewer than half the book's confirmed pairs.
    short_updates: float
    #: Mean over the ``cfar`` updates of the pairs decided / the book's confirmed pairs (<= 1).
    decided_share: float
    confirmed: int
    common: int
    range_rel: float
    az_rel: float
    range_err_m: float
    az_err_deg: float
    el_err_deg: float


def radar_runs(results: Iterable[RunResult]) -> list[RadarRun]:
    out = []
    for res in results:
        for r in res.radars:
            c = r.counts
            cps = [k for k in r.checkpoints if k.settled_common]
            out.append(
                RadarRun(
                    ratio(c.found, c.common),
                    ratio(c.settled_found, c.settled_common),
                    ratio(c.correct, c.confirmed),
                    ratio(c.false, c.confirmed),
                    ratio(c.settled_false, c.settled_confirmed),
                    ratio(sum(k.settled_found for k in cps), sum(k.settled_common for k in cps)),
                    ratio(sum(k.false for k in r.checkpoints), sum(k.confirmed for k in r.checkpoints)),
                    ratio(sum(k.settled_found < GOAL_COMPLETE * k.settled_common for k in cps), len(cps)),
                    ratio(
                        sum(d < SHORT_UPDATE * b for d, b in r.updates if b), sum(b > 0 for _, b in r.updates)
                    ),
                    _mean([min(1.0, d / b) for d, b in r.updates if b]),
                    c.confirmed,
                    c.common,
                    r.relative("range_bias_m"),
                    r.relative("azimuth_bias_deg"),
                    r.error("range_bias_m"),
                    r.error("azimuth_bias_deg"),
                    r.error("elevation_bias_deg"),
                )
            )
    return out


def _mean(xs: Sequence[float]) -> float:
    v = [x for x in xs if np.isfinite(x)]
    return float(np.mean(v)) if v else math.nan


def _worst(xs: Sequence[float], low: bool) -> float:
    """The worst run: the lowest (``low``) or the highest value; a missing value (NaN, e.g.
    no bias estimate) is the worst of all."""
    if any(not np.isfinite(x) for x in xs):
        return math.nan
    return float(min(xs) if low else max(xs)) if xs else math.nan


def _pct(x: float, digits: int = 1) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.{digits}f}"


def _num(x: float, fmt: str) -> str:
    return "-" if not np.isfinite(x) else format(x, fmt)


def _mw(xs: Sequence[float], low: bool, fmt: Callable[[float], str]) -> str:
    """``mean / worst``."""
    return f"{fmt(_mean(xs))} / {fmt(_worst(xs, low))}"


@dataclass
class Verdict:
    """Which goals a condition meets (on the mean over runs and in every run)."""

    complete_mean: bool
    complete_all: bool
    precision_mean: bool
    precision_all: bool
    false_mean: bool
    false_all: bool
    bias_runs: int
    bias_total: int


def verdict(rr: Sequence[RadarRun]) -> Verdict:
    cs = [r.complete_settled for r in rr]
    fs = [r.false for r in rr]
    ps = [r.precision for r in rr]
    within = [
        bool(np.isfinite(r.range_rel) and np.isfinite(r.az_rel) and max(r.range_rel, r.az_rel) <= GOAL_BIAS)
        for r in rr
    ]
    mean_c, worst_c = _mean(cs), _worst(cs, True)
    mean_f, worst_f = _mean(fs), _worst(fs, False)
    mean_p, worst_p = _mean(ps), _worst(ps, True)
    return Verdict(
        bool(mean_c >= GOAL_COMPLETE),
        bool(worst_c >= GOAL_COMPLETE),
        bool(mean_p >= 1 - GOAL_FALSE),
        bool(worst_p >= 1 - GOAL_FALSE),
        bool(mean_f <= GOAL_FALSE),
        bool(worst_f <= GOAL_FALSE),
        sum(within),
        len(within),
    )


def _age_rates(ages: Sequence[tuple[float, bool]], edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Share of ``True`` per age bin, and the count."""
    if not ages:
        return np.full(len(edges) - 1, np.nan), np.zeros(len(edges) - 1)
    a = np.array([x for x, _ in ages])
    ok = np.array([y for _, y in ages], dtype=float)
    k = np.clip(np.digitize(a, edges) - 1, 0, len(edges) - 2)
    n = np.bincount(k, minlength=len(edges) - 1).astype(float)
    s = np.bincount(k, weights=ok, minlength=len(edges) - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return s / n, n


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_vs_age(
    path: pathlib.Path,
    conditions: Sequence[Condition],
    by_cond: Mapping[int, list[RunResult]],
    max_age_s: float,
) -> None:
    plt = _plt()
    edges = np.arange(0.0, max_age_s + AGE_BIN_S, AGE_BIN_S)
    mids = edges[:-1] + AGE_BIN_S / 2
    fig, axes = plt.subplots(1, 2, figsize=(11.0, 4.6))
    for i, cond in enumerate(conditions):
        res = by_cond.get(i, [])
        ac = [x for r in res for x in r.aircraft_ages]
        pc = [x for r in res for x in r.pair_ages]
        comp, n = _age_rates(ac, edges)
        prec, m = _age_rates(pc, edges)
        style = {"color": f"C{i % 10}", "ls": "-" if cond.group == LONE else "--", "marker": "o", "ms": 3}
        label = cond.label if len(cond.label) < 40 else cond.label[:38] + "..."
        axes[0].plot(mids[n >= 5], 100 * comp[n >= 5], label=label, **style)
        axes[1].plot(mids[m >= 5], 100 * (1 - prec[m >= 5]), label=label, **style)
    axes[0].axhline(100 * GOAL_COMPLETE, color="k", lw=0.8, ls=":")
    axes[1].axhline(100 * GOAL_FALSE, color="k", lw=0.8, ls=":")
    for ax, yl in zip(
        axes,
        ("common aircraft with a correct pair (%)", "false confirmed pairs / confirmed (%)"),
        strict=True,
    ):
        ax.axvline(SETTLE_S, color="k", lw=0.8, ls=":")
        ax.set_xlabel("age: time since radar track confirmed and address heard (s)")
        ax.set_ylabel(yl)
        ax.grid(True, alpha=0.3)
    axes[0].set_ylim(bottom=max(0.0, axes[0].get_ylim()[0]))
    axes[0].legend(fontsize=6.5, loc="lower right")
    fig.suptitle(f"Radar-ADS-B pairs against age, every {CHECK_S:.0f} s of every run", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_bias(
    path: pathlib.Path, conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]
) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 4.2))
    for group, marker, color in ((LONE, "o", "C0"), (NETWORK, "s", "C3")):
        rows = [
            r
            for i, cond in enumerate(conditions)
            if cond.group == group
            for res in by_cond.get(i, [])
            for r in res.radars
        ]
        for ax, name in zip(axes, ("range_bias_m", "azimuth_bias_deg"), strict=True):
            x = [abs(r.truth_bias[name]) for r in rows]
            y = [100 * r.relative(name) if r.estimate is not None else np.nan for r in rows]
            ax.scatter(x, y, s=12, marker=marker, color=color, alpha=0.7, label=group)
    for ax, name, unit in zip(axes, ("range", "azimuth"), ("m", "deg"), strict=True):
        ax.axhline(100 * GOAL_BIAS, color="k", lw=0.8, ls=":")
        ax.set_xlabel(f"|true {name} bias| ({unit})")
        ax.set_ylabel(f"|estimate - truth| / |truth| (%), {name}")
        ax.set_yscale("log")
        ax.grid(True, alpha=0.3, which="both")
    axes[0].legend(fontsize=8)
    fig.suptitle("Absolute bias estimates against ADS-B (final /biases of each run, each radar)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _yes(ok: bool) -> str:
    return "yes" if ok else "**no**"


def _group_tables(
    group: str, conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]
) -> tuple[list[str], list[tuple[Condition, Verdict]]]:
    """The group's three tables (final snapshot, through the run, biases) and verdicts."""
    pct = _pct

    def m(x: float) -> str:
        return _num(x, ".1f")

    def d(x: float) -> str:
        return _num(x, ".3f")

    final = [
        "| condition | runs x radars | confirmed pairs / radar | common aircraft / radar | completeness, "
        f"settled >= {SETTLE_S:.0f} s (%) | completeness, all (%) | precision (%) | false (%) | "
        "identity agreement, radar-ADS-B (%) | s / run |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    during = [
        f"| condition | completeness, settled (%) | checkpoints with settled completeness < "
        f"{100 * GOAL_COMPLETE:.0f} % (%) | false (%) | `cfar` pairs decided / confirmed, per update (%) | "
        "short `cfar` updates (%) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    bias = [
        "| condition | range error (%) | azimuth error (%) | range error (m) | azimuth error (deg) | "
        f"elevation error (deg) | radars within {100 * GOAL_BIAS:.0f} % (range and azimuth) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    verdicts = []
    for i, cond in enumerate(conditions):
        if cond.group != group or i not in by_cond:
            continue
        res = by_cond[i]
        rr = radar_runs(res)
        v = verdict(rr)
        verdicts.append((cond, v))
        ident = [ratio(r.identity_equal, r.identity_pairs) for r in res]
        final.append(
            f"| {cond.label} | {len(res)} x {cond.radars} | {_mean([r.confirmed for r in rr]):.0f} | "
            f"{_mean([r.common for r in rr]):.0f} | "
            f"{_mw([r.complete_settled for r in rr], True, pct)} | "
            f"{_mw([r.complete for r in rr], True, pct)} | "
            f"{_mw([r.precision for r in rr], True, pct)} | "
            f"{_mw([r.false for r in rr], False, pct)} | "
            f"{_mw(ident, True, pct)} | {_mean([r.seconds for r in res]):.1f} |"
        )
        during.append(
            f"| {cond.label} | {_mw([r.complete_in_run for r in rr], True, pct)} | "
            f"{_mw([r.dips for r in rr], False, pct)} | "
            f"{_mw([r.false_in_run for r in rr], False, pct)} | "
            f"{_mw([r.decided_share for r in rr], True, pct)} | "
            f"{_mw([r.short_updates for r in rr], False, pct)} |"
        )
        bias.append(
            f"| {cond.label} | {_mw([r.range_rel for r in rr], False, pct)} | "
            f"{_mw([r.az_rel for r in rr], False, pct)} | "
            f"{_mw([r.range_err_m for r in rr], False, m)} | "
            f"{_mw([r.az_err_deg for r in rr], False, d)} | "
            f"{_mw([r.el_err_deg for r in rr], False, d)} | {v.bias_runs} / {v.bias_total} |"
        )
    out = [
        "Final snapshot:",
        "",
        *final,
        "",
        f"Through the run (the same scoring every {CHECK_S:.0f} s of data time, pooled per run; "
        f"*short* `cfar` updates decided fewer than {100 * SHORT_UPDATE:.0f} % of the confirmed pairs):",
        "",
        *during,
        "",
        "Absolute bias estimates (final `/biases`):",
        "",
        *bias,
    ]
    return out, verdicts


def _wrong_summary(conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]) -> list[str]:
    """Per condition: the false pairs of the final snapshots by cause."""
    lines = []
    for i, cond in enumerate(conditions):
        wrong = [w for r in by_cond.get(i, []) for w in r.wrong]
        if not wrong:
            continue
        parts = []
        for cause, what in (
            ("clutter", "a clutter track"),
            ("unequipped", "the track of an unequipped aircraft"),
            ("other", "the track of another equipped aircraft"),
        ):
            ws = [w for w in wrong if w.cause == cause]
            if not ws:
                continue
            notes = []
            dist = [w.distance_km for w in ws if np.isfinite(w.distance_km)]
            if dist:
                notes.append(f"the two aircraft {min(dist):.1f}-{max(dist):.1f} km apart")
            if dup := sum(w.duplicate for w in ws):
                notes.append(f"{dup} on a duplicate track")
            parts.append(f"{len(ws)} with {what}" + (f" ({', '.join(notes)})" if notes else ""))
        settled = sum(w.settled for w in wrong)
        moved = sum(w.code_matches for w in wrong)
        untracked = sum(not w.address_tracked for w in wrong)
        gone = sum(w.gone for w in wrong)
        lines.append(
            f"* {cond.label}: {len(wrong)} false pair{'s' if len(wrong) > 1 else ''} ({settled} settled): "
            + "; ".join(parts)
            + f".  The radar track's latest Mode S code is the paired address in {moved} (the track "
            "now follows that aircraft); the address's own aircraft has no confirmed track of the "
            f"radar in {untracked}; the radar track was deleted after the pair set's update in {gone}."
        )
    return lines


def run(
    out_dir: pathlib.Path,
    runs: int | None = None,
    seed: int = 0,
    progress: Callable[[str], None] = print,
    *,
    conditions: Sequence[Condition] = CONDITIONS,
    duration_s: float = DURATION_S,
    workers: int | None = None,
) -> str:
    """Run the study, write ``adsb_*.png`` into ``out_dir``, return the markdown section.

    ``runs``: runs per condition (None: :data:`DEFAULT_RUNS`).  ``conditions``, ``duration_s``
    and ``workers`` (processes; None: up to 2) make small runs for tests.
    """
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n = DEFAULT_RUNS if runs is None else max(int(runs), 1)
    jobs = make_jobs(n, seed, conditions, duration_s)
    workers = min(2, os.cpu_count() or 1) if workers is None else workers
    progress(
        f"adsb: {len(jobs)} runs ({n} per condition, {duration_s:g} s of data each), {workers} processes"
    )
    t0 = time.perf_counter()
    results = _run_all(jobs, workers, progress)
    took = time.perf_counter() - t0
    by_cond: dict[int, list[RunResult]] = {}
    for r in results:
        by_cond.setdefault(r.index, []).append(r)
    plot_vs_age(out_dir / "adsb_vs_age.png", conditions, by_cond, duration_s)
    plot_bias(out_dir / "adsb_bias.png", conditions, by_cond)

    md = [
        "## ADS-B as a bias-free reference: radar-ADS-B pairs and absolute biases",
        "",
        f"{len(jobs)} runs: {len(conditions)} conditions x {n} seeds, each {duration_s:g} s of data streamed "
        "through the service's `Engine` (default configuration, in process, the simulator's wire "
        "messages: plot batches and `AdsbBatch`).  The service correlates each radar with the ADS-B "
        "source by `cfar` and registers it to it (`/biases`); nothing is tuned for this study.  Every "
        "radar of every run has its own biases: range 100-600 m and azimuth 0.1-0.5 deg with random "
        "signs, elevation uniform in +-0.15 deg.  Radars are the catalog's (200 m / 0.2 deg noise, "
        "4-5 s scans, Pd 0.95), Mode S (their plots carry the aircraft's codes: the identity figure; "
        "the identity veto is off, so the codes play no part in the association).  The ADS-B receiver "
        "hears every `stride`-th aircraft of the simulation, reports each every 1 s (height error "
        "15 m), one batch per 2 s.",
        "",
        "*Lone radar*: the two-radar scenario's radar A alone (the area 240 km square, the radar "
        "100 km west of its centre); one factor at a time from the baseline (120 aircraft, 1 in 2 "
        "equipped, no clutter, every report with a height, ADS-B position sigma 10 m), then the hard "
        "settings together.  *Network*: the two-radar scenario's A and B, or the three-radar "
        "scenario's A, B, C; 120 aircraft, 1 in 2 equipped; the catalog's clutter.",
        "",
        "Scoring by the simulator's truth, per radar, on the final snapshot (after `Engine.flush`): a "
        "confirmed radar-ADS-B pair is *correct* when its radar track's aircraft (the track's "
        "`truth_id`: the most common aircraft of its plots) has the address `track_b`, otherwise "
        "*false*.  A pair set is updated once per scan and the track table at every batch, so a pair "
        "may name a radar track deleted since (its aircraft left the area): such a track is scored "
        "by what it was when last seen.  *Common* aircraft = equipped aircraft heard in the last "
        f"{RECENT_S:.0f} s that hold a confirmed track of the radar; **completeness** = common "
        "aircraft with a correct confirmed pair / common aircraft; *settled*: the aircraft's radar "
        f"track confirmed and its address heard (with a height) at least {SETTLE_S:.0f} s before "
        "(the age figure shows why: pairs confirm within about 30 s).  **Precision** = correct / "
        "confirmed pairs, **false** = false / confirmed pairs (every confirmed pair, settled or "
        "not).  Bias errors are `|estimate - truth|` of the final `/biases` per radar, relative to "
        "`|truth|` for range and azimuth.  *Identity agreement* is `/status` `identity` on the "
        "radar-ADS-B pairs (pairs whose radar track carries a Mode S address: the share whose "
        "address equals `track_b`; no truth needed).  Cells are **mean / worst** over runs (and "
        "radars, for networks); a missing bias estimate is shown as `-` and counts as outside 10 %.",
        "",
        "The issue's goal, *radar-ADS-B pairs at least 95 % correct and at most 2 % false; one radar "
        "alone gets its range and azimuth bias within 10 %*, is read two ways: (1) completeness of "
        "settled aircraft >= 95 % and false <= 2 %; (2) literally, precision >= 95 % and false <= 2 % "
        "(false <= 2 % already implies precision >= 98 %).  The bias goal is read per run: both "
        "relative errors <= 10 %.",
    ]
    verdict_lines: list[str] = []
    for group in (LONE, NETWORK):
        tables, verdicts = _group_tables(group, conditions, by_cond)
        if not verdicts:
            continue
        md += ["", f"### {group}", "", *tables]
        for cond, v in verdicts:
            verdict_lines.append(
                f"| {cond.label} | {_yes(v.complete_mean)} / {_yes(v.complete_all)} | "
                f"{_yes(v.false_mean)} / {_yes(v.false_all)} | {_yes(v.precision_mean)} / "
                f"{_yes(v.precision_all)} | {_yes(v.bias_runs == v.bias_total)} "
                f"({v.bias_runs} / {v.bias_total}) |"
            )
    all_v = [verdict(radar_runs(by_cond[i])) for i in sorted(by_cond)]
    lone_v = [verdict(radar_runs(by_cond[i])) for i in sorted(by_cond) if conditions[i].group == LONE]
    md += [
        "",
        "### Goals",
        "",
        "Per condition, on the mean over runs / in every run:",
        "",
        "| condition | completeness settled >= 95 % | false <= 2 % | precision >= 98 % | "
        "range and azimuth bias within 10 % (runs) |",
        "|---|---|---|---|---|",
        *verdict_lines,
        "",
        f"**Pairs, reading (1)**: met on the mean in {sum(v.complete_mean and v.false_mean for v in all_v)} "
        f"of {len(all_v)} conditions, in every run in "
        f"{sum(v.complete_all and v.false_all for v in all_v)}.  **Pairs, reading (2)**: met on the mean "
        f"in {sum(v.precision_mean and v.false_mean for v in all_v)} of {len(all_v)}, in every run in "
        f"{sum(v.precision_all and v.false_all for v in all_v)}.  **Lone-radar biases within 10 %**: "
        f"{sum(v.bias_runs for v in lone_v)} of {sum(v.bias_total for v in lone_v)} runs "
        f"(all radars, networks included: {sum(v.bias_runs for v in all_v)} of "
        f"{sum(v.bias_total for v in all_v)}).",
    ]
    wrong = _wrong_summary(conditions, by_cond)
    md += ["", "False pairs on the final snapshots, by cause:", ""]
    md += wrong if wrong else ["* none."]
    all_wrong = [w for res in results for w in res.wrong]
    if any(w.code_matches and w.truth_id is not None for w in all_wrong):
        md += [
            "",
            "A false pair whose radar track's latest Mode S code is the paired address is a radar track "
            "that went over from one aircraft to another (crossing aircraft: a swap in the radar "
            "tracker): the pair follows the aircraft the track now holds, but the track's truth label, "
            "the most common aircraft of all its plots, is still the first one.",
        ]
    finals = [r.counts for res in results for r in res.radars]
    missed = sum(c.settled_common - c.settled_found for c in finals)
    unpaired = sum(c.settled_unpaired for c in finals)
    updates = [u for res in results for r in res.radars for u in r.updates if u[1]]
    short = sum(d < SHORT_UPDATE * b for d, b in updates)
    md += [
        "",
        f"Missed aircraft: of the {sum(c.settled_common for c in finals)} settled common aircraft on the "
        f"final snapshots, {missed} had no correct pair; {unpaired} of them had neither a track nor "
        f"the address in any confirmed pair (their pair had been dropped, or not yet confirmed).  "
        f"{short} of the {len(updates)} `cfar` updates ({_pct(ratio(short, len(updates)))} %) were "
        "short.",
    ]
    if short:
        md += [
            "",
            "Short updates leave confirmed pairs undecided for that update (`service/correlation/cfar.py`, "
            "`cfar_associate`: per-candidate chi-square gates, ambiguous candidates left undecided, "
            "confirmed pairs re-checked); a pair missed by `PairBookParams.drop_misses` updates in a row "
            "is dropped.  Look at the runs with the most of them first.",
        ]
    rr = [r for res in results for r in [res] if res.radar_pairs]
    if rr:
        md += [
            "",
            f"Radar-radar pairs (networks, `svd-topology`): {sum(r.radar_pairs for r in rr)} confirmed "
            f"on the final snapshots, {sum(r.radar_pairs_false for r in rr)} false.",
        ]
    errs = sum(r.errors for r in results)
    md += [
        "",
        f"Rejected or failed input messages (`fusion/errors`) over all runs: {errs}.  Study time "
        f"{took:.0f} s on {workers} processes.",
        "",
        "![Completeness and false rate against age](adsb_vs_age.png)",
        "",
        "![Bias errors against the true bias](adsb_bias.png)",
    ]
    return "\n".join(md)
