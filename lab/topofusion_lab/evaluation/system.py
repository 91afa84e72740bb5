"""System-track study: one fused, bias-compensated track per aircraft on a 12-radar network.

Entry point :func:`run` (``topofusion evaluate --only system``).  Every run streams a catalog
scenario of the simulator (:func:`~topofusion_lab.scenarios.simulator.generate`; the wire
bytes of ``wire_messages``) through the service's :class:`~service.engine.Engine` with its
default configuration, in process (no correlation process), and reads the system tracks
(contract §4.4) from ``engine.snapshot().system_tracks("confirmed")``.  Nothing of the service
is tuned here.

Conditions (:data:`CONDITIONS`): the ``national`` scenario (12 radars on a 250 km ring, 1 500
aircraft, biases 150-450 m / 0.1-0.4 deg of varied sign, clutter 20-50 plots per scan, Pd
0.90-0.95) and, for comparison, the ``three-radar`` scenario (3 radars, 80 aircraft).  The
radars' biases are the catalog's; each run has its own simulator seed (traffic, noise,
clutter).

Truth (evaluation only): the scenario gets an exact ADS-B source (no position or height error,
every aircraft, one report per second) whose messages are kept out of the engine: they give
each aircraft's true position every second (aircraft fly straight at constant speed, so the
position at any time is exact by linear interpolation, or extrapolation by less than a
second).  A radar track's aircraft is its ``truth_id`` (the most common aircraft of its plots).

Scoring (:func:`score`) at every :data:`CHECK_S` of data time and on the final snapshot (after
``Engine.flush``), on the **confirmed** system tracks, each member labelled by its radar
track's aircraft (``None``: a clutter track):

* *pure*: every member follows the same aircraft; *mixed*: members of two aircraft, or of an
  aircraft and clutter; *clutter*: every member a clutter track (a false radar track on its
  own, not a fusion error).  **Purity** = pure / (pure + mixed);
* **duplicates** = aircraft in two or more confirmed system tracks / aircraft in at least one;
* **coverage** = aircraft holding a confirmed radar track (any radar) that are in a confirmed
  pure system track / aircraft holding a confirmed radar track;
* position errors against the truth at the system tracks' ``time_s``: *fused* = the system
  track's position (pure tracks only); *raw* = each of its member radar tracks as the radar
  reports it (with the radar's bias), predicted to ``time_s``; the **ratio** is fused RMS /
  raw RMS (pooled over tracks and members);
* consistency of ``position_sigma_m`` (``sigma = sqrt(tr P / 3)``): ``e^2 / (3 sigma^2)`` per
  pure track, whose mean is 1 for an honest sigma (below 1: sigma larger than the error).
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from service.correlation.pairs import PairBookParams
from service.correlation.prediction import predict_states
from service.engine import Engine
from service.fusion.system_tracks import SystemTrackParams
from service.geo import geodetic_to_ecef
from service.tracking.base import TrackTable
from service.wire.keys import Keys
from topofusion_lab.evaluation.jobs import ratio, run_jobs
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import AdsbSpec, Scenario, generate, identity_of

PREFIX = "fusion"
TRUTH_ID = "truth"
#: Runs (seeds) per condition by default.
DEFAULT_RUNS = 4
#: Scoring interval through a run (data seconds).
CHECK_S = 60.0
#: Checkpoints from this data time on count as settled (the headline pools them).
WARMUP_S = 180.0
GOAL_PURITY = 0.99
GOAL_DUPLICATES = 0.02
GOAL_COVERAGE = 0.97
GOAL_RATIO = 0.35


@dataclass(frozen=True)
class Condition:
    label: str
    scenario: str
    duration_s: float


CONDITIONS: tuple[Condition, ...] = (
    Condition("national: 12 radars, 1 500 aircraft", "national", 480.0),
    Condition("three-radar: 3 radars, 80 aircraft", "three-radar", 480.0),
)


@dataclass(frozen=True)
class Job:
    index: int
    condition: Condition
    run: int
    seed: int
    duration_s: float


# -- truth --------------------------------------------------------------------------------


class Truth:
    """Each aircraft's true ECEF position every second, from the exact ADS-B source's batches
    (the last :attr:`keep_s` seconds)."""

    def __init__(self, keep_s: float = 120.0) -> None:
        self.keep_s = keep_s
        self._at: dict[int, tuple[dict[str, int], np.ndarray]] = {}

    def add(self, body: Mapping[str, Any]) -> None:
        r = body["reports"]
        t = np.asarray(r["time_s"], dtype=float)
        if not t.size:
            return
        ecef = np.atleast_2d(
            geodetic_to_ecef(
                np.asarray(r["latitude_deg"], dtype=float),
                np.asarray(r["longitude_deg"], dtype=float),
                np.asarray(r["altitude_m"], dtype=float),
            )
        ).reshape(-1, 3)
        sec = np.round(t).astype(np.int64)
        icao = list(r["icao24"])
        for s in np.unique(sec).tolist():
            rows = np.flatnonzero(sec == s)
            self._at[int(s)] = ({icao[i]: k for k, i in enumerate(rows.tolist())}, ecef[rows])
        newest = max(self._at)
        for s in [s for s in self._at if s < newest - self.keep_s]:
            del self._at[s]

    def position(self, address: str, time_s: float) -> np.ndarray | None:
        """The true position of ``address`` at ``time_s`` (None: not known around then)."""
        s0 = math.floor(time_s)
        pairs = ((s0, s0 + 1), (s0 - 1, s0), (s0, s0 - 1)) if s0 + 1 not in self._at else ((s0, s0 + 1),)
        for a, b in pairs:
            pa, pb = self._get(address, a), self._get(address, b)
            if pa is not None and pb is not None:
                return pa + (pb - pa) * (time_s - a) / (b - a)
        return None

    def _get(self, address: str, second: int) -> np.ndarray | None:
        got = self._at.get(second)
        if got is None:
            return None
        k = got[0].get(address)
        return None if k is None else got[1][k]


# -- scoring ------------------------------------------------------------------------------


Member = tuple[str, str]


@dataclass
class Scored:
    """The scoring of one snapshot's confirmed system tracks."""

    time_s: float
    #: The checkpoint's data time (s from the start; the system tracks' ``time_s`` is up to a
    #: second earlier); NaN for the final snapshot.
    checkpoint_s: float = math.nan
    #: Snapshots pooled in it (:func:`merge`).
    snapshots: int = 1
    tracks: int = 0
    pure: int = 0
    mixed: int = 0
    #: Mixed tracks whose other members all follow the track's aircraft now (:func:`_swapped`).
    mixed_swapped: int = 0
    clutter: int = 0
    #: Aircraft in at least one confirmed system track / in two or more.
    aircraft: int = 0
    duplicated: int = 0
    #: Duplicated aircraft with two tracks of one radar among their system tracks' members (a
    #: radar-tracker duplicate: two tracks of a source never share a system track), with one
    #: of their system tracks mixed, and the others (tracks of different radars not linked).
    dup_radar: int = 0
    dup_mixed: int = 0
    dup_unlinked: int = 0
    #: Duplicated aircraft whose *stray* tracks (their own members outside the system track
    #: holding most of them) are all younger than :data:`YOUNG_S`; each one's oldest stray
    #: track's age (s).
    dup_young: int = 0
    stray_age: list[float] = field(default_factory=list)
    #: Aircraft holding a confirmed radar track, and those of them in a confirmed pure system
    #: track; of the others: in a mixed system track only / in no system track at all.
    seen: int = 0
    covered: int = 0
    uncovered_mixed: int = 0
    #: ... in tentative system tracks only (of them: in two or more), in no system track at all.
    uncovered_held: int = 0
    uncovered_held_apart: int = 0
    uncovered_absent: int = 0
    #: Per pure system track with a known truth: fused error (m), its sigma (m), members, and
    #: the RMS raw error of its members (m).
    fused_err: list[float] = field(default_factory=list)
    sigma: list[float] = field(default_factory=list)
    members: list[int] = field(default_factory=list)
    track_raw: list[float] = field(default_factory=list)
    #: Per member of those tracks: raw error (m), and the member count of its system track.
    raw_err: list[float] = field(default_factory=list)
    raw_members: list[int] = field(default_factory=list)
    #: Members of every confirmed system track (pure or not).
    all_members: list[int] = field(default_factory=list)
    #: Per one-member pure track with a known truth (in ``fused_err`` order among them): its
    #: radar track's age (s), and whether its aircraft is in another system track too.
    single_age: list[float] = field(default_factory=list)
    single_dup: list[bool] = field(default_factory=list)
    #: A few failing cases for the report: (kind, description).
    cases: list[tuple[str, str]] = field(default_factory=list)

    @property
    def purity(self) -> float:
        return ratio(self.pure, self.pure + self.mixed)

    @property
    def duplicates(self) -> float:
        return ratio(self.duplicated, self.aircraft)

    @property
    def coverage(self) -> float:
        return ratio(self.covered, self.seen)

    @property
    def ratio(self) -> float:
        """RMS fused error / RMS raw error, the raw one over every member (the headline)."""
        return ratio(_rms(self.fused_err), _rms(self.raw_err))

    @property
    def ratio_per_track(self) -> float:
        """RMS fused error / RMS over tracks of each track's members' RMS raw error (each
        aircraft weighs the same on both sides)."""
        return ratio(_rms(self.fused_err), _rms(self.track_raw))

    def ratio_members(self, at_least: int) -> float:
        """The headline ratio over the system tracks of at least ``at_least`` members."""
        n, rn = np.asarray(self.members), np.asarray(self.raw_members)
        fe, re = np.asarray(self.fused_err), np.asarray(self.raw_err)
        return ratio(_rms(fe[n >= at_least]), _rms(re[rn >= at_least]))


#: A stray track younger than this (s) is a new radar track whose pairs have not confirmed yet.
YOUNG_S = 60.0


def score(
    body: Mapping[str, Any],
    label: Mapping[Member, str | None],
    seen: Iterable[str],
    raw_position: Mapping[Member, np.ndarray],
    true_position: Callable[[str, float], np.ndarray | None],
    age_s: Mapping[Member, float] | None = None,
    stale_s: Mapping[Member, float] | None = None,
    max_cases: int = 6,
    hold_young_s: float | None = None,
) -> Scored:
    """Score a ``SystemTrackBatch`` (its confirmed tracks; the tentative ones tell where an
    uncovered aircraft is).

    ``label``: each radar track's aircraft (None: clutter; a member missing from it counts as
    clutter); ``seen``: aircraft holding a confirmed radar track; ``raw_position``: each radar
    track's reported (biased) position predicted to the batch's ``time_s``; ``true_position``:
    an aircraft's true position at a time (None: unknown); ``age_s``: each radar track's age
    (s; a missing one counts as old); ``stale_s``: time since each radar track's last plot (s;
    for the examples only).  ``hold_young_s`` (a what-if, evaluation only): a one-member system
    track whose radar track is younger than this counts as tentative.
    """
    age_s = age_s or {}
    stale_s = stale_s or {}

    def describe(track: Mapping[str, Any]) -> str:
        return _describe(track, label, age_s, stale_s)

    when = float(body["time_s"])
    out = Scored(when)
    tracks_of: dict[str, list[int]] = {}
    pure_aircraft: set[str] = set()
    mixed_aircraft: set[str] = set()
    worst: list[tuple[float, int]] = []
    singles: list[tuple[str, Member]] = []
    tracks = [s for s in body["system_tracks"] if s["status"] == "confirmed"]
    if hold_young_s is not None:
        tracks = [
            s for s in tracks if len(s["members"]) > 1 or age_s.get(_members(s)[0], math.inf) >= hold_young_s
        ]
    counted = {id(s) for s in tracks}
    tentative = [s for s in body["system_tracks"] if id(s) not in counted]
    for k, s in enumerate(tracks):
        members = [(m["radar_id"], m["track_id"]) for m in s["members"]]
        names = {label.get(m) for m in members}
        out.tracks += 1
        out.all_members.append(len(members))
        for n in names - {None}:
            tracks_of.setdefault(str(n), []).append(k)
        if names == {None}:
            out.clutter += 1
            continue
        if len(names) > 1:
            out.mixed += 1
            mixed_aircraft.update(str(n) for n in names - {None})
            swapped, why = _swapped(members, label, raw_position, true_position, when)
            out.mixed_swapped += swapped
            kind = "mixed, a member now following the track's aircraft" if swapped else "mixed"
            if len([c for c in out.cases if c[0] == kind]) < max_cases:
                out.cases.append((kind, f"{describe(s)}; {why}"))
            continue
        out.pure += 1
        name = str(next(iter(names)))
        pure_aircraft.add(name)
        true = true_position(name, when)
        if true is None:
            continue
        err = float(np.linalg.norm(np.asarray(s["position_ecef_m"]) - true))
        out.fused_err.append(err)
        out.sigma.append(float(s["position_sigma_m"]))
        out.members.append(len(members))
        worst.append((err, k))
        if len(members) == 1:
            singles.append((name, members[0]))
        raw = [float(np.linalg.norm(raw_position[m] - true)) for m in members if m in raw_position]
        out.raw_err += raw
        out.raw_members += [len(members)] * len(raw)
        if raw:
            out.track_raw.append(_rms(raw))
    for err, k in sorted(worst, reverse=True)[:max_cases]:
        t = tracks[k]
        out.cases.append(
            (
                "largest fused error",
                f"{err:.0f} m, sigma {t['position_sigma_m']:.0f} m: {describe(t)}",
            )
        )
    out.aircraft = len(tracks_of)
    for name, m in singles:
        out.single_age.append(age_s.get(m, math.inf))
        out.single_dup.append(len(tracks_of[name]) > 1)
    for name, ks in tracks_of.items():
        if len(ks) < 2:
            continue
        out.duplicated += 1
        own = [[m for m in _members(tracks[k]) if label.get(m) == name] for k in ks]
        radars = Counter(r for part in own for r, _ in part)
        if any(n > 1 for n in radars.values()):
            out.dup_radar += 1
            kind = "duplicate: radar track duplicate"
        elif name in mixed_aircraft:
            out.dup_mixed += 1
            kind = "duplicate: one track mixed"
        else:
            out.dup_unlinked += 1
            kind = "duplicate: tracks of different radars not linked"
        main = max(range(len(ks)), key=lambda j: len(own[j]))
        stray = [age_s.get(m, math.inf) for j, part in enumerate(own) if j != main for m in part]
        out.stray_age.append(max(stray, default=math.inf))
        out.dup_young += bool(stray) and max(stray) < YOUNG_S
        if len([c for c in out.cases if c[0] == kind]) < max_cases:
            out.cases.append((kind, f"{name}: " + " | ".join(describe(tracks[k]) for k in ks)))
    seen = set(seen)
    out.seen = len(seen)
    out.covered = len(seen & pure_aircraft)
    missing = seen - pure_aircraft
    out.uncovered_mixed = len(missing & mixed_aircraft)
    held: dict[str, list[int]] = {}
    for k, s in enumerate(tentative):
        for n in {label.get(m) for m in _members(s)} - {None}:
            held.setdefault(str(n), []).append(k)
    for name in sorted(missing - mixed_aircraft):
        where = held.get(name, [])
        if not where:
            out.uncovered_absent += 1
            continue
        out.uncovered_held += 1
        out.uncovered_held_apart += len(where) > 1
        kind = "uncovered, in tentative system tracks only"
        if len([c for c in out.cases if c[0] == kind]) < max_cases:
            out.cases.append((kind, f"{name}: " + " | ".join(describe(tentative[k]) for k in where)))
    return out


def _members(track: Mapping[str, Any]) -> list[Member]:
    return [(m["radar_id"], m["track_id"]) for m in track["members"]]


def _describe(
    track: Mapping[str, Any],
    label: Mapping[Member, str | None],
    age_s: Mapping[Member, float],
    stale_s: Mapping[Member, float],
) -> str:
    parts = []
    for m in _members(track):
        notes = []
        if m in age_s:
            notes.append(f"{age_s[m]:.0f} s")
        if m in stale_s and stale_s[m] >= 10.0:
            notes.append(f"last plot {stale_s[m]:.0f} s before")
        parts.append(f"{m[0]}/{m[1]}={label.get(m)}" + (f" ({', '.join(notes)})" if notes else ""))
    return f"{track['system_track_id']} [{', '.join(parts)}]"


def _swapped(
    members: Sequence[Member],
    label: Mapping[Member, str | None],
    raw_position: Mapping[Member, np.ndarray],
    true_position: Callable[[str, float], np.ndarray | None],
    when: float,
) -> tuple[bool, str]:
    """Whether every member of a mixed track that is not of its most common aircraft is a
    track of another aircraft now nearer the most common one (a radar track that went over to
    it: its label is the aircraft of most of its plots, over its whole life), and why."""
    names = Counter(label.get(m) for m in members if label.get(m) is not None)
    if not names:
        return False, ""
    major = str(names.most_common(1)[0][0])
    at_major = true_position(major, when)
    ok, notes = at_major is not None, []
    for m in members:
        own = label.get(m)
        if own == major:
            continue
        at_own = None if own is None else true_position(str(own), when)
        if at_major is None or at_own is None or m not in raw_position:
            ok = False
            notes.append(f"{m[1]} ({own}) cannot be placed")
            continue
        d_major = float(np.linalg.norm(raw_position[m] - at_major))
        d_own = float(np.linalg.norm(raw_position[m] - at_own))
        ok &= d_major < d_own
        notes.append(f"{m[1]} is {d_major / 1000:.1f} km from {major}, {d_own / 1000:.1f} km from {own}")
    return ok, "; ".join(notes)


@dataclass
class Inputs:
    """What :func:`score` needs of the radars' track tables."""

    label: dict[Member, str | None]
    seen: set[str]
    raw: dict[Member, np.ndarray]
    age_s: dict[Member, float]
    #: Time since each track's last plot (s).
    stale_s: dict[Member, float]


def snapshot_inputs(
    tables: Mapping[str, TrackTable], time_s: float, accel_psd: float, scan_s: Mapping[str, float]
) -> Inputs:
    """From the radars' track tables: each track's aircraft, the aircraft with a confirmed
    track, each track's reported position predicted to ``time_s``, and its age, taken as its
    plots x the radar's scan period ``scan_s`` (a little less than its age: scans without a
    detection are not counted)."""
    out = Inputs({}, set(), {}, {}, {})
    for rid, table in tables.items():
        if not len(table):
            continue
        ids = table.track_id.tolist()
        truths = [None if t is None else str(t) for t in table.truth_id.tolist()]
        out.label.update(((rid, tid), t) for tid, t in zip(ids, truths, strict=True))
        out.seen.update(
            t for t, c in zip(truths, table.confirmed.tolist(), strict=True) if c and t is not None
        )
        pos, _, _ = predict_states(
            table.position_ecef_m, table.velocity_ecef_mps, table.covariance, time_s - table.time_s, accel_psd
        )
        out.raw.update(((rid, tid), p) for tid, p in zip(ids, pos, strict=True))
        out.stale_s.update(
            ((rid, tid), time_s - t) for tid, t in zip(ids, table.time_s.tolist(), strict=True)
        )
        period = scan_s.get(rid, math.nan)
        out.age_s.update(((rid, tid), n * period) for tid, n in zip(ids, table.plots.tolist(), strict=True))
    return out


# -- one run ------------------------------------------------------------------------------


@dataclass
class RunResult:
    index: int
    run: int
    seed: int
    #: Every :data:`CHECK_S` of data time (``time_s`` relative to the start), then the final.
    checkpoints: list[Scored]
    final: Scored
    #: Radars with a bias estimate at each checkpoint, and at the end.
    registered: list[int]
    radars: int
    #: Final bias estimate errors per radar: (range m, azimuth deg).
    bias_err: list[tuple[float, float]]
    seconds: float = 0.0
    errors: int = 0
    #: The checkpoints and the final snapshot scored with young one-member tracks held back
    #: (``score(..., hold_young_s=YOUNG_S)``).
    held: list[Scored] = field(default_factory=list)


def scenario_of(job: Job) -> Scenario:
    exact = AdsbSpec(
        TRUTH_ID, report_period_s=1.0, batch_period_s=1.0, position_sigma_m=0.0, height_sigma_m=0.0
    )
    return replace(get_scenario(job.condition.scenario), duration_s=job.duration_s, adsb=(exact,))


def _score_engine(
    engine: Engine, truth: Truth, t0: float, accel_psd: float, scan_s: Mapping[str, float]
) -> tuple[Scored, Scored, int] | None:
    """The snapshot scored, and scored again with young one-member tracks held back (a
    what-if), and the radars with a bias estimate."""
    snap = engine.snapshot()
    body = snap.system_tracks("all")
    if body["time_s"] is None:
        return None
    tables = {rid: table for rid, (_, table) in snap.tracks.items()}
    got = snapshot_inputs(tables, float(body["time_s"]), accel_psd, scan_s)

    def true(name: str, t: float) -> np.ndarray | None:
        return truth.position(identity_of(name)[1], t)

    s = score(body, got.label, got.seen, got.raw, true, got.age_s, got.stale_s)
    held = score(body, got.label, got.seen, got.raw, true, got.age_s, got.stale_s, hold_young_s=YOUNG_S)
    s.time_s -= t0
    held.time_s -= t0
    return s, held, len(snap.biases())


def run_one(job: Job) -> RunResult:
    """Stream one job's scenario through a default engine and score it."""
    t_start = time.perf_counter()
    sc = scenario_of(job)
    engine = Engine()
    accel_psd = engine.config.correlation.prediction.accel_psd
    keys = Keys(PREFIX)
    scan_s = {r.radar_id: r.scan_period_s for r in sc.radars}
    truth = Truth()
    checkpoints: list[Scored] = []
    held: list[Scored] = []
    registered: list[int] = []
    errors = 0
    t0 = sc.start_time_s
    next_check = CHECK_S
    for m in generate(sc, job.seed):
        if m.kind == "adsb":  # the truth: never given to the engine
            truth.add(m.body)
            continue
        out = engine.ingest(keys.input(m.kind, m.radar_id), json.dumps(m.body).encode(), receive_time_s=0.0)
        errors += sum(o.key.endswith("/errors") for o in out)
        if m.time_s - t0 >= next_check:
            got = _score_engine(engine, truth, t0, accel_psd, scan_s)
            if got is not None:
                got[0].checkpoint_s = got[1].checkpoint_s = next_check
                checkpoints.append(got[0])
                held.append(got[1])
                registered.append(got[2])
            next_check += CHECK_S
    errors += sum(o.key.endswith("/errors") for o in engine.flush())
    got = _score_engine(engine, truth, t0, accel_psd, scan_s)
    final = got[0] if got is not None else Scored(math.nan)
    held.append(got[1] if got is not None else Scored(math.nan))
    registered.append(got[2] if got is not None else 0)
    estimates = {b["radar_id"]: b for b in engine.snapshot().biases()}
    bias_err = []
    for r in sc.radars:
        est = estimates.get(r.radar_id)
        bias_err.append(
            (abs(est["range_bias_m"] - r.range_bias_m), abs(est["azimuth_bias_deg"] - r.azimuth_bias_deg))
            if est
            else (math.nan, math.nan)
        )
    return RunResult(
        job.index,
        job.run,
        job.seed,
        checkpoints,
        final,
        registered,
        len(sc.radars),
        bias_err,
        time.perf_counter() - t_start,
        errors,
        held,
    )


def make_jobs(runs: int, seed: int, conditions: Sequence[Condition] = CONDITIONS) -> list[Job]:
    """The runs, longest first (the national ones) so that the process pool ends together."""
    jobs = []
    for i, c in enumerate(conditions):
        for r in range(runs):
            sim_seed = int(np.random.SeedSequence([seed, i, r]).generate_state(1)[0] % (2**31))
            jobs.append(Job(i, c, r, sim_seed, c.duration_s))
    return sorted(jobs, key=lambda j: -j.duration_s * len(get_scenario(j.condition.scenario).radars))


def _run_all(jobs: list[Job], workers: int, progress: Callable[[str], None]) -> list[RunResult]:
    return sorted(run_jobs(run_one, jobs, workers, progress, "system"), key=lambda r: (r.index, r.run))


# -- summary ------------------------------------------------------------------------------


def _rms(xs: Sequence[float] | np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(xs)))) if len(xs) else math.nan


def merge(parts: Sequence[Scored]) -> Scored:
    """Pool several scorings (sums of counts, concatenated errors)."""
    out = Scored(math.nan, snapshots=0)
    for p in parts:
        for f in (
            "snapshots",
            "tracks",
            "pure",
            "mixed",
            "mixed_swapped",
            "clutter",
            "aircraft",
            "duplicated",
            "dup_radar",
            "dup_mixed",
            "dup_unlinked",
            "dup_young",
            "seen",
            "covered",
            "uncovered_mixed",
            "uncovered_held",
            "uncovered_held_apart",
            "uncovered_absent",
        ):
            setattr(out, f, getattr(out, f) + getattr(p, f))
        for f in (
            "fused_err",
            "sigma",
            "members",
            "track_raw",
            "raw_err",
            "raw_members",
            "all_members",
            "single_age",
            "single_dup",
            "stray_age",
            "cases",
        ):
            getattr(out, f).extend(getattr(p, f))
    return out


def settled(r: RunResult) -> Scored:
    """A run's checkpoints from :data:`WARMUP_S` on and its final snapshot, pooled."""
    return merge([c for c in r.checkpoints if c.checkpoint_s >= WARMUP_S] + [r.final])


def settled_held(r: RunResult) -> Scored:
    """:func:`settled` of the what-if scoring (young one-member tracks held back)."""
    return merge([c for c in r.held[:-1] if c.checkpoint_s >= WARMUP_S] + r.held[-1:])


def nees(s: Scored) -> float:
    """Mean of ``e^2 / (3 sigma^2)`` over the pure tracks."""
    e, sg = np.asarray(s.fused_err), np.asarray(s.sigma)
    return float(np.mean(e**2 / (3.0 * sg**2))) if e.size else math.nan


def _mean(xs: Sequence[float]) -> float:
    v = [x for x in xs if np.isfinite(x)]
    return float(np.mean(v)) if v else math.nan


def _worst(xs: Sequence[float], low: bool) -> float:
    if not xs or any(not np.isfinite(x) for x in xs):
        return math.nan
    return float(min(xs) if low else max(xs))


def _pct(x: float, digits: int = 2) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.{digits}f}"


def _num(x: float, fmt: str = ".0f") -> str:
    return "-" if not np.isfinite(x) else format(x, fmt)


def _mw(xs: Sequence[float], low: bool, fmt: Callable[[float], str]) -> str:
    return f"{fmt(_mean(xs))} / {fmt(_worst(xs, low))}"


def _yes(ok: bool) -> str:
    return "yes" if ok else "**no**"


@dataclass(frozen=True)
class Verdict:
    purity: tuple[bool, bool]
    duplicates: tuple[bool, bool]
    coverage: tuple[bool, bool]
    ratio: tuple[bool, bool]


def verdict(scores: Sequence[Scored]) -> Verdict:
    """Goals met on the mean over runs, and in every run."""

    def both(xs: list[float], ok: Callable[[float], bool]) -> tuple[bool, bool]:
        return bool(ok(_mean(xs))), bool(xs) and all(np.isfinite(x) and ok(x) for x in xs)

    return Verdict(
        both([s.purity for s in scores], lambda x: x >= GOAL_PURITY),
        both([s.duplicates for s in scores], lambda x: x <= GOAL_DUPLICATES),
        both([s.coverage for s in scores], lambda x: x >= GOAL_COVERAGE),
        both([s.ratio for s in scores], lambda x: x <= GOAL_RATIO),
    )


def _headline_row(label: str, scores: Sequence[Scored]) -> str:
    def m(x: float) -> str:
        return _num(x, ".0f")

    def r(x: float) -> str:
        return _num(x, ".3f")

    return (
        f"| {label} | {len(scores)} | {_mean([s.tracks / s.snapshots for s in scores]):.0f} | "
        f"{_mw([s.purity for s in scores], True, _pct)} | "
        f"{_mw([s.duplicates for s in scores], False, _pct)} | "
        f"{_mw([s.coverage for s in scores], True, _pct)} | "
        f"{_mw([_rms(s.fused_err) for s in scores], False, m)} | "
        f"{_mw([_rms(s.raw_err) for s in scores], False, m)} | "
        f"{_mw([s.ratio for s in scores], False, r)} |"
    )


HEADLINE_HEAD = [
    "| condition, snapshots | runs | confirmed system tracks | purity (%) | duplicates (%) | coverage (%) | "
    "fused RMS (m) | raw RMS (m) | fused / raw |",
    "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
]

#: 99 % quantile of the chi-square distribution with 3 degrees of freedom.
CHI2_3_99 = 11.345


def _q(xs: Sequence[float] | np.ndarray, k: float) -> float:
    return float(np.percentile(xs, k)) if len(xs) else math.nan


def _m(x: float) -> str:
    return _num(x, ".0f")


def _f2(x: float) -> str:
    return _num(x, ".2f")


def _f3(x: float) -> str:
    return _num(x, ".3f")


def _hi(xs: list[float], fmt: Callable[[float], str]) -> str:
    return _mw(xs, False, fmt)


def _error_row(label: str, scores: Sequence[Scored]) -> str:
    def medians(s: Scored) -> float:
        return ratio(_q(s.fused_err, 50), _q(s.raw_err, 50))

    return (
        f"| {label} | {_hi([_q(s.fused_err, 50) for s in scores], _m)} | "
        f"{_hi([_q(s.fused_err, 90) for s in scores], _m)} | "
        f"{_hi([_q(s.fused_err, 99) for s in scores], _m)} | "
        f"{_hi([max(s.fused_err, default=math.nan) for s in scores], _m)} | "
        f"{_hi([_q(s.raw_err, 50) for s in scores], _m)} | {_hi([_q(s.raw_err, 90) for s in scores], _m)} | "
        f"{_hi([s.ratio for s in scores], _f3)} | {_hi([s.ratio_per_track for s in scores], _f3)} | "
        f"{_hi([s.ratio_members(2) for s in scores], _f3)} | {_hi([medians(s) for s in scores], _f3)} |"
    )


ERR_HEAD = [
    "| condition, snapshots | fused p50 (m) | fused p90 (m) | fused p99 (m) | fused max (m) | raw p50 (m) | "
    "raw p90 (m) | fused / raw (headline) | per track | tracks of >= 2 members | p50 / p50 |",
    "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
]


def _nees_of(s: Scored, members: Callable[[np.ndarray], np.ndarray] | None = None) -> float:
    e, sg, n = np.asarray(s.fused_err), np.asarray(s.sigma), np.asarray(s.members)
    keep = members(n) if members is not None else np.ones(e.shape, dtype=bool)
    return float(np.mean(e[keep] ** 2 / (3.0 * sg[keep] ** 2))) if keep.any() else math.nan


def _sigma_row(label: str, scores: Sequence[Scored]) -> str:
    def beyond(s: Scored) -> float:
        e, sg = np.asarray(s.fused_err), np.asarray(s.sigma)
        return float(np.mean(e**2 / sg**2 > CHI2_3_99)) if e.size else math.nan

    def scale(s: Scored) -> float:
        """The factor sigma would need to be multiplied by to make the mean 1."""
        return math.sqrt(nees(s))

    return (
        f"| {label} | {_hi([_mean(s.sigma) for s in scores], _m)} | "
        f"{_hi([_q(s.sigma, 50) for s in scores], _m)} | "
        f"{_hi([nees(s) for s in scores], _f2)} | "
        f"{_hi([_nees_of(s, lambda n: n == 1) for s in scores], _f2)} | "
        f"{_hi([_nees_of(s, lambda n: n >= 2) for s in scores], _f2)} | "
        f"{_hi([scale(s) for s in scores], _f2)} | {_hi([beyond(s) for s in scores], _pct)} |"
    )


SIGMA_HEAD = [
    "| condition, snapshots | mean sigma (m) | p50 sigma (m) | e^2 / (3 sigma^2), mean | one-member tracks | "
    "tracks of >= 2 members | error / stated sigma (sqrt of the mean) | e^2 / sigma^2 > 11.34 (%; 1 % if "
    "honest) |",
    "|---|---:|---:|---:|---:|---:|---:|---:|",
]


def _cause_row(label: str, scores: Sequence[Scored]) -> str:
    def single(s: Scored) -> float:
        return float(np.mean(np.asarray(s.all_members) == 1)) if s.all_members else math.nan

    def per(s: Scored, n: int) -> float:
        return n / s.snapshots

    def mean(f: Callable[[Scored], float]) -> str:
        return f"{_mean([f(s) for s in scores]):.1f}"

    return (
        f"| {label} | {_mw([_mean(s.all_members) for s in scores], True, _f2)} | "
        f"{_hi([single(s) for s in scores], _pct)} | {mean(lambda s: per(s, s.mixed))} "
        f"({mean(lambda s: per(s, s.mixed_swapped))}) | "
        f"{mean(lambda s: per(s, s.clutter))} | {mean(lambda s: per(s, s.duplicated))} "
        f"({mean(lambda s: per(s, s.dup_radar))} / {mean(lambda s: per(s, s.dup_mixed))} / "
        f"{mean(lambda s: per(s, s.dup_unlinked))}) | "
        f"{_hi([ratio(s.dup_young, s.duplicated) for s in scores], _pct)} | "
        f"{mean(lambda s: per(s, s.seen - s.covered))} ({mean(lambda s: per(s, s.uncovered_mixed))} / "
        f"{mean(lambda s: per(s, s.uncovered_held))} ({mean(lambda s: per(s, s.uncovered_held_apart))}) / "
        f"{mean(lambda s: per(s, s.uncovered_absent))}) |"
    )


CAUSE_HEAD = [
    "| condition, snapshots | members / system track | one-member tracks (%) | mixed tracks (of them with "
    "every other member now nearer the track's aircraft) | clutter-only "
    "tracks | duplicated aircraft (radar duplicate / one track mixed / not linked) | duplicated aircraft "
    f"whose stray tracks are all < {YOUNG_S:.0f} s old (%) | uncovered aircraft (in a mixed track only / "
    "in tentative system tracks only (in two or more) / in none) |",
    "|---|---:|---:|---:|---:|---:|---:|---:|",
]

#: Member-count bins of the table by members: (label, lowest, highest).
MEMBER_BINS = (("1", 1, 1), ("2", 2, 2), ("3", 3, 3), ("4-6", 4, 6), ("7-9", 7, 9), ("10-12", 10, 12))


def _by_members(label: str, s: Scored) -> list[str]:
    """Pure tracks by member count, all runs' settled snapshots pooled."""
    n, fe, sg = np.asarray(s.members), np.asarray(s.fused_err), np.asarray(s.sigma)
    rn, re = np.asarray(s.raw_members), np.asarray(s.raw_err)
    total = float(np.sum(fe**2))
    out = []
    for name, lo, hi in MEMBER_BINS:
        k, kr = (n >= lo) & (n <= hi), (rn >= lo) & (rn <= hi)
        if not k.any():
            continue
        out.append(
            f"| {label} | {name} | {_pct(float(np.mean(k)), 1)} | {_m(_rms(fe[k]))} | {_m(_q(fe[k], 50))} | "
            f"{_m(_rms(re[kr]))} | {_f3(ratio(_rms(fe[k]), _rms(re[kr])))} | "
            f"{_pct(ratio(float(np.sum(fe[k] ** 2)), total), 1)} | "
            f"{_f2(float(np.mean(fe[k] ** 2 / (3 * sg[k] ** 2))))} |"
        )
    return out


MEMBERS_HEAD = [
    "| condition | members | share of pure tracks (%) | fused RMS (m) | fused p50 (m) | raw RMS (m) | "
    "fused / raw | share of the fused squared error (%) | e^2 / (3 sigma^2), mean |",
    "|---|---|---:|---:|---:|---:|---:|---:|---:|",
]


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_vs_time(
    path: pathlib.Path, conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]
) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 4, figsize=(15.0, 3.8))
    for i, cond in enumerate(conditions):
        res = by_cond.get(i, [])
        for k, r in enumerate(res):
            t = [c.time_s for c in r.checkpoints]
            style = {"color": f"C{i}", "marker": "o", "ms": 3, "lw": 1.0, "alpha": 0.8}
            lab = cond.label if k == 0 else None
            axes[0].plot(t, [100 * c.purity for c in r.checkpoints], label=lab, **style)
            axes[1].plot(t, [100 * c.duplicates for c in r.checkpoints], label=lab, **style)
            axes[2].plot(t, [100 * c.coverage for c in r.checkpoints], label=lab, **style)
            axes[3].plot(t, [c.ratio for c in r.checkpoints], label=lab, **style)
    for ax, goal, yl in zip(
        axes,
        (100 * GOAL_PURITY, 100 * GOAL_DUPLICATES, 100 * GOAL_COVERAGE, GOAL_RATIO),
        ("purity (%)", "duplicated aircraft (%)", "coverage (%)", "fused RMS / raw RMS"),
        strict=True,
    ):
        ax.axhline(goal, color="k", lw=0.8, ls=":")
        ax.axvline(WARMUP_S, color="grey", lw=0.8, ls="--")
        ax.set_xlabel("data time (s)")
        ax.set_ylabel(yl)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle(f"Confirmed system tracks every {CHECK_S:.0f} s of every run (dotted: goal)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_errors(
    path: pathlib.Path, conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]
) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 4, figsize=(18.0, 4.2))
    for i, cond in enumerate(conditions):
        s = merge([settled(r) for r in by_cond.get(i, [])])
        if not s.fused_err:
            continue
        short = cond.label.split(":")[0]
        for errs, ls, what in ((s.fused_err, "-", "fused"), (s.raw_err, "--", "raw members")):
            e = np.sort(errs)
            axes[0].plot(e, np.arange(1, e.size + 1) / e.size, ls=ls, color=f"C{i}", label=f"{short}, {what}")
        n = np.asarray(s.members)
        fe = np.asarray(s.fused_err)
        rn, re = np.asarray(s.raw_members), np.asarray(s.raw_err)
        ks = np.unique(n)
        axes[1].plot(ks, [_rms(fe[n == k]) for k in ks], "o-", color=f"C{i}", ms=4, label=f"{short}, fused")
        axes[1].plot(
            ks, [_rms(re[rn == k]) for k in ks], "s--", color=f"C{i}", ms=4, label=f"{short}, raw members"
        )
        sg = np.asarray(s.sigma)
        axes[2].scatter(sg, fe / np.sqrt(3.0), s=3, alpha=0.25, color=f"C{i}", label=short)
        ages = np.asarray(s.stray_age)
        ages = ages[np.isfinite(ages)]
        if ages.size:
            axes[3].hist(
                ages, bins=np.arange(0.0, ages.max() + 10.0, 10.0), color=f"C{i}", alpha=0.6, label=short
            )
    axes[0].set_xscale("log")
    axes[0].set_xlabel("position error (m)")
    axes[0].set_ylabel("share of pure system tracks / members")
    axes[1].set_xlabel("members of the system track")
    axes[1].set_ylabel("RMS position error (m)")
    axes[2].set_xlabel("position_sigma_m (m)")
    axes[2].set_ylabel("error / sqrt(3) (m)")
    axes[2].set_xscale("log")
    axes[2].set_yscale("log")
    lim = axes[2].get_xlim()
    axes[2].plot(lim, lim, color="k", lw=0.8, ls=":")
    axes[3].axvline(YOUNG_S, color="k", lw=0.8, ls=":")
    axes[3].set_xlabel("duplicated aircraft: age of its oldest stray track (s)")
    axes[3].set_ylabel("aircraft-snapshots")
    for ax in axes:
        ax.grid(True, alpha=0.3, which="both")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.suptitle(
        f"Pure confirmed system tracks from {WARMUP_S:.0f} s on and at the end (all runs pooled)", fontsize=10
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(
    out_dir: pathlib.Path,
    runs: int | None = None,
    seed: int = 0,
    progress: Callable[[str], None] = print,
    *,
    conditions: Sequence[Condition] = CONDITIONS,
    workers: int | None = None,
) -> str:
    """Run the study, write ``system_*.png`` into ``out_dir``, return the markdown section.

    ``runs``: runs per condition (None: :data:`DEFAULT_RUNS`); ``conditions`` and ``workers``
    (processes; None: up to 2) make small runs for tests.
    """
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n = DEFAULT_RUNS if runs is None else max(int(runs), 1)
    jobs = make_jobs(n, seed, conditions)
    workers = min(2, os.cpu_count() or 1) if workers is None else workers
    progress(f"system: {len(jobs)} runs ({n} per condition), {workers} processes")
    t0 = time.perf_counter()
    results = _run_all(jobs, workers, progress)
    took = time.perf_counter() - t0
    by_cond: dict[int, list[RunResult]] = {}
    for r in results:
        by_cond.setdefault(r.index, []).append(r)
    plot_vs_time(out_dir / "system_vs_time.png", conditions, by_cond)
    plot_errors(out_dir / "system_errors.png", conditions, by_cond)
    return report(conditions, by_cond, n, took, workers)


def report(
    conditions: Sequence[Condition],
    by_cond: Mapping[int, list[RunResult]],
    n: int,
    took: float,
    workers: int,
) -> str:
    """The markdown section of the study."""
    headline, errs, sigmas, causes = [*HEADLINE_HEAD], [*ERR_HEAD], [*SIGMA_HEAD], [*CAUSE_HEAD]
    members = [*MEMBERS_HEAD]
    goals = [
        "| condition, snapshots | purity >= 99 % | duplicates <= 2 % | coverage >= 97 % | "
        "fused / raw <= 0.35 |",
        "|---|---|---|---|---|",
    ]
    for i, cond in enumerate(conditions):
        res = by_cond.get(i, [])
        if not res:
            continue
        for what, scores in (
            (f"settled (>= {WARMUP_S:.0f} s and final, pooled per run)", [settled(r) for r in res]),
            ("final", [r.final for r in res]),
        ):
            label = f"{cond.label}, {what}"
            headline.append(_headline_row(label, scores))
            errs.append(_error_row(label, scores))
            sigmas.append(_sigma_row(label, scores))
            causes.append(_cause_row(label, scores))
            v = verdict(scores)
            goals.append(
                f"| {label} | "
                + " | ".join(
                    f"{_yes(a)} / {_yes(b)}" for a, b in (v.purity, v.duplicates, v.coverage, v.ratio)
                )
                + " |"
            )
        members += _by_members(cond.label.split(":")[0], merge([settled(r) for r in res]))
    md = [
        "## System tracks: one fused, bias-compensated track per aircraft",
        "",
        f"{sum(len(v) for v in by_cond.values())} runs ({n} seeds per condition) of catalog scenarios "
        "streamed through the service's `Engine` (default configuration, in process, no correlation "
        "process; the simulator's wire messages); the system tracks are the engine's own "
        '(`snapshot().system_tracks("confirmed")`, contract §4.4), rebuilt every second of data time '
        "from every radar's tracks, bias-compensated with the joint estimate (solved every 30 s), and "
        "the confirmed pairs; a young lone radar track near another system track that lacks its radar "
        "stays tentative for a while (`SystemTrackParams`).  Nothing is tuned for this study.  "
        "*national*: 12 radars on a 250 km ring, "
        "1 500 aircraft over a 740 km square, biases 150-450 m / 0.1-0.4 deg (the catalog's), clutter "
        "20-50 plots per scan, Pd 0.90-0.95, scans of 4-6 s, plot noise 200 m / 0.2 deg / 0.2 deg "
        "elevation; *three-radar*: 3 radars, 80 aircraft, biases 100-150 m / 0.1-0.15 deg, the same "
        "noise.  Every run has its own simulator seed; "
        + ", ".join(f"{c.scenario} runs {c.duration_s:g} s of data" for c in conditions)
        + ".",
        "",
        "Truth (evaluation only): an exact ADS-B source (every aircraft, every second, no error) is added "
        "to the scenario and its messages kept out of the engine; a radar track's aircraft is its "
        "`truth_id` (the most common aircraft of its plots).  Scoring on the **confirmed** system "
        f"tracks every {CHECK_S:.0f} s of data time and on the final snapshot (after `Engine.flush`): "
        "*pure* = every member follows one aircraft, *mixed* = members of two aircraft (or of an "
        "aircraft and clutter), *clutter-only* = a lone false radar track (not counted in purity).  "
        "**Purity** = pure / (pure + mixed); **duplicates** = aircraft in two or more confirmed system "
        "tracks / aircraft in at least one; **coverage** = aircraft holding a confirmed radar track "
        "that are in a confirmed pure system track / aircraft holding a confirmed radar track.  "
        "Position errors (3-D) at the system tracks' `time_s`: *fused* = the system track's position "
        "(pure tracks), *raw* = each of its member radar tracks as the radar reports it (with the "
        "radar's bias), predicted to that time; **fused / raw** = RMS of the fused errors / RMS of "
        "the raw errors over every member (as tests/fusion/test_system_tracks_service.py computes it).  "
        f"*Settled* pools a run's checkpoints from {WARMUP_S:.0f} s on and its final snapshot; cells "
        "are **mean / worst** over runs.",
        "",
        "### Headline",
        "",
        *headline,
        "",
        "### Goals",
        "",
        "On the mean over runs / in every run:",
        "",
        *goals,
        "",
        *_verdict_lines(conditions, by_cond),
        "",
        "### Position errors",
        "",
        "The fused / raw ratio four ways: the headline (RMS over tracks / RMS over members); *per "
        "track* (each track's members' raw errors RMS-averaged first, so that an aircraft weighs the "
        "same on both sides); over the tracks of two or more members only; and the ratio of medians.",
        "",
        *errs,
        "",
        "By member count (settled snapshots of every run pooled; *share of the fused squared error*: how "
        "much of the fused RMS each group makes):",
        "",
        *members,
        "",
        "### Is the stated sigma honest?",
        "",
        "`sigma` is `position_sigma_m` (`sqrt(tr P / 3)`, per axis) and `e` the 3-D error: "
        "`e^2 / (3 sigma^2)` is 1 on average for an honest sigma, below 1 when sigma is larger than "
        "the error (conservative); *error / stated sigma* is the square root of that mean.",
        "",
        *sigmas,
        "",
        "### Members and failures",
        "",
        "Counts per snapshot (mean over runs).  A duplicated aircraft's *stray* tracks are its radar "
        "tracks outside the system track holding most of them; a track's age is its plots x its "
        "radar's scan period (a little under its true age: missed scans are not counted).",
        "",
        *causes,
    ]
    md += _through_run(conditions, by_cond)
    md += _bias_lines(conditions, by_cond)
    md += _analysis(conditions, by_cond)
    md += _what_if(conditions, by_cond)
    md += _cases(conditions, by_cond)
    errors = sum(r.errors for v in by_cond.values() for r in v)
    per_run = {
        cond.label.split(":")[0]: _mean([r.seconds for r in by_cond.get(i, [])])
        for i, cond in enumerate(conditions)
        if by_cond.get(i)
    }
    md += [
        "",
        f"Rejected or failed input messages (`fusion/errors`) over all runs: {errors}.  Study time "
        f"{took:.0f} s on {workers} processes ("
        + "; ".join(f"{k}: {v:.0f} s per run" for k, v in per_run.items())
        + ", generation and scoring included, on a shared machine).",
        "",
        "![Purity, duplicates, coverage and the error ratio through the runs](system_vs_time.png)",
        "",
        "![Position errors, by member count, and against the stated sigma](system_errors.png)",
    ]
    return "\n".join(md)


def _verdict_lines(conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]) -> list[str]:
    """One sentence per goal on the settled snapshots of the first (national) condition."""
    res = by_cond.get(0, [])
    if not res:
        return []
    scores = [settled(r) for r in res]
    v = verdict(scores)
    name = conditions[0].label.split(":")[0]

    def said(ok: tuple[bool, bool]) -> str:
        return (
            "met in every run" if ok[1] else ("met on the mean, not in every run" if ok[0] else "**not met**")
        )

    return [
        f"On the {name} network, settled: purity >= 99 % {said(v.purity)} "
        f"({_pct(_mean([s.purity for s in scores]))} %); duplicates <= 2 % {said(v.duplicates)} "
        f"({_pct(_mean([s.duplicates for s in scores]))} %); coverage >= 97 % {said(v.coverage)} "
        f"({_pct(_mean([s.coverage for s in scores]))} %); fused / raw <= 0.35 {said(v.ratio)} "
        f"({_f3(_mean([s.ratio for s in scores]))}).",
    ]


def _what_if(conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]) -> list[str]:
    """The same snapshots scored with young one-member system tracks counted as tentative."""
    rows = []
    for i, cond in enumerate(conditions):
        res = by_cond.get(i, [])
        if res and all(r.held for r in res):
            rows.append(_headline_row(f"{cond.label}, settled, held back", [settled_held(r) for r in res]))
            rows.append(
                _headline_row(f"{cond.label}, settled, as the service does", [settled(r) for r in res])
            )
    if not rows:
        return []
    return [
        "",
        "### What if a lone new radar track waited?",
        "",
        "Evaluation only, nothing of the service changed: the service holds a young lone radar track "
        "back only near another system track that lacks its radar (`SystemTrackParams`); here the same "
        f"snapshots are scored again with every one-member system track whose radar track is younger "
        f"than {YOUNG_S:.0f} s (plots x scan period) counted as tentative, wherever it is.  Coverage "
        "pays for the aircraft held by such a track alone.",
        "",
        *HEADLINE_HEAD,
        *rows,
    ]


def _share(mask: np.ndarray) -> float:
    """Share of ``True`` (NaN when empty)."""
    return float(np.mean(mask)) if mask.size else math.nan


def _analysis(conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]) -> list[str]:
    """Why the goals are met or not: the mechanisms, with this run's figures (settled snapshots of
    every run pooled)."""
    lines = ["", "### Why", ""]
    for i, cond in enumerate(conditions):
        res = by_cond.get(i, [])
        if not res:
            continue
        s = merge([settled(r) for r in res])
        name = cond.label.split(":")[0]
        n, fe, sg = np.asarray(s.members), np.asarray(s.fused_err), np.asarray(s.sigma)
        one = n == 1
        total = float(np.sum(fe**2))
        ages = np.asarray(s.stray_age)
        ages = ages[np.isfinite(ages)]
        s_age, s_dup = np.asarray(s.single_age), np.asarray(s.single_dup, dtype=bool)
        young_single = s_age < YOUNG_S
        tail = fe**2 / np.maximum(sg, 1e-9) ** 2 > CHI2_3_99
        mean_nees = nees(s)
        book, solo = PairBookParams(), SystemTrackParams()
        lines += [
            f"**{name}** ({len(res)} runs, {s.snapshots} settled snapshots, "
            f"{s.tracks / max(s.snapshots, 1):.0f} confirmed system tracks and "
            f"{s.seen / max(s.snapshots, 1):.0f} aircraft with a confirmed radar track per snapshot):",
            "",
            f"* *Purity* {_pct(s.purity)} %: {s.mixed} mixed tracks in all, {s.mixed_swapped} of them "
            "with every member of another aircraft now nearer the track's aircraft than its own (a radar "
            "track that went over to another aircraft: its label is the aircraft of most of its plots "
            "over its whole life, so the fusion is right and the label is late); the others join a "
            "clutter track, or tracks of two aircraft flying close (examples below).",
            f"* *Duplicates* {_pct(s.duplicates)} %: {s.duplicated} duplicated aircraft-snapshots: "
            f"{s.dup_unlinked} with tracks of different radars not linked, {s.dup_radar} with two tracks "
            f"of one radar (a radar-tracker duplicate: two tracks of a source never share a system "
            f"track), {s.dup_mixed} with a mixed track (a radar track gone over to another aircraft, "
            "see purity: each of the two aircraft's system tracks then holds a track of the other).  In "
            f"{_pct(ratio(s.dup_young, s.duplicated), 1)} % of them every stray track is younger than "
            f"{YOUNG_S:.0f} s (median {_num(_q(ages, 50), '.0f')} s, figure below).  A radar's new track "
            "on an aircraft the other radars already hold (it comes into that radar's cover or over its "
            "radio horizon, or the radar restarted its track) has no confirmed pair for its first scans: "
            f"the pair book confirms a pair after {book.confirm_hits} hits in {book.window} updates "
            "(`PairBookParams`; one update per scan, of confirmed radar tracks).  The service holds such "
            f"a lone track tentative while it is younger than {solo.solo_hold_s:.0f} s and lies within "
            f"{solo.solo_gate_m / 1000:.0f} km of another system track that has no track of its radar "
            "(`SystemTrackParams`); a young stray track farther off is a duplicate until its pairs "
            "confirm.  Without the young stray tracks the rate would be "
            f"{_pct(ratio(s.duplicated - s.dup_young, s.aircraft))} %.",
            f"* *Coverage* {_pct(s.coverage)} %: of {s.seen - s.covered} uncovered aircraft-snapshots, "
            f"{s.uncovered_mixed} are in mixed tracks only, {s.uncovered_held} in tentative system tracks "
            f"only and {s.uncovered_absent} in no system track at all (a confirmed radar track that is no "
            "member: confirmed since the last rebuild, at most 1 s before, or without a plot for more "
            "than the prediction's `max_age_s`, 60 s).  The tentative ones are young lone tracks the "
            "service holds back (`SystemTrackParams`) although no confirmed system track holds their "
            f"aircraft: {s.uncovered_held_apart} in two or more tentative system tracks (a new "
            "aircraft's tracks from different radars, each held back by the other's system track "
            "nearby, which has no track of its radar: the hold does not ask whether that system track "
            f"is confirmed itself, so both wait for their pair, or {solo.solo_hold_s:.0f} s), "
            f"{s.uncovered_held - s.uncovered_held_apart} in one (held near a system track of another "
            "aircraft, or of clutter).",
            f"* *Fused / raw* {_f3(s.ratio)}: one-member system tracks are {_pct(_share(one), 1)} % of "
            f"the pure tracks and make {_pct(ratio(float(np.sum(fe[one] ** 2)), total), 1)} % of the "
            f"fused squared error; {_pct(_share(young_single), 1)} % of them are radar tracks younger "
            f"than {YOUNG_S:.0f} s and {_pct(_share(s_dup), 1)} % the stray track of an aircraft held "
            "by another system track.  A young track at long range is off by kilometres (plot noise "
            "0.2 deg is 1 km across at 300 km, and as much in height); a one-member track is "
            "compensated but not fused, so it keeps that error.  Over the tracks of two or more members "
            f"the ratio is {_f3(s.ratio_members(2))}; the ratio of medians is "
            f"{_f3(ratio(_q(fe, 50), _q(s.raw_err, 50)))}.",
            f"* *Sigma*: mean `e^2 / (3 sigma^2)` {_f2(mean_nees)} (error / sigma "
            f"{_f2(math.sqrt(mean_nees))}): "
            + (
                "on the whole the stated sigma is larger than the error, as covariance intersection is "
                "built to be (it assumes the worst correlation between the members), and the "
                "compensation adds the bias estimate's own uncertainty.  "
                if mean_nees < 1.0
                else "on the whole the stated sigma is smaller than the error.  "
            )
            + f"{_pct(_share(tail))} % of the tracks lie beyond the chi-square 99 % bound (1 % if "
            f"honest): {_pct(_share(tail[one]))} % of the one-member tracks, {_pct(_share(tail[~one]))} % "
            "of the others"
            + (
                ": a one-member track's sigma is its radar track's covariance, too small for a young "
                "track that started badly."
                if _share(tail[one]) > 0.01
                else "."
            ),
            "",
        ]
    return lines


def _through_run(conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]) -> list[str]:
    lines = [
        "",
        "### Through the runs",
        "",
        "Per checkpoint, mean over runs (radars registered: with a bias estimate in `/biases`):",
        "",
        "| condition | data time (s) | radars registered | confirmed system tracks | purity (%) | "
        "duplicates (%) | coverage (%) | fused RMS (m) | raw RMS (m) | fused / raw |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for i, cond in enumerate(conditions):
        res = by_cond.get(i, [])
        if not res:
            continue
        n_cp = min(len(r.checkpoints) for r in res)
        for k in range(n_cp):
            cs = [r.checkpoints[k] for r in res]
            lines.append(
                f"| {cond.label.split(':')[0]} | {_mean([c.checkpoint_s for c in cs]):.0f} | "
                f"{_mean([r.registered[k] for r in res]):.1f} / {res[0].radars} | "
                f"{_mean([c.tracks for c in cs]):.0f} | {_pct(_mean([c.purity for c in cs]))} | "
                f"{_pct(_mean([c.duplicates for c in cs]))} | {_pct(_mean([c.coverage for c in cs]))} | "
                f"{_num(_mean([_rms(c.fused_err) for c in cs]))} | "
                f"{_num(_mean([_rms(c.raw_err) for c in cs]))} | "
                f"{_num(_mean([c.ratio for c in cs]), '.3f')} |"
            )
    return lines


def _bias_lines(conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]]) -> list[str]:
    lines = ["", "Final bias estimates (`/biases`) against the simulator's biases, over radars and runs:", ""]
    for i, cond in enumerate(conditions):
        res = by_cond.get(i, [])
        if not res:
            continue
        rng = [e[0] for r in res for e in r.bias_err]
        az = [e[1] for r in res for e in r.bias_err]
        lines.append(
            f"* {cond.label}: range error mean {_num(_mean(rng), '.1f')} m, "
            f"worst {_num(_worst(rng, False), '.1f')} m; "
            f"azimuth error mean {_num(_mean(az), '.4f')} deg, worst {_num(_worst(az, False), '.4f')} deg."
        )
    return lines


def _cases(
    conditions: Sequence[Condition], by_cond: Mapping[int, list[RunResult]], per_kind: int = 3
) -> list[str]:
    """A few failing cases of the final snapshots (member ``radar/track=aircraft (age)``), up to
    ``per_kind`` of each kind per condition."""
    lines = [
        "",
        "Examples from the final snapshots (members as `radar/track=aircraft (age)`):",
        "",
    ]
    shown = 0
    for i, cond in enumerate(conditions):
        kinds: dict[str, list[str]] = {}
        for r in by_cond.get(i, []):
            for kind, text in r.final.cases:
                kinds.setdefault(kind, []).append(f"run {r.run}: {text}")
        for kind, texts in kinds.items():
            for text in texts[:per_kind]:
                lines.append(f"* {cond.label.split(':')[0]}, {kind}, {text}")
                shown += 1
    return lines if shown else []
