"""Formation study: SIAP-style metrics of the radar trackers in formations, before, unaided and now.

Entry point :func:`run` (``topofusion evaluate --only formation``); also
``python -m topofusion_lab.evaluation.formation [--runs N] [--seed S] [--out DIR]``.

Every run feeds a formation scenario through :class:`service.engine.Engine` in this process,
exactly as :mod:`topofusion_lab.evaluation.formation_pipeline` does (``topofusion replay
--offline``: the bytes ``topofusion simulate`` publishes, the service's code path, no Zenoh),
three times per seed on the same messages: with every formation rule off (*before*: the tracker's
duplicate rule, its formation's quiet model and weighted update, ``FormationParams.off()``; its two-model
filter, ``FilterParams.imm`` off, so one constant-velocity model; its initiator's ranking by velocity support,
``LogicParams.support_weight = 0``; its deletion by the radar's detection probability,
``ManagerParams.deletion_miss_probability = 0``, so three misses whatever the radar;
correlation's caution with low-quality tracks,
``correlation.prompt.min_quality = 0``; its swap rule, ``correlation.swap.enabled = False``;
the published score's tracks' quality, ``correlation.book.quality_exponent = 0``; the hold of
a contested pair, ``correlation.book.hold_score = 0``; the aid of association,
``tracking.aid.enabled = False``), with the default and the aid of association off
(*unaided*: :mod:`service.tracking.aid`, on by default), and with the default configuration
(*now*).  Nothing else of the service is changed or tuned.

Scenario grid (:data:`POINTS`), each from the catalog's ``formation`` scenario (three en-route
radars, 30 aircraft at 230 m/s, azimuth biases of 0.3-0.4 deg), its first :data:`DURATION_S`:
the lattice spacing is 1x, 2x, 3x and 4x the *cross-range error* of the radars, the largest
over the three of ``range x azimuth sigma`` (radians) at the scenario centre (where the
formation is at 300 s), 403 m (radar C: 0.20 deg at 115 km).  Detection probability: the
catalog's (0.95, 0.92, 0.75) and, at 2x, every radar at 0.7 and every radar at 0.95.  Two more
shapes at 2x (``topofusion_lab.scenarios.catalog``): two groups of 15 *crossing* at 40 deg at
the centre at 300 s, and two groups *merging* (converging at 15 deg each side, each turning at
240 s onto the formation's heading where together they make one lattice).  And the lattice at
2x and 3x *in traffic* (:func:`with_traffic`): 32 more aircraft in two wide groups around it,
of which only the formation's aircraft, their tracks and pairs are scored; a formation alone is
the registration's worst case, and in a real sky it flies among others.  :data:`DEFAULT_RUNS`
seeds each; the same seeds for every point and every tracker.

Sampling: the engine's snapshot every :data:`SAMPLE_S` of data time (a scan of the slowest
radar) from :data:`WARMUP_S` on, and the final one (after ``flush``).  Truth (evaluation only;
no algorithm reads it): each track's ``truth_id`` (the aircraft with most of its plots;
``None``: a track on clutter) and the simulator's true target states
(``generate(..., observe=)``, every simulation step; a state between steps is the step's
position plus velocity times the time since, as the simulator itself moves targets).

Metrics, after Stone Soup's ``SIAPMetrics`` (the SIAP attribute measures of Votruba et al.,
*Single Integrated Air Picture (SIAP) Metrics Implementation*, 2001): there, at each time J is
the number of true objects, JT of those tracked, N the number of tracks and NA of those
assigned to a true object; completeness = sum JT / sum J, ambiguity = sum NA / sum JT,
spuriousness = sum (N - NA) / sum N, positional accuracy = the mean error of the assigned
tracks, and the rate of track-number change = sum over truths of (track numbers - 1) / sum of
their time tracked.  Here per radar and sample, on **confirmed** radar tracks, a track assigned
to its ``truth_id`` (:func:`siap_sample`); every sum runs over radars, samples and seeds:

* **completeness**: aircraft-samples with >= 1 confirmed track / aircraft-samples of aircraft
  the radar can detect (within its range and radio horizon, :func:`~topofusion_lab.scenarios.
  simulator.in_coverage`, and Pd > 0);
* **ambiguity**: confirmed tracks on aircraft / aircraft with >= 1 (1 is ideal);
* **duplicates**: confirmed tracks beyond the first on one aircraft / confirmed tracks;
* **spuriousness**: confirmed tracks on clutter (``truth_id`` None) / confirmed tracks;
* **astray** (a diagnostic, not SIAP's): confirmed tracks on an aircraft whose position is
  horizontally nearer another aircraft (each as the radar sees it, at the track's time) than
  their own / confirmed tracks on aircraft: tracks swapped onto a neighbour.  ``truth_id`` is
  the aircraft of most of a track's plots, so a swapped track still counts on its first
  aircraft: that aircraft then shows as duplicated (and the neighbour's own track as its
  second) although no two tracks follow one aircraft;
* **plots to another aircraft** (a diagnostic, not SIAP's): of the plots that joined a track
  (tentative or confirmed) already on an aircraft (the aircraft of most of its plots, with at
  least :data:`~service.evaluation.truth.LED_PLOTS` of them), the share of another aircraft's
  (:class:`~service.evaluation.truth.TruthTally`'s ``joined_other / joined_led``, over the
  whole run): the association errors themselves, the cause of tracks astray, ID switches and
  duplicates; in brackets the share of those whose track's own aircraft had a plot in the same
  batch (``joined_other_seen``: the one assignment chose the neighbour's; the rest, own
  aircraft not detected in that batch, is a track that took a plot while its aircraft was missed);
* **ID switches** per aircraft-hour (:class:`IdSwitches`): per radar and aircraft, the track
  *followed* is kept while it is among the aircraft's confirmed tracks; when it is not (or at
  the first sample with one), the confirmed track with the most plots (then the smallest id)
  is followed, and that is a switch unless it is the first assignment (a gap without any
  confirmed track is no switch; coming back under the same id neither).  Rate = switches /
  (aircraft-samples with >= 1 confirmed track x :data:`SAMPLE_S` / 3600), the SIAP rate per
  time tracked;
* **position error**: the mean (SIAP's positional accuracy) and the RMS of the horizontal
  error (the difference without its component along the local vertical at the truth) of
  confirmed tracks on aircraft at the track's ``time_s``, against the aircraft's true position
  *as the radar sees it*: moved by the radar's true range, gain, azimuth and elevation biases
  (:func:`apparent`; the trackers work in the radar's frame and cannot know them:
  registration is another study's).  A track that has drifted onto a neighbour while most of
  its plots are still its first aircraft's counts with the distance between them.  The RMS
  against the true position itself, bias included, is :func:`summarize`'s ``raw_rms_m``;
* **quality**: the mean ``TrackTable.quality`` of confirmed tracks (NaN values left out);
* **pairs correct / false**: :func:`~topofusion_lab.evaluation.formation_pipeline.
  score_snapshot`'s ``found / common`` and ``false / judged`` (all radar pairs together),
  pooled over the samples from :data:`PAIR_WARMUP_S` on (the registration of the biases
  takes the first minutes); the mean over seeds, and for false pairs also the worst seed;
* **pairs on two aircraft now** (a diagnostic beside the pair rates, not a goal): of the
  same judged confirmed pairs, those whose two tracks are now nearest two different aircraft
  (:func:`nearest_aircraft`, each as its radar sees them): pairs that fuse two aircraft at that
  moment (:func:`pairs_on_two_aircraft`).  The two judges differ on a track that went over to
  a neighbour: ``truth_id`` (most of its plots) still names its first aircraft, so its pair
  with the neighbour's track on another radar counts false although both follow one aircraft
  now, and its pair with its first aircraft's track counts right although it fuses two;
* **score reliability**: over the same samples, every judged confirmed pair's published score
  in the bins of :data:`~topofusion_lab.evaluation.formation_pipeline.SCORE_BINS`, the share
  of each bin that is right, and the Brier score (the mean of ``(score - right)^2``): whether a
  pair's score means what it says through the whole pipeline, the trackers' mistakes included.

The formation goals are checked per configuration: false pairs <= 2 % in every seed at every
spacing, correct pairs >= 92 % on average at spacing >= 2x, duplicate tracks <= 2 %, and ID
switches (now) at most half of before's, each over the lattice points and the whole grid as
said in the table.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys
import time
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from itertools import pairwise
from typing import Any

import numpy as np

from service.config import EngineConfig, with_aid, without_aid
from service.evaluation.truth import TruthLabelledTracker
from service.geo import Site, ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from service.tracking.params import FormationParams
from topofusion_lab.evaluation.formation_bounds import (
    BOUNDS,
    EngineRef,
    RadarTruth,
    bounded_factory,
    no_hold,
)
from topofusion_lab.evaluation.formation_pipeline import (
    SCORE_BINS,
    formation_scenario,
    run_pipeline,
    score_snapshot,
)
from topofusion_lab.evaluation.jobs import ratio, run_jobs
from topofusion_lab.scenarios.catalog import formation_crossing, formation_merging, get_scenario
from topofusion_lab.scenarios.simulator import FormationSpec, RadarSpec, Scenario, in_coverage

#: Seeds per point by default.
DEFAULT_RUNS = 3
#: Data seconds per run (the catalog's 600 s cost about 2 minutes of engine time a run at 2x
#: spacing on a 2-core machine; by 480 s the pairs have settled).
DURATION_S = 480.0
#: Sampling interval (data s): a scan of the formation's slowest radar (B, 10 s).
SAMPLE_S = 10.0
#: Tracking metrics from this data time on (track initiation over).
WARMUP_S = 120.0
#: Pair metrics from this data time on (the registration of the biases settled).
PAIR_WARMUP_S = 360.0
#: The configurations compared: every formation rule off, the default without the aid of
#: association, and the default now.
VARIANTS = ("before", "unaided", "now")
GOAL_FALSE_PCT = 2.0
GOAL_CORRECT_PCT = 92.0
GOAL_DUPLICATES = 0.02
GOAL_SWITCH_RATIO = 0.5


#: Aircraft of background traffic at the points *in traffic* (:func:`with_traffic`).
TRAFFIC_AIRCRAFT = 32


@dataclass(frozen=True)
class Point:
    """A point of the grid: ``shape`` ``lattice`` (the catalog's formation), ``crossing`` or
    ``merging``; the lattice spacing in cross-range errors; every radar's Pd (None: the
    catalog's); ``traffic``: aircraft of background traffic around the formation
    (:func:`with_traffic`; only the formation's aircraft are scored)."""

    label: str
    shape: str
    spacing_x: float
    pd: float | None = None
    traffic: int = 0


POINTS: tuple[Point, ...] = (
    Point("1x", "lattice", 1.0),
    Point("2x", "lattice", 2.0),
    Point("3x", "lattice", 3.0),
    Point("4x", "lattice", 4.0),
    Point("2x, Pd 0.7", "lattice", 2.0, 0.7),
    Point("2x, Pd 0.95", "lattice", 2.0, 0.95),
    Point("crossing, 2x", "crossing", 2.0),
    Point("merging, 2x", "merging", 2.0),
    # The lattice in traffic: a formation within a sky of other aircraft, whose spread lets
    # the registration find the biases (a formation alone flies one place on one heading, and
    # the biases' combinations it shows are few).
    Point("2x in traffic", "lattice", 2.0, traffic=TRAFFIC_AIRCRAFT),
    Point("3x in traffic", "lattice", 3.0, traffic=TRAFFIC_AIRCRAFT),
)
#: Background traffic: two wide groups, this far apart (m), each its own heading and speed.
TRAFFIC_SPACING_M = 20_000.0


def cross_range_m(sc: Scenario) -> float:
    """The largest ``range x azimuth sigma`` (rad) of ``sc``'s radars at the scenario centre, at
    the middle of the scenario's altitude band."""
    centre = geodetic_to_ecef(sc.center_lat_deg, sc.center_lon_deg, float(np.mean(sc.altitude_m)))
    return max(
        float(r.site().ecef_to_polar(centre)[0]) * math.radians(r.azimuth_sigma_deg) for r in sc.radars
    )


def scenario(point: Point, duration_s: float | None = None, targets: int | None = None) -> Scenario:
    """The scenario of a grid point (``duration_s`` / ``targets``: the catalog's if None)."""
    base = get_scenario("formation")
    spacing = point.spacing_x * cross_range_m(base)
    n = base.targets if targets is None else targets
    if point.shape == "lattice":
        sc = formation_scenario(n, spacing)
    elif point.shape == "crossing":
        sc = formation_crossing(spacing, targets=n)
    elif point.shape == "merging":
        sc = formation_merging(spacing, targets=n)
    else:
        raise ValueError(f"unknown shape {point.shape!r}")
    if point.pd is not None:
        sc = replace(sc, radars=tuple(replace(r, pd=point.pd) for r in sc.radars))
    if duration_s is not None:
        sc = replace(sc, duration_s=duration_s)
    return with_traffic(sc, point.traffic) if point.traffic else sc


def with_traffic(sc: Scenario, n: int) -> Scenario:
    """``sc`` (one formation) with ``n`` more aircraft around it: two groups of half each,
    :data:`TRAFFIC_SPACING_M` apart with a jitter of 0.3 spacing, one heading 160 at 210 m/s
    from 50 km north, one 300 at 180 m/s from 50 km east (both through the radars' common
    coverage).  The formation's aircraft keep their ids (``T1`` .. ``Tk``, spawned first)."""
    assert sc.formation is not None
    groups = (
        replace(sc.formation, count=sc.targets),
        _group(160.0, 210.0, -20_000.0, 50_000.0, n // 2),
        _group(300.0, 180.0, 50_000.0, -30_000.0, n - n // 2),
    )
    return replace(sc, formation=None, formations=groups, targets=sc.targets + n)


def _group(heading_deg: float, speed_mps: float, east_m: float, north_m: float, n: int) -> FormationSpec:
    return FormationSpec(
        spacing_m=TRAFFIC_SPACING_M,
        jitter=0.3,
        heading_deg=heading_deg,
        speed_mps=speed_mps,
        start_east_m=east_m,
        start_north_m=north_m,
        count=n,
    )


def focus_of(point: Point, sc: Scenario) -> frozenset[str] | None:
    """The aircraft a point scores: with background traffic the formation's (None: all)."""
    if not point.traffic:
        return None
    return frozenset(f"T{k}" for k in range(1, sc.targets - point.traffic + 1))


def engine_config(variant: str) -> EngineConfig:
    """The engine's configuration of a variant (:data:`VARIANTS`): *before* has every formation
    rule off (the tracker's duplicate rule, formation's quiet model and weighted update, two-model filter and
    initiator's velocity support, deletion by the radar's detection probability, correlation's
    caution with low-quality tracks and its swap rule, the published score's tracks' quality,
    the hold of a contested pair, the aid of association), *unaided* the default with the aid of
    association off (``tracking.aid``, :mod:`service.tracking.aid`; the bounds' tracker),
    *now* is the default."""
    cfg = EngineConfig()
    if variant == "before":
        base = without_aid(cfg)
        corr = base.correlation
        return replace(
            base,
            tracking=replace(
                base.tracking,
                formation=FormationParams.off(),
                filter=replace(base.tracking.filter, imm=False),
                logic=replace(base.tracking.logic, support_weight=0.0),
                manager=replace(base.tracking.manager, deletion_miss_probability=0.0),
            ),
            correlation=replace(
                corr,
                prompt=replace(corr.prompt, min_quality=0.0),
                swap=replace(corr.swap, enabled=False),
                book=replace(corr.book, quality_exponent=0.0, hold_score=0.0),
            ),
        )
    if variant == "now":
        return cfg
    if variant == "unaided":
        return without_aid(cfg)
    raise ValueError(f"unknown variant {variant!r}")


# -- truth ----------------------------------------------------------------------------------------
class TruthLog:
    """The simulator's true target states at every step (an ``observe`` of ``generate``)."""

    def __init__(self, sc: Scenario) -> None:
        self.t0 = sc.start_time_s
        self.center = geodetic_to_ecef(sc.center_lat_deg, sc.center_lon_deg, 0.0)
        self.rot = enu_rotation(sc.center_lat_deg, sc.center_lon_deg)
        self.times: list[float] = []
        self.rows: list[dict[str, int]] = []
        self.pos: list[np.ndarray] = []
        self.vel: list[np.ndarray] = []

    def __call__(self, t: float, ids: np.ndarray, pos: np.ndarray, vel: np.ndarray) -> None:
        self.times.append(t)
        self.rows.append({str(x): i for i, x in enumerate(ids)})
        self.pos.append(pos)
        self.vel.append(vel)

    def _step(self, t_rel: float) -> int:
        return max(int(np.searchsorted(self.times, t_rel + 1e-9, side="right")) - 1, 0)

    def aircraft(self, t_abs: float) -> tuple[list[str], np.ndarray]:
        """Every aircraft and its true ECEF position at data time ``t_abs``."""
        k = self._step(t_abs - self.t0)
        names = list(self.rows[k])
        enu = self.pos[k] + self.vel[k] * (t_abs - self.t0 - self.times[k])
        return names, enu @ self.rot.T + self.center

    def ecef(self, names: Sequence[str], t_abs: np.ndarray) -> np.ndarray:
        """True ECEF positions of aircraft ``names[i]`` at data times ``t_abs[i]`` (NaN: unknown)."""
        out = np.full((len(names), 3), np.nan)
        for i, (name, t) in enumerate(zip(names, t_abs, strict=True)):
            k = self._step(float(t) - self.t0)
            row = self.rows[k].get(name)
            if row is not None:
                enu = self.pos[k][row] + self.vel[k][row] * (float(t) - self.t0 - self.times[k])
                out[i] = enu @ self.rot.T + self.center
        return out


def apparent(radar: RadarSpec, site: Site, ecef: np.ndarray) -> np.ndarray:
    """Positions ``ecef`` as radar ``radar`` sees them without noise: its range gain and bias,
    azimuth and elevation biases applied in its polar frame (as the simulator applies them)."""
    r, az, el = site.ecef_to_polar(ecef)
    r = r * (1.0 + radar.range_gain_ppm * 1e-6) + radar.range_bias_m
    return site.polar_to_ecef(r, az + radar.azimuth_bias_deg, el + radar.elevation_bias_deg)


def _truth_for(sc: Scenario, truth: TruthLog) -> Callable[[str, Site], RadarTruth]:
    """The association bounds' truth (:mod:`.formation_bounds`): each radar's true positions
    of the aircraft as it sees them (:func:`apparent`), and its biases."""
    radars = {r.radar_id: r for r in sc.radars}

    def truth_for(radar_id: str, site: Site) -> RadarTruth:
        radar = radars[radar_id]

        def positions(names: Sequence[str], t_abs: np.ndarray) -> np.ndarray:
            ecef = truth.ecef(names, t_abs)
            ok = ~np.isnan(ecef[:, 0])
            ecef[ok] = apparent(radar, site, ecef[ok])
            return ecef

        return RadarTruth(
            positions, lambda ecef: unbiased(radar, site, ecef), lambda ecef: apparent(radar, site, ecef)
        )

    return truth_for


def unbiased(radar: RadarSpec, site: Site, ecef: np.ndarray) -> np.ndarray:
    """The inverse of :func:`apparent`: positions ``ecef`` radar ``radar`` reports, its biases
    taken out."""
    r, az, el = site.ecef_to_polar(ecef)
    r = (r - radar.range_bias_m) / (1.0 + radar.range_gain_ppm * 1e-6)
    return site.polar_to_ecef(r, az - radar.azimuth_bias_deg, el - radar.elevation_bias_deg)


def nearest_aircraft(truth: TruthLog, radar: RadarSpec, site: Site, ecef: np.ndarray, t_abs: float) -> str:
    """The aircraft horizontally nearest to a track's position ``ecef`` at its time, every
    aircraft as radar ``radar`` sees it (:func:`apparent`)."""
    names, true = truth.aircraft(float(t_abs))
    d = horizontal_errors(np.broadcast_to(ecef, true.shape), apparent(radar, site, true))
    return names[int(np.argmin(d))]


def horizontal_errors(track_ecef: np.ndarray, truth_ecef: np.ndarray) -> np.ndarray:
    """The horizontal part of ``track - truth`` (m): without its component along the local
    vertical (the ellipsoid's normal) at the truth."""
    track_ecef, truth_ecef = np.atleast_2d(track_ecef), np.atleast_2d(truth_ecef)
    lat, lon, _ = ecef_to_geodetic(truth_ecef)
    lat, lon = np.radians(np.atleast_1d(lat)), np.radians(np.atleast_1d(lon))
    up = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=1)
    d = track_ecef - truth_ecef
    horizontal = d - np.sum(d * up, axis=1)[:, None] * up
    return np.asarray(np.linalg.norm(horizontal, axis=1))


# -- the metrics ----------------------------------------------------------------------------------
def pairs_on_two_aircraft(
    pair_views: Iterable[Any], nearest: Mapping[tuple[str, str], str]
) -> tuple[int, int]:
    """Of the confirmed pairs of ``pair_views`` (``PairSetView``) whose two tracks are both in
    ``nearest`` ((radar, track id) -> the aircraft nearest the track now), how many there are
    and how many have two different nearest aircraft."""
    judged = two = 0
    for view in pair_views:
        c = view.columns
        for ta, tb, ok in zip(c["track_a"], c["track_b"], c["confirmed"], strict=True):
            a = nearest.get((view.radar_a, str(ta)))
            b = nearest.get((view.radar_b, str(tb)))
            if ok and a is not None and b is not None:
                judged += 1
                two += a != b
    return judged, two


def siap_sample(labels: Sequence[str | None], detectable: Collection[str]) -> dict[str, int]:
    """SIAP counts of one radar's confirmed tracks at one sample: ``labels`` their ``truth_id``
    (None: clutter), ``detectable`` the aircraft the radar can detect then.

    ``truths`` (J), ``tracked`` (JT: of those, with >= 1 track), ``tracks`` (N), ``assigned``
    (NA: tracks on an aircraft), ``aircraft`` (aircraft with >= 1 track, detectable or not),
    ``duplicates`` (NA - aircraft), ``spurious`` (N - NA)."""
    on = [x for x in labels if x is not None]
    aircraft = set(on)
    return {
        "truths": len(set(detectable)),
        "tracked": len(aircraft & set(detectable)),
        "tracks": len(labels),
        "assigned": len(on),
        "aircraft": len(aircraft),
        "duplicates": len(on) - len(aircraft),
        "spurious": len(labels) - len(on),
    }


class IdSwitches:
    """Track-number changes per radar and aircraft through a sequence of samples (see the
    module: the followed track, its switches, and the aircraft-samples tracked)."""

    def __init__(self) -> None:
        self.following: dict[tuple[str, str], str] = {}
        self.switches = 0
        self.tracked = 0

    def update(self, radar: str, tracks: Iterable[tuple[str, str | None, int]]) -> int:
        """One sample of ``radar``'s confirmed tracks as ``(track_id, truth_id, plots)``;
        returns the switches it adds."""
        by_aircraft: dict[str, list[tuple[int, str]]] = {}
        for track_id, truth, plots in tracks:
            if truth is not None:
                by_aircraft.setdefault(truth, []).append((int(plots), str(track_id)))
        added = 0
        for aircraft, held in by_aircraft.items():
            self.tracked += 1
            key = (radar, aircraft)
            now = self.following.get(key)
            if now is not None and any(tid == now for _, tid in held):
                continue
            best = min(held, key=lambda c: (-c[0], c[1]))[1]
            if now is not None:
                added += 1
            self.following[key] = best
        self.switches += added
        return added


# -- one run ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Job:
    index: int
    point: Point
    variant: str
    run: int
    seed: int
    duration_s: float | None
    targets: int | None
    #: A bound's tracks' reference error (m; :mod:`.formation_bounds`, ``true-position``).
    offset_m: float = 0.0
    #: The correlation's hold of contested pairs on (the default) or off.
    hold: bool = True
    #: ``paired*`` bounds: the correlation's pairs and biases this far back (data s).
    aid_lag_s: float = 0.0


def _zero() -> dict[str, float]:
    keys = ("truths", "tracked", "tracks", "assigned", "aircraft", "duplicates", "spurious")
    return dict.fromkeys(keys, 0.0)


def run_one(job: Job) -> dict[str, Any]:
    """One seeded run of a point with one tracker: the pooled sums of every metric."""
    started = time.perf_counter()
    sc = scenario(job.point, job.duration_s or DURATION_S, job.targets)
    assert sc.duration_s is not None
    warmup = min(WARMUP_S, 0.25 * sc.duration_s)
    pair_warmup = min(PAIR_WARMUP_S, 0.5 * sc.duration_s)
    at = list(np.arange(warmup, sc.duration_s - 1e-9, SAMPLE_S))
    truth = TruthLog(sc)
    focus = focus_of(job.point, sc)
    config = engine_config("unaided" if job.variant in BOUNDS else job.variant)
    if not job.hold:
        config = no_hold(config)
    if job.variant == "now" and job.aid_lag_s > 0:
        config = with_aid(config, lag_s=job.aid_lag_s)
    factory = None
    ref = EngineRef(job.aid_lag_s)
    if job.variant in BOUNDS:
        factory = bounded_factory(config, job.variant, _truth_for(sc, truth), job.offset_m, job.seed, ref)
    radars = {r.radar_id: r for r in sc.radars}
    sites = {r.radar_id: r.site() for r in sc.radars}
    siap = _zero()
    ids = IdSwitches()
    err1 = err2 = raw2 = 0.0
    astray = 0
    errors = 0
    quality_sum, quality_n = 0.0, 0
    pairs = dict.fromkeys(("common", "found", "false", "judged", "judged_now", "two_now"), 0)
    score_n = [0] * (len(SCORE_BINS) - 1)
    score_right = [0] * (len(SCORE_BINS) - 1)
    brier = 0.0
    samples = 0
    joined = {"led": 0, "other": 0, "other_seen": 0}
    for t, snap, engine in run_pipeline(
        sc, job.seed, config=config, at_s=at, observe=truth, tracker_factory=factory, on_engine=ref.set
    ):
        if t >= sc.duration_s:  # (the last snapshot: the whole run's association counts)
            for tracked in engine.tracking.tracked.values():
                if isinstance(tracked.tracker, TruthLabelledTracker):
                    joined["led"] += tracked.tracker.tally.joined_led
                    joined["other"] += tracked.tracker.tally.joined_other
                    joined["other_seen"] += tracked.tracker.tally.joined_other_seen
        samples += 1
        t_abs = sc.start_time_s + t
        names, ecef = truth.aircraft(t_abs)
        if focus is not None:  # (the background's aircraft and their tracks are not scored)
            keep = [i for i, n in enumerate(names) if n in focus]
            names, ecef = [names[i] for i in keep], ecef[keep]
        pair_sample = t >= pair_warmup - 1e-9
        nearest: dict[tuple[str, str], str] = {}  # (radar, track) -> nearest aircraft now
        for rid, (_, table) in sorted(snap.tracks.items()):
            radar = radars.get(rid)
            if radar is None:
                continue
            conf = np.asarray(table.confirmed, dtype=bool)
            if focus is not None:
                conf &= np.array([x is None or str(x) in focus for x in table.truth_id], dtype=bool)
            labels = [None if x is None else str(x) for x in table.truth_id[conf]]
            rng_m = sites[rid].ecef_to_polar(ecef)[0] if names else np.empty(0)
            alt = np.atleast_1d(ecef_to_geodetic(ecef)[2]) if names else np.empty(0)
            covered = in_coverage(radar, rng_m, alt) if radar.pd > 0 else np.zeros(len(names), bool)
            detectable = {n for n, ok in zip(names, covered, strict=True) if ok}
            for k, v in siap_sample(labels, detectable).items():
                siap[k] += v
            ids.update(rid, zip(table.track_id[conf], labels, table.plots[conf], strict=True))
            near = {
                int(i): nearest_aircraft(truth, radar, sites[rid], table.position_ecef_m[i], table.time_s[i])
                for i in np.flatnonzero(conf)
                if pair_sample or table.truth_id[i] is not None
            }
            if pair_sample:
                nearest.update({(rid, str(table.track_id[i])): a for i, a in near.items()})
            on = [i for i, x in zip(np.flatnonzero(conf), labels, strict=True) if x is not None]
            labels_on = [x for x in labels if x is not None]
            if on:
                true = truth.ecef([str(table.truth_id[i]) for i in on], table.time_s[on])
                ok = ~np.isnan(true[:, 0])
                pos = table.position_ecef_m[on][ok]
                e = horizontal_errors(pos, apparent(radar, sites[rid], true[ok]))
                raw = horizontal_errors(pos, true[ok])
                err1 += float(np.sum(e))
                err2 += float(np.sum(e**2))
                raw2 += float(np.sum(raw**2))
                errors += int(ok.sum())
                astray += sum(near[int(i)] != label for i, label in zip(on, labels_on, strict=True))
            q = np.asarray(table.quality, dtype=float)[conf]
            q = q[~np.isnan(q)]
            quality_sum += float(q.sum())
            quality_n += int(q.size)
        if pair_sample:
            judged_now, two_now = pairs_on_two_aircraft(snap.pair_views, nearest)
            pairs["judged_now"] += judged_now
            pairs["two_now"] += two_now
            scored = score_snapshot(snap, focus)
            total = scored["total"]
            for b, (n_b, right_b) in enumerate(
                zip(scored["scores"]["score_n"], scored["scores"]["score_right"], strict=True)
            ):
                score_n[b] += n_b
                score_right[b] += right_b
            brier += scored["scores"]["brier_sum"]
            pairs["common"] += total["common"]
            pairs["found"] += total["found"]
            pairs["false"] += total["false"]
            pairs["judged"] += total["confirmed"] - total["gone"]
    return {
        "index": job.index,
        "point": job.point.label,
        "variant": job.variant,
        "run": job.run,
        "seed": job.seed,
        "targets": sc.targets,
        "duration_s": sc.duration_s,
        "samples": samples,
        **siap,
        "astray": astray,
        "joined_led": joined["led"],
        "joined_other": joined["other"],
        "joined_other_seen": joined["other_seen"],
        "switches": ids.switches,
        "tracked_samples": ids.tracked,
        "errors": errors,
        "err1": err1,
        "err2": err2,
        "raw2": raw2,
        "quality_sum": quality_sum,
        "quality_n": quality_n,
        **{f"pairs_{k}": v for k, v in pairs.items()},
        "score_n": score_n,
        "score_right": score_right,
        "brier_sum": brier,
        "wall_s": time.perf_counter() - started,
    }


# -- summary ---------------------------------------------------------------------------------------
def summarize(runs: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """The metrics of several runs (sums pooled; pair rates also per run: mean, worst)."""

    def tot(k: str) -> float:
        return float(sum(r[k] for r in runs))

    per_correct = [100.0 * ratio(r["pairs_found"], r["pairs_common"]) for r in runs]
    score_n = np.sum([r["score_n"] for r in runs], axis=0)
    score_right = np.sum([r["score_right"] for r in runs], axis=0)
    per_false = [100.0 * ratio(r["pairs_false"], r["pairs_judged"]) for r in runs]
    per_two = [100.0 * ratio(r["pairs_two_now"], r["pairs_judged_now"]) for r in runs]
    hours = tot("tracked_samples") * SAMPLE_S / 3600.0
    return {
        "runs": len(runs),
        "completeness": ratio(tot("tracked"), tot("truths")),
        "ambiguity": ratio(tot("assigned"), tot("aircraft")),
        "duplicates": ratio(tot("duplicates"), tot("tracks")),
        "spuriousness": ratio(tot("spurious"), tot("tracks")),
        "astray": ratio(tot("astray"), tot("assigned")),
        "plots_other": ratio(tot("joined_other"), tot("joined_led")),
        "plots_other_seen": ratio(tot("joined_other_seen"), tot("joined_other")),
        "switches_per_h": ratio(tot("switches"), hours),
        "switches": tot("switches"),
        "position_mean_m": ratio(tot("err1"), tot("errors")),
        "position_rms_m": math.sqrt(ratio(tot("err2"), tot("errors"))),
        "raw_rms_m": math.sqrt(ratio(tot("raw2"), tot("errors"))),
        "quality": ratio(tot("quality_sum"), tot("quality_n")),
        "correct_pct": _nanmean(per_correct),
        "false_pct": _nanmean(per_false),
        "false_worst_pct": _nanmax(per_false),
        "two_now_pct": _nanmean(per_two),
        "two_now_worst_pct": _nanmax(per_two),
        **{f"score_n_{k}": float(v) for k, v in enumerate(score_n)},
        **{
            f"score_right_{k}": ratio(float(r), float(n))
            for k, (r, n) in enumerate(zip(score_right, score_n, strict=True))
        },
        "brier": ratio(tot("brier_sum"), float(sum(score_n))),
    }


def _nanmean(xs: Sequence[float]) -> float:
    d = [x for x in xs if not math.isnan(x)]
    return float(np.mean(d)) if d else math.nan


def _nanmax(xs: Sequence[float]) -> float:
    d = [x for x in xs if not math.isnan(x)]
    return max(d) if d else math.nan


def _f(x: float, fmt: str) -> str:
    return "-" if math.isnan(x) else format(x, fmt)


def report(
    points: Sequence[Point], results: Sequence[Mapping[str, Any]], n: int, took: float, workers: int
) -> str:
    """The markdown section of the study."""
    by: dict[tuple[int, str], list[Mapping[str, Any]]] = {}
    for r in results:
        by.setdefault((r["index"], r["variant"]), []).append(r)
    first = results[0] if results else {"targets": 0, "duration_s": 0.0}
    unit = cross_range_m(get_scenario("formation"))
    lines = [
        "## Formation: SIAP-style tracker metrics, before, unaided and now",
        "",
        f"The catalog's `formation` scenario (3 radars, {first['targets']} aircraft, "
        f"{first['duration_s']:.0f} s) through the engine, per point {n} seed(s), each run three times "
        "on the same messages: *before*, every formation rule off (the tracker's duplicate rule, "
        "formation's quiet model and weighted update, two-model filter and initiator's velocity support, its "
        "deletion by the radar's detection probability, correlation's caution with "
        "low-quality tracks and its swap rule, the published "
        "score's tracks' quality, the aid of association), *unaided*, the default with the aid "
        "of association by the other radars' confirmed partners off (`tracking.aid.enabled`, on "
        "by default; docs/architecture.md, tracks in formations), and *now*, the default "
        "configuration.  Spacing in cross-range "
        f"errors (1x = {unit:.0f} m: radar C's 0.20 deg at 115 km); Pd the catalog's (0.95/0.92/0.75) "
        "unless given; *in traffic*: the lattice among "
        f"{TRAFFIC_AIRCRAFT} more aircraft in two wide groups, of which only the formation's "
        "aircraft, their tracks and pairs are scored (plots to another aircraft: every track's).  "
        "Confirmed radar tracks sampled every "
        f"{SAMPLE_S:.0f} s from {WARMUP_S:.0f} s; pairs from {PAIR_WARMUP_S:.0f} s (shorter runs: "
        "a quarter and half of the run).  Pairs are judged by the aircraft of most of each "
        "track's plots (`truth_id`); *on two aircraft now* judges the same pairs by the aircraft "
        "each track is nearest at the sample: pairs that fuse two aircraft then (a diagnostic, "
        "not a goal).  Definitions: the module docstring of "
        "`topofusion_lab.evaluation.formation` (after Stone Soup's SIAP metrics).",
        "",
        "| point | tracker | completeness | ambiguity | duplicates | astray | spurious "
        "| plots to another aircraft (its own there) | ID switches / aircraft-h "
        "| position error m, mean (RMS) | quality | pairs correct | pairs false (worst seed) "
        "| pairs on two aircraft now (worst seed) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    summaries: dict[tuple[int, str], dict[str, float]] = {}
    for i, point in enumerate(points):
        for variant in VARIANTS:
            runs = by.get((i, variant), [])
            if not runs:
                continue
            s = summaries[(i, variant)] = summarize(runs)
            lines.append(
                f"| {point.label} ({point.spacing_x * unit:.0f} m) | {variant} "
                f"| {_f(100 * s['completeness'], '.1f')} % | {_f(s['ambiguity'], '.3f')} "
                f"| {_f(100 * s['duplicates'], '.2f')} % | {_f(100 * s['astray'], '.1f')} % "
                f"| {_f(100 * s['spuriousness'], '.2f')} % | {_f(100 * s['plots_other'], '.1f')} % "
                f"({_f(100 * s['plots_other_seen'], '.0f')} %) "
                f"| {_f(s['switches_per_h'], '.2f')} ({s['switches']:.0f}) "
                f"| {_f(s['position_mean_m'], '.0f')} ({_f(s['position_rms_m'], '.0f')}) "
                f"| {_f(s['quality'], '.3f')} | {_f(s['correct_pct'], '.1f')} % "
                f"| {_f(s['false_pct'], '.2f')} % ({_f(s['false_worst_pct'], '.2f')} %) "
                f"| {_f(s['two_now_pct'], '.2f')} % ({_f(s['two_now_worst_pct'], '.2f')} %) |"
            )
    if any(r.get("shared") for r in results):
        lines += [
            "",
            "_The configurations before and now are equal in this tree: each run gives both rows "
            "(the engine is deterministic)._",
        ]
    lines += ["", *reliability(points, summaries, unit)]
    lines += ["", *goals(points, by, summaries)]
    lines += [
        "",
        f"{len(results)} runs in {took:.0f} s ({workers} process(es)); the raw sums per run in "
        "`formation.json`.",
    ]
    return "\n".join(lines)


def reliability(
    points: Sequence[Point], summaries: Mapping[tuple[int, str], Mapping[str, float]], unit: float
) -> list[str]:
    """The reliability table: per point and configuration, the share of the judged confirmed
    pairs in each score bin that are right (and how many there are), and the Brier score."""
    edges = [f"{lo:g}-{hi:g}" for lo, hi in pairwise(SCORE_BINS)]
    rows = [
        "Pair scores through the whole pipeline (the published `score` of every judged confirmed "
        "pair at every pair sample): the share right in each score bin (pairs in it), and the "
        "Brier score, the mean of (score - right)^2.  A score means what it says when the share "
        "right lies within its bin.",
        "",
        "| point | tracker | " + " | ".join(f"score {e}" for e in edges) + " | Brier |",
        "|---|---|" + "---|" * (len(edges) + 1),
    ]
    for (i, variant), s in summaries.items():
        cells = [
            f"{_f(100 * s[f'score_right_{k}'], '.0f')} % ({s[f'score_n_{k}']:.0f})" for k in range(len(edges))
        ]
        label = f"{points[i].label} ({points[i].spacing_x * unit:.0f} m)"
        rows.append(f"| {label} | {variant} | " + " | ".join(cells) + f" | {_f(s['brier'], '.3f')} |")
    return rows


def goals(
    points: Sequence[Point],
    by: Mapping[tuple[int, str], Sequence[Mapping[str, Any]]],
    summaries: Mapping[tuple[int, str], Mapping[str, float]],
) -> list[str]:
    """The goal table (a column per configuration)."""
    lattice = [i for i, p in enumerate(points) if p.shape == "lattice"]
    wide = [i for i in lattice if points[i].spacing_x >= 2.0]
    rows = ["| goal | " + " | ".join(VARIANTS) + " |", "|---|" + "---|" * len(VARIANTS)]
    worst, correct, dups = [], [], []
    pooled: dict[str, dict[str, float]] = {}
    for variant in VARIANTS:
        w = [summaries[(i, variant)]["false_worst_pct"] for i in lattice if (i, variant) in summaries]
        worst.append(_nanmax(w))
        c = [summaries[(i, variant)]["correct_pct"] for i in wide if (i, variant) in summaries]
        correct.append(_nanmean(c))
        every = [r for i in range(len(points)) for r in by.get((i, variant), [])]
        pooled[variant] = summarize(every) if every else {}
        dups.append(pooled[variant].get("duplicates", math.nan))

    def mark(ok: bool) -> str:
        return "yes" if ok else "no"

    rows.append(
        f"| false pairs <= {GOAL_FALSE_PCT:.0f} % in every seed at every lattice spacing (worst) | "
        + " | ".join(f"{_f(x, '.2f')} % {mark(x <= GOAL_FALSE_PCT)}" for x in worst)
        + " |"
    )
    rows.append(
        f"| correct pairs >= {GOAL_CORRECT_PCT:.0f} % on average at spacing >= 2x (lattice points) | "
        + " | ".join(f"{_f(x, '.1f')} % {mark(x >= GOAL_CORRECT_PCT)}" for x in correct)
        + " |"
    )
    rows.append(
        f"| duplicate tracks <= {100 * GOAL_DUPLICATES:.0f} % (pooled over every point) | "
        + " | ".join(f"{_f(100 * x, '.2f')} % {mark(x <= GOAL_DUPLICATES)}" for x in dups)
        + " |"
    )
    before = pooled.get("before", {}).get("switches_per_h", math.nan)
    cells = [_f(before, ".2f")]
    for variant in VARIANTS[1:]:
        x = pooled.get(variant, {}).get("switches_per_h", math.nan)
        cells.append(f"{_f(x, '.2f')} {mark(x <= GOAL_SWITCH_RATIO * before if before > 0 else x == 0)}")
    rows.append(
        "| ID switches at least halved against before (pooled over every point, per aircraft-h) | "
        + " | ".join(cells)
        + " |"
    )
    return rows


# -- the study ----------------------------------------------------------------------------------------
def make_jobs(
    n: int,
    seed: int,
    points: Sequence[Point],
    duration_s: float | None,
    targets: int | None,
    variants: Sequence[str] = VARIANTS,
) -> list[Job]:
    return [
        Job(i, p, variant, r, seed + r + 1, duration_s, targets)
        for r in range(n)
        for i, p in enumerate(points)
        for variant in variants
    ]


def variants_equal() -> bool:
    """Whether the engine configurations before and now are the same (then one run, the engine
    being deterministic, gives both rows)."""
    return engine_config("before") == engine_config("now")


def run(
    out_dir: pathlib.Path,
    runs: int | None = None,
    seed: int = 0,
    progress: Callable[[str], None] = print,
    *,
    points: Sequence[Point] = POINTS,
    duration_s: float | None = None,
    targets: int | None = None,
    workers: int | None = None,
) -> str:
    """Run the study, write ``formation.json`` (every run's sums) into ``out_dir``, return the
    markdown section.  ``runs``: seeds per point (None: :data:`DEFAULT_RUNS`); ``points``,
    ``duration_s``, ``targets`` and ``workers`` (processes; None: up to 2) make small runs."""
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n = DEFAULT_RUNS if runs is None else max(int(runs), 1)
    same = variants_equal()
    variants = tuple(v for v in VARIANTS if not (same and v == "before"))
    jobs = make_jobs(n, seed, points, duration_s, targets, variants)
    workers = min(2, os.cpu_count() or 1) if workers is None else workers
    progress(
        f"formation: {len(jobs)} runs ({n} seeds x {len(points)} points x {len(variants)} trackers"
        f"{': before = now' if same else ''}), {workers} processes"
    )
    t0 = time.perf_counter()
    done = run_jobs(run_one, jobs, workers, progress, "formation")
    if same:
        done += [{**r, "variant": "before", "shared": True} for r in done if r["variant"] == "now"]
    results = sorted(done, key=lambda r: (r["index"], VARIANTS.index(r["variant"]), r["run"]))
    took = time.perf_counter() - t0
    (out_dir / "formation.json").write_text(
        json.dumps({"points": [asdict(p) for p in points], "runs": results}, indent=1) + "\n",
        encoding="utf-8",
    )
    return report(points, results, n, took, workers)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, help=f"seeds per point (default {DEFAULT_RUNS})")
    p.add_argument("--seed", type=int, default=0, help="seeds are seed+1 .. seed+runs (default 0)")
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("evaluation"), help="output folder")
    p.add_argument("--point", action="append", choices=[x.label for x in POINTS], help="only these points")
    p.add_argument("--duration", type=float, help="data seconds per run (default the scenario's 600)")
    p.add_argument("--targets", type=int, help="aircraft (default the scenario's 30)")
    p.add_argument("--workers", type=int, help="processes (default up to 2)")
    args = p.parse_args(argv)
    points = [x for x in POINTS if not args.point or x.label in args.point]

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    section = run(
        args.out,
        args.runs,
        args.seed,
        progress,
        points=points,
        duration_s=args.duration,
        targets=args.targets,
        workers=args.workers,
    )
    (args.out / "formation.md").write_text(section + "\n", encoding="utf-8")
    print(section)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
