"""Dense-formation study: correct and false confirmed pairs against spacing and track age.

Entry point :func:`run` (``topofusion evaluate --only dense``).  Each scene is three radars
around one formation of ``N`` aircraft (10-50) flying one heading and speed on a jittered
square lattice whose spacing is ``ratio`` times the *cross-range track error*.  Every radar
has unknown biases (azimuth 0.2-2 deg, range 50-500 m, elevation up to 0.1 deg, random
signs), its own azimuth noise (0.1-0.3 deg) and its own probability of detection (two radars
0.85-0.95, one 0.7-0.8).  The correlators never see the biases nor ``truth_id``.

Tracker output (as :mod:`.correlation_stream`, per radar and aircraft): the position error
is the radar's bias plus ``track_noise_factor`` times its measurement sigmas, correlated
from scan to scan (AR(1), ``noise_correlation``), reported with the matching covariance;
velocities are the biased picture's plus white noise.  A track is started by a detection,
confirmed at ``confirm_hits`` detections and reported as a row of the radar's
:class:`~service.tracking.base.TrackTable` from its first detection on.  A *missed
detection* leaves the row as it was (its ``time_s`` and state are those of the last
detection: the tracker coasts and the correlator extrapolates it); a tentative track is
deleted after ``drop_tentative_misses`` consecutive misses, a confirmed one after
``drop_confirmed_misses``, and the aircraft is then re-acquired under a new track id.

The cross-range track error of a radar is ``range x track_noise_factor x azimuth sigma``
at the formation's mid-run position; the scene's error is the largest of the three radars'
(the spacing ratio is therefore the one the noisiest radar sees; the other two see more).

Methods on the same tables: ``svd-topology``, ``gmm`` and ``nearest`` through
:class:`service.correlation.PairCorrelator` (one per radar pair, all three pairs updated at
the end of every scan by :func:`update_scan`), and Stone Soup's ``TrackToTrackCounting``
at a few distance thresholds (:func:`stonesoup_pairs`).

Scoring (evaluation only, by ``truth_id``), per radar pair and scan:

* *common aircraft*: aircraft with a confirmed track in both radars' tables;
* *correct rate* = correct confirmed pairs / common aircraft;
* *false rate* = false confirmed pairs / confirmed pairs;
* *age* of a common aircraft or of a confirmed pair: data time since both of its tracks
  were first reported confirmed.

Rates pool numerators and denominators over scans, radar pairs and scenes.
"""

from __future__ import annotations

import datetime
import math
import os
import pathlib
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from service.correlation import CorrelationParams, PairCorrelator
from service.correlation.cycles import implied_for
from service.geo import Site, ecef_to_geodetic, polar_to_enu
from service.tracking.base import TrackTable
from topofusion_lab.evaluation.correlation_scenario import SITE_LAT_DEG, SITE_LON_DEG

#: Spacing / cross-range track error of the scenes (the x axis).
RATIOS = (0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)
#: Formation sizes; scene ``s`` of a ratio has ``SIZES[s % 3]`` aircraft (``--runs 1``: 30).
SIZES = (30, 50, 10)
#: Scenes per ratio by default (two of each size).
DEFAULT_RUNS = 6
#: ``svd-topology`` as it was before the history evidence: every update decides alone (and no
#: cycle step), to show what the evidence adds on the same tables.
SINGLE_UPDATES = "svd-topology, single updates"
METHODS = ("svd-topology", SINGLE_UPDATES, "gmm", "nearest")


def correlator_of(label: str, site_a: Site, site_b: Site) -> PairCorrelator:
    """The correlator a row of the study stands for."""
    if label == SINGLE_UPDATES:
        base = CorrelationParams()
        params = replace(
            base,
            evidence=replace(base.evidence, enabled=False),
            cycles=replace(base.cycles, enabled=False),
        )
        return PairCorrelator("svd-topology", site_a, site_b, params)
    return PairCorrelator(label, site_a, site_b)


#: Stone Soup ``TrackToTrackCounting`` association thresholds (horizontal distance, m).
STONESOUP_THRESHOLDS_M = (1_000.0, 3_000.0, 10_000.0)
#: The must-show regime: spacing at least this many cross-range track errors.
GOAL_RATIO = 1.5
GOAL_CORRECT = 0.95
GOAL_FALSE = 0.03
#: Common aircraft and pairs younger than this are left out of the spacing table (the age
#: figure shows them).
SETTLED_AGE_S = 60.0
AGE_BIN_S = 20.0


def stonesoup_label(threshold_m: float, one_to_one: bool = True) -> str:
    return f"stonesoup {threshold_m / 1e3:g} km" + ("" if one_to_one else " (as is)")


def labels() -> list[str]:
    """The rows of the study: the correlators, then Stone Soup per threshold."""
    return [*METHODS, *(stonesoup_label(t) for t in STONESOUP_THRESHOLDS_M)]


# -- scene -------------------------------------------------------------------------------


@dataclass(frozen=True)
class DenseScene:
    """What a scene is made of; the random draws come from ``seed``."""

    aircraft: int
    ratio: float
    seed: tuple[int, ...]
    scans: int = 40
    scan_period_s: float = 10.0
    track_noise_factor: float = 0.6
    noise_correlation: float = 0.8
    velocity_sigma_mps: float = 6.0
    range_sigma_m: float = 100.0
    confirm_hits: int = 3
    drop_tentative_misses: int = 2
    drop_confirmed_misses: int = 4
    #: Lattice jitter, uniform +- this fraction of the spacing on each horizontal axis.
    jitter: float = 0.25
    altitude_m: float = 9_000.0
    #: Multiplies the drawn biases (0: unbiased radars, for checks).
    bias_scale: float = 1.0


@dataclass(frozen=True)
class RadarSetup:
    site: Site
    range_bias_m: float
    azimuth_bias_deg: float
    elevation_bias_deg: float
    pd: float
    #: Horizontal distance to the formation's mid-run centre (m).
    range_m: float

    @property
    def cross_range_m(self) -> float:
        """Cross-range track error without the noise factor (range x azimuth sigma)."""
        return self.range_m * math.radians(self.site.azimuth_sigma_deg)


@dataclass(frozen=True)
class SceneSetup:
    """The drawn scene: radars, the formation's frame and spacing."""

    scene: DenseScene
    centre: Site
    radars: tuple[RadarSetup, ...]
    cross_range_m: float
    spacing_m: float
    #: Initial ENU positions (formation-centre frame) and the common velocity.
    position0: np.ndarray
    velocity: np.ndarray


def draw_scene(scene: DenseScene) -> SceneSetup:
    """Radars, biases, Pd, noise and the formation of one scene (seeded)."""
    rng = np.random.default_rng(np.random.SeedSequence(list(scene.seed)))
    centre = Site("O", SITE_LAT_DEG, SITE_LON_DEG, 0.0)
    bearing0 = rng.uniform(0.0, 360.0)
    low_pd = int(rng.integers(3))
    radars = []
    for i, name in enumerate("ABC"):
        bearing = np.radians(bearing0 + 120.0 * i + rng.uniform(-20.0, 20.0))
        dist = rng.uniform(100_000.0, 180_000.0)
        lat, lon, _ = ecef_to_geodetic(
            centre.enu_to_ecef(np.array([dist * np.sin(bearing), dist * np.cos(bearing), 0.0]))
        )
        az_sigma = rng.uniform(0.1, 0.3)
        site = Site(
            name,
            float(lat),
            float(lon),
            50.0,
            scene.range_sigma_m,
            az_sigma,
            az_sigma,
            scene.scan_period_s,
        )
        sign = rng.choice([-1.0, 1.0], size=3)
        radars.append(
            RadarSetup(
                site=site,
                range_bias_m=scene.bias_scale * float(sign[0] * rng.uniform(50.0, 500.0)),
                azimuth_bias_deg=scene.bias_scale * float(sign[1] * rng.uniform(0.2, 2.0)),
                elevation_bias_deg=scene.bias_scale * float(rng.uniform(-0.1, 0.1)),
                pd=float(rng.uniform(0.7, 0.8) if i == low_pd else rng.uniform(0.85, 0.95)),
                range_m=float(dist),
            )
        )
    cross = scene.track_noise_factor * max(r.cross_range_m for r in radars)
    spacing = scene.ratio * cross
    n = scene.aircraft
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    grid = np.array([(c - (cols - 1) / 2, r - (rows - 1) / 2) for r in range(rows) for c in range(cols)])[:n]
    grid = grid + rng.uniform(-scene.jitter, scene.jitter, grid.shape)
    heading = rng.uniform(0.0, 2 * np.pi)
    speed = rng.uniform(180.0, 250.0)
    # Lattice columns across the track, rows along it.
    along = np.array([np.sin(heading), np.cos(heading)])
    across = np.array([np.cos(heading), -np.sin(heading)])
    xy = spacing * (grid[:, :1] * across + grid[:, 1:] * along)
    velocity = np.array([speed * along[0], speed * along[1], 0.0])
    mid = scene.scans * scene.scan_period_s / 2
    pos = np.column_stack([xy, scene.altitude_m + rng.uniform(-30.0, 30.0, n)]) - velocity * mid
    return SceneSetup(scene, centre, tuple(radars), cross, spacing, pos, velocity)


class RadarTracker:
    """One radar's tracker output over the formation (see the module docstring)."""

    def __init__(self, rng: np.random.Generator, setup: SceneSetup, radar: RadarSetup) -> None:
        self.rng = rng
        self.setup = setup
        self.radar = radar
        n = setup.position0.shape[0]
        self.eta = rng.normal(size=(n, 3))
        self.track_no = np.full(n, -1)
        self.hits = np.zeros(n, dtype=np.int64)
        self.misses = np.zeros(n, dtype=np.int64)
        self.confirmed = np.zeros(n, dtype=bool)
        self.time_s = np.zeros(n)
        self.pos = np.zeros((n, 3))
        self.vel = np.zeros((n, 3))
        self.cov = np.zeros((n, 6, 6))
        self.next_no = int(rng.integers(100, 1000))

    def scan(self, scan_start: float) -> TrackTable:
        sc, site, rd = self.setup.scene, self.radar.site, self.radar
        centre = self.setup.centre
        rho = sc.noise_correlation
        self.eta = rho * self.eta + np.sqrt(1 - rho**2) * self.rng.normal(size=self.eta.shape)
        pos0, vel = self.setup.position0, self.setup.velocity
        # Time of each aircraft inside the scan from its azimuth at the scan start.
        _, az0, _ = site.ecef_to_polar(centre.enu_to_ecef(pos0 + vel * scan_start))
        t = scan_start + az0 / 360.0 * sc.scan_period_s
        r, az, el = site.ecef_to_polar(centre.enu_to_ecef(pos0 + vel * t[:, None]))
        k = sc.track_noise_factor
        rm = r + rd.range_bias_m + k * site.range_sigma_m * self.eta[:, 0]
        azm = az + rd.azimuth_bias_deg + k * site.azimuth_sigma_deg * self.eta[:, 1]
        elm = el + rd.elevation_bias_deg + k * site.elevation_sigma_deg * self.eta[:, 2]
        pos = site.enu_to_ecef(polar_to_enu(rm, azm, elm))
        cov_enu = site.measurement_covariance_enu(rm, azm, elm) * k**2
        # Velocity as the biased radar sees it: true ENU velocity rotated by the azimuth bias.
        v_enu = (centre.rotation @ vel) @ site.rotation
        d = np.radians(rd.azimuth_bias_deg)
        c, s = np.cos(d), np.sin(d)
        v_b = np.array([v_enu[0] * c + v_enu[1] * s, -v_enu[0] * s + v_enu[1] * c, v_enu[2]])
        n = len(r)
        v_b = v_b + self.rng.normal(0.0, sc.velocity_sigma_mps, (n, 3)) * np.array([1.0, 1.0, 0.5])
        cov = np.zeros((n, 6, 6))
        cov[:, :3, :3] = site.rotation @ cov_enu @ site.rotation.T
        cov[:, 3:, 3:] = np.diag(np.array([1.0, 1.0, 0.25]) * sc.velocity_sigma_mps**2)

        detected = self.rng.uniform(size=n) < rd.pd
        # Misses: coast (row unchanged) or delete.
        live = self.track_no >= 0
        missed = live & ~detected
        self.misses[missed] += 1
        limit = np.where(self.confirmed, sc.drop_confirmed_misses, sc.drop_tentative_misses)
        gone = missed & (self.misses >= limit)
        self.track_no[gone] = -1
        self.hits[gone] = 0
        self.confirmed[gone] = False
        # New tracks, numbered in random order (an id says nothing about the aircraft).
        new = np.flatnonzero(detected & (self.track_no < 0))
        new = new[self.rng.permutation(len(new))]
        self.track_no[new] = self.next_no + np.arange(len(new))
        self.next_no += len(new)
        self.hits[detected] += 1
        self.misses[detected] = 0
        self.confirmed |= self.hits >= sc.confirm_hits
        self.time_s[detected] = t[detected]
        self.pos[detected] = pos[detected]
        self.vel[detected] = (v_b @ site.rotation.T)[detected]
        self.cov[detected] = cov[detected]
        keep = np.flatnonzero(self.track_no >= 0)
        return TrackTable(
            track_id=np.array([f"{site.site_id}{no}" for no in self.track_no[keep]]),
            confirmed=self.confirmed[keep].copy(),
            time_s=self.time_s[keep].copy(),
            position_ecef_m=self.pos[keep].copy(),
            velocity_ecef_mps=self.vel[keep].copy(),
            covariance=self.cov[keep].copy(),
            plots=self.hits[keep].copy(),
            truth_id=np.array([f"T{i}" for i in keep], dtype=object),
        )


def simulate(setup: SceneSetup) -> list[tuple[dict[str, TrackTable], float]]:
    """Every scan's tables (radar id -> table) and the update time (end of the scan)."""
    sc = setup.scene
    rng = np.random.default_rng(np.random.SeedSequence([*sc.seed, 1]))
    trackers = [RadarTracker(rng, setup, r) for r in setup.radars]
    out = []
    for k in range(sc.scans):
        t0 = k * sc.scan_period_s
        tables = {tr.radar.site.site_id: tr.scan(t0) for tr in trackers}
        out.append((tables, t0 + sc.scan_period_s))
    return out


# -- correlation -------------------------------------------------------------------------

PairKey = tuple[str, str]


def update_scan(
    correlators: Mapping[PairKey, PairCorrelator], tables: Mapping[str, TrackTable], time_s: float
) -> None:
    """One scan's correlation: every radar pair's correlator updated with the two tables, in
    the order the correlation stage would, each with the pairs the other two pairs of its
    triangles imply as the books are now (the cycle step of :mod:`service.correlation.cycles`;
    the service takes the books of a recent point of a data-time grid instead,
    :mod:`service.pipeline.cycle_links`, a scan-by-scan study has no finer time)."""
    for (a, b), corr in correlators.items():
        cycles = corr.params.cycles
        implied = implied_for((a, b), correlators, cycles.min_strength) if cycles.enabled else None
        corr.update(tables[a], tables[b], time_s, implied)


# -- scoring -----------------------------------------------------------------------------


@dataclass
class Records:
    """Raw scoring records of one method, pooled later (one entry per item and scan)."""

    #: Spacing ratio and age (s) of each common aircraft.
    common_ratio: list[float] = field(default_factory=list)
    common_age: list[float] = field(default_factory=list)
    #: Spacing ratio, age (s) and truth of each confirmed pair.
    pair_ratio: list[float] = field(default_factory=list)
    pair_age: list[float] = field(default_factory=list)
    pair_ok: list[bool] = field(default_factory=list)
    #: Score and truth of every published pair (tentative and confirmed).
    score: list[float] = field(default_factory=list)
    score_ok: list[bool] = field(default_factory=list)

    def extend(self, other: Records) -> None:
        for name in self.__dataclass_fields__:
            getattr(self, name).extend(getattr(other, name))


class Scorer:
    """Turns pairs of track ids into common/correct/false records by ``truth_id``."""

    def __init__(self, ratio: float) -> None:
        self.ratio = ratio
        #: (radar, track id) -> time the track was first reported confirmed.
        self.confirmed_since: dict[tuple[str, str], float] = {}

    def see(self, tables: Mapping[str, TrackTable], time_s: float) -> None:
        """Note the tracks first reported confirmed at ``time_s``."""
        for radar, table in tables.items():
            for tid, conf in zip(table.track_id, table.confirmed, strict=True):
                if conf:
                    self.confirmed_since.setdefault((radar, str(tid)), time_s)

    def score(
        self,
        rec: Records,
        radars: PairKey,
        tables: Mapping[str, TrackTable],
        time_s: float,
        confirmed: Iterable[tuple[str, str]],
        published: Iterable[tuple[str, str, float]] = (),
    ) -> None:
        """Records of one radar pair at one scan: its common aircraft, confirmed pairs and
        the scores of its published pairs (``(track_a, track_b, score)``)."""
        ra, rb = radars
        ta, tb = tables[ra], tables[rb]
        truth_a = {str(i): str(t) for i, t in zip(ta.track_id, ta.truth_id, strict=True)}
        truth_b = {str(i): str(t) for i, t in zip(tb.track_id, tb.truth_id, strict=True)}
        conf_a = {str(t): str(i) for i, t, c in zip(ta.track_id, ta.truth_id, ta.confirmed, strict=True) if c}
        conf_b = {str(t): str(i) for i, t, c in zip(tb.track_id, tb.truth_id, tb.confirmed, strict=True) if c}
        for truth in conf_a.keys() & conf_b.keys():
            rec.common_ratio.append(self.ratio)
            rec.common_age.append(self._age(ra, conf_a[truth], rb, conf_b[truth], time_s))
        for a, b in confirmed:
            rec.pair_ratio.append(self.ratio)
            rec.pair_age.append(self._age(ra, a, rb, b, time_s))
            rec.pair_ok.append(a in truth_a and truth_a[a] == truth_b.get(b))
        for a, b, s in published:
            rec.score.append(s)
            rec.score_ok.append(a in truth_a and truth_a[a] == truth_b.get(b))

    def _age(self, ra: str, a: str, rb: str, b: str, time_s: float) -> float:
        since = max(self.confirmed_since.get((ra, a), time_s), self.confirmed_since.get((rb, b), time_s))
        return time_s - since


def rates(
    rec: Records,
    ratio_min: float = -np.inf,
    ratio_max: float = np.inf,
    age_min: float = -np.inf,
    age_max: float = np.inf,
) -> tuple[float, float, int, int]:
    """(correct rate, false rate, common aircraft, confirmed pairs) of the records with the
    spacing ratio in ``[ratio_min, ratio_max]`` and the age in ``[age_min, age_max)``."""
    cr, ca = np.asarray(rec.common_ratio), np.asarray(rec.common_age)
    pr, pa, ok = np.asarray(rec.pair_ratio), np.asarray(rec.pair_age), np.asarray(rec.pair_ok, dtype=bool)
    cm = (cr >= ratio_min) & (cr <= ratio_max) & (ca >= age_min) & (ca < age_max)
    pm = (pr >= ratio_min) & (pr <= ratio_max) & (pa >= age_min) & (pa < age_max)
    common, conf = int(cm.sum()), int(pm.sum())
    correct = int((ok & pm).sum())
    false = conf - correct
    return (
        correct / common if common else float("nan"),
        false / conf if conf else float("nan"),
        common,
        conf,
    )


def brier(rec: Records) -> float:
    s, ok = np.asarray(rec.score), np.asarray(rec.score_ok, dtype=float)
    return float(np.mean((s - ok) ** 2)) if len(s) else float("nan")


def fit_calibration(rec: Records, slope: float, offset: float) -> tuple[float, float]:
    """The logistic calibration (``EvidenceParams.calibration_slope`` / ``_offset``) that makes
    ``rec``'s scores, produced with ``slope`` and ``offset``, fit their outcomes best (maximum
    likelihood, Newton's method on the two parameters over the uncalibrated log-odds)."""
    s = np.clip(np.asarray(rec.score, dtype=float), 1e-9, 1 - 1e-9)
    y = np.asarray(rec.score_ok, dtype=float)
    raw = (np.log(s / (1 - s)) - offset) / slope
    x = np.column_stack([raw, np.ones_like(raw)])
    beta = np.array([1.0, 0.0])
    for _ in range(50):
        p = 1 / (1 + np.exp(-(x @ beta)))
        grad = x.T @ (y - p)
        hess = (x * (p * (1 - p))[:, None]).T @ x + 1e-6 * np.eye(2)
        step = np.linalg.solve(hess, grad)
        step *= min(1.0, 1.0 / max(float(np.abs(step).max()), 1e-12))  # damped: no overshoot
        beta = beta + step
        if np.abs(step).max() < 1e-10:
            break
    return float(beta[0]), float(beta[1])


def reliability(rec: Records, bins: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per score bin: mean score, fraction correct, count (NaN where empty)."""
    s, ok = np.asarray(rec.score), np.asarray(rec.score_ok, dtype=float)
    idx = np.clip((s * bins).astype(int), 0, bins - 1) if len(s) else np.zeros(0, dtype=int)
    count = np.bincount(idx, minlength=bins).astype(float)
    with np.errstate(invalid="ignore"):
        mean_s = np.bincount(idx, weights=s, minlength=bins) / count
        frac = np.bincount(idx, weights=ok, minlength=bins) / count
    return mean_s, frac, count


# -- Stone Soup ----------------------------------------------------------------------------

_EPOCH = datetime.datetime(2020, 1, 1)


def _scan_states(
    frames: Sequence[tuple[Mapping[str, TrackTable], float]], radar: str, centre: Site
) -> dict[str, dict[int, np.ndarray]]:
    """Per confirmed track: scan index -> [x, vx, y, vy] in the formation centre's ENU at the
    update time (the row extrapolated at constant velocity, as the correlators do)."""
    out: dict[str, dict[int, np.ndarray]] = {}
    for k, (tables, t) in enumerate(frames):
        tab = tables[radar]
        rows = np.flatnonzero(tab.confirmed)
        if not len(rows):
            continue
        dt = t - tab.time_s[rows]
        enu = centre.ecef_to_enu(tab.position_ecef_m[rows] + tab.velocity_ecef_mps[rows] * dt[:, None])
        v = tab.velocity_ecef_mps[rows] @ centre.rotation
        for j, r in enumerate(rows):
            out.setdefault(str(tab.track_id[r]), {})[k] = np.array([enu[j, 0], v[j, 0], enu[j, 1], v[j, 1]])
    return out


def stonesoup_pairs(
    frames: Sequence[tuple[Mapping[str, TrackTable], float]],
    radars: PairKey,
    centre: Site,
    threshold_m: float,
    consec_pairs_confirm: int = 3,
    consec_misses_end: int = 2,
) -> tuple[list[list[tuple[str, str]]], list[list[tuple[str, str]]]]:
    """Stone Soup's ``TrackToTrackCounting`` on the two radars' confirmed tracks.

    Each track is a Stone Soup ``Track`` of ``State([x, vx, y, vy])`` at the scans' update
    times (so both radars' states share timestamps, which the counting technique needs);
    the measure is the horizontal Euclidean distance.  The associator is run once on the
    whole stream; an association ``[start, end]`` becomes *confirmed* at the scan where its
    ``consec_pairs_confirm``-th consecutive hit arrived and stays confirmed until the scan
    of its ``consec_misses_end``-th consecutive miss (the scans at which the technique
    itself could have said so: nothing from the future).  Pairs never within the threshold
    at ``consec_pairs_confirm`` common scans cannot associate and are not passed to it
    (only time is saved).

    Returns per scan the confirmed pairs *as is* (a track may be in several) and
    *one-to-one*: the pairs a per-scan assignment keeps that maximises the time each
    association has lasted so far (the causal form of Stone Soup's ``one_to_one``
    deconfliction, which maximises whole association durations).
    """
    from stonesoup.dataassociator.tracktotrack import TrackToTrackCounting
    from stonesoup.measures import Euclidean
    from stonesoup.types.state import State
    from stonesoup.types.track import Track

    ra, rb = radars
    scans = len(frames)
    sa = _scan_states(frames, ra, centre)
    sb = _scan_states(frames, rb, centre)

    def to_track(tid: str, states: dict[int, np.ndarray]) -> Any:
        return Track(
            [
                State(x.reshape(4, 1), timestamp=_EPOCH + datetime.timedelta(seconds=float(frames[k][1])))
                for k, x in sorted(states.items())
            ],
            id=tid,
        )

    # Gate with numpy: scans within the threshold per pair.
    ids_a, ids_b = list(sa), list(sb)
    xa = np.full((len(ids_a), scans, 2), np.nan)
    xb = np.full((len(ids_b), scans, 2), np.nan)
    for i, tid in enumerate(ids_a):
        for k, x in sa[tid].items():
            xa[i, k] = x[[0, 2]]
    for j, tid in enumerate(ids_b):
        for k, x in sb[tid].items():
            xb[j, k] = x[[0, 2]]
    tracks_a = {tid: to_track(tid, sa[tid]) for tid in ids_a}
    assoc = TrackToTrackCounting(
        association_threshold=threshold_m,
        consec_pairs_confirm=consec_pairs_confirm,
        consec_misses_end=consec_misses_end,
        measure=Euclidean(mapping=[0, 2]),
        pos_map=[0, 2],
    )
    # (a, b) -> scans at which the pair is confirmed, with the scan its association started.
    active: list[list[tuple[str, str, int]]] = [[] for _ in range(scans)]
    for j, tid_b in enumerate(ids_b):
        if not len(ids_a):
            break
        with np.errstate(invalid="ignore"):
            near = np.linalg.norm(xa - xb[j][None], axis=2) <= threshold_m  # (na, scans)
        cands = np.flatnonzero(near.sum(axis=1) >= consec_pairs_confirm)
        if not len(cands):
            continue
        track_b = to_track(tid_b, sb[tid_b])
        result = assoc.associate_tracks({tracks_a[ids_a[i]] for i in cands}, {track_b})
        for association in result.associations:
            t_a, _ = association.objects
            common = sorted(set(sa[t_a.id]) & set(sb[tid_b]))
            times = [_EPOCH + datetime.timedelta(seconds=float(frames[k][1])) for k in common]
            # One pair's successive associations come merged into a compound time range.
            tr = association.time_range
            for part in getattr(tr, "time_ranges", [tr]):
                i_start = times.index(part.start_timestamp)
                i_end = times.index(part.end_timestamp)
                first = common[i_start + consec_pairs_confirm - 1]
                # Open at the end of the common stretch, or ended by misses (i_end: the first).
                open_end = i_end == len(common) - 1
                last = common[-1] if open_end else common[i_end + consec_misses_end - 1] - 1
                for k in range(first, last + 1):
                    active[k].append((str(t_a.id), tid_b, common[i_start]))
    as_is = [[(a, b) for a, b, _ in act] for act in active]
    one: list[list[tuple[str, str]]] = []
    for k, act in enumerate(active):
        if not act:
            one.append([])
            continue
        ua = sorted({a for a, _, _ in act})
        ub = sorted({b for _, b, _ in act})
        dur = np.zeros((len(ua), len(ub)))
        for a, b, start in act:
            dur[ua.index(a), ub.index(b)] = k - start + 1
        ri, ci = linear_sum_assignment(dur, maximize=True)
        one.append([(ua[i], ub[j]) for i, j in zip(ri, ci, strict=True) if dur[i, j] > 0])
    return as_is, one


# -- one scene ---------------------------------------------------------------------------


@dataclass
class SceneResult:
    ratio: float
    aircraft: int
    cross_range_m: float
    spacing_m: float
    records: dict[str, Records]
    ms_per_update: dict[str, float]
    seconds: float
    #: Per radar pair: horizontal distance between the two radars' biased pictures of the
    #: formation centre at mid-run (what absolute-position association must bridge).
    bias_displacement_m: np.ndarray


def bias_displacements(setup: SceneSetup) -> np.ndarray:
    """Per radar pair: horizontal distance (m) between where the two radars' biases put the
    formation centre at mid-run (noise-free)."""
    centre = setup.centre.enu_to_ecef(np.array([0.0, 0.0, setup.scene.altitude_m]))
    seen = []
    for r in setup.radars:
        rng, az, el = r.site.ecef_to_polar(centre)
        biased = polar_to_enu(rng + r.range_bias_m, az + r.azimuth_bias_deg, el + r.elevation_bias_deg)
        seen.append(setup.centre.ecef_to_enu(r.site.enu_to_ecef(biased))[:2])
    n = len(seen)
    return np.array([np.hypot(*(seen[i] - seen[j])) for i in range(n) for j in range(i + 1, n)])


def radar_pairs(radars: Sequence[str]) -> list[PairKey]:
    return [(a, b) for i, a in enumerate(radars) for b in radars[i + 1 :]]


def run_scene(scene: DenseScene, thresholds: Sequence[float] = STONESOUP_THRESHOLDS_M) -> SceneResult:
    """All methods on one scene's tables."""
    t_start = time.perf_counter()
    setup = draw_scene(scene)
    frames = simulate(setup)
    sites = {r.site.site_id: r.site for r in setup.radars}
    keys = radar_pairs(list(sites))
    records: dict[str, Records] = {}
    ms: dict[str, float] = {}
    for method in METHODS:
        rec = Records()
        scorer = Scorer(scene.ratio)
        correlators = {(a, b): correlator_of(method, sites[a], sites[b]) for a, b in keys}
        spent = 0.0
        for tables, t in frames:
            scorer.see(tables, t)
            t0 = time.perf_counter()
            update_scan(correlators, tables, t)
            spent += time.perf_counter() - t0
            for key, corr in correlators.items():
                ps = corr.pairs()
                scorer.score(
                    rec,
                    key,
                    tables,
                    t,
                    [(p.track_a, p.track_b) for p in ps if p.status == "confirmed"],
                    [(p.track_a, p.track_b, p.score) for p in ps],
                )
        records[method] = rec
        ms[method] = 1e3 * spent / (len(frames) * len(keys))
    for thr in thresholds:
        rec_one, rec_all = Records(), Records()
        scorer = Scorer(scene.ratio)
        per_pair = {key: stonesoup_pairs(frames, key, setup.centre, thr) for key in keys}
        for k, (tables, t) in enumerate(frames):
            scorer.see(tables, t)
            for key, (as_is, one) in per_pair.items():
                scorer.score(rec_one, key, tables, t, one[k])
                scorer.score(rec_all, key, tables, t, as_is[k])
        records[stonesoup_label(thr)] = rec_one
        records[stonesoup_label(thr, one_to_one=False)] = rec_all
    return SceneResult(
        scene.ratio,
        scene.aircraft,
        setup.cross_range_m,
        setup.spacing_m,
        records,
        ms,
        time.perf_counter() - t_start,
        bias_displacements(setup),
    )


def make_scenes(runs: int, seed: int, ratios: Sequence[float] = RATIOS, scans: int = 40) -> list[DenseScene]:
    sizes = SIZES
    return [
        DenseScene(aircraft=sizes[s % len(sizes)], ratio=ratio, seed=(seed, i, s), scans=scans)
        for s in range(runs)
        for i, ratio in enumerate(ratios)
    ]


# -- figures and report ------------------------------------------------------------------


def goal_from(rows: Sequence[tuple[float, float, int, int]], ratios: Sequence[float]) -> str:
    """The smallest ratio from which every row (correct, false, ...) meets the goal, as text."""
    ok = [c >= GOAL_CORRECT and f <= GOAL_FALSE for c, f, _, _ in rows]
    k = len(ok)
    while k > 0 and ok[k - 1]:
        k -= 1
    return f"{ratios[k]:g}" if k < len(ok) else f"not met up to {ratios[-1]:g}"


def _pct(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.1f}"


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


_STYLE = {"svd-topology": "C0", "gmm": "C1", "nearest": "C2", SINGLE_UPDATES: "C7"}


def _style(label: str) -> dict[str, Any]:
    if label in _STYLE:
        return {"color": _STYLE[label], "marker": "o", "lw": 2.0}
    k = next((i for i, t in enumerate(STONESOUP_THRESHOLDS_M) if label == stonesoup_label(t)), 0)
    return {"color": f"C{3 + k}", "marker": "s", "ls": "--", "lw": 1.2}


def plot_vs_spacing(
    path: pathlib.Path, ratios: Sequence[float], table: dict[str, list[tuple[float, float]]]
) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 4.2))
    for lab, vals in table.items():
        axes[0].plot(ratios, [100 * c for c, _ in vals], ms=4, label=lab, **_style(lab))
        axes[1].plot(ratios, [100 * f for _, f in vals], ms=4, label=lab, **_style(lab))
    axes[0].axhline(100 * GOAL_CORRECT, color="k", lw=0.8, ls=":")
    axes[1].axhline(100 * GOAL_FALSE, color="k", lw=0.8, ls=":")
    for ax, yl in zip(
        axes, ("correct confirmed / common aircraft (%)", "false confirmed / confirmed (%)"), strict=True
    ):
        ax.axvline(GOAL_RATIO, color="k", lw=0.8, ls=":")
        ax.set_xscale("log")
        ax.minorticks_off()
        ax.set_xticks(list(ratios), [f"{r:g}" for r in ratios])
        ax.set_xlabel("spacing / cross-range track error")
        ax.set_ylabel(yl)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(
        f"Dense formations, three radars, unknown biases (ages >= {SETTLED_AGE_S:.0f} s)", fontsize=10
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_vs_age(path: pathlib.Path, records: dict[str, Records], max_age_s: float) -> None:
    plt = _plt()
    edges = np.arange(0.0, max_age_s + AGE_BIN_S, AGE_BIN_S)
    mids = edges[:-1] + AGE_BIN_S / 2
    fig, axes = plt.subplots(2, 2, figsize=(10.5, 7.0), sharex=True)
    for col, (lo, hi, name) in enumerate(((0.0, GOAL_RATIO - 1e-9, "< "), (GOAL_RATIO, np.inf, ">= "))):
        for lab in labels():
            rs = [rates(records[lab], lo, hi, a, a + AGE_BIN_S) for a in edges[:-1]]
            axes[0, col].plot(mids, [100 * r[0] for r in rs], ms=3, label=lab, **_style(lab))
            axes[1, col].plot(mids, [100 * r[1] for r in rs], ms=3, label=lab, **_style(lab))
        axes[0, col].set_title(f"spacing ratio {name}{GOAL_RATIO:g}", fontsize=10)
        axes[0, col].axhline(100 * GOAL_CORRECT, color="k", lw=0.8, ls=":")
        axes[1, col].axhline(100 * GOAL_FALSE, color="k", lw=0.8, ls=":")
        axes[1, col].set_xlabel("time since both tracks confirmed (s)")
        axes[0, col].set_ylabel("correct confirmed / common (%)")
        axes[1, col].set_ylabel("false confirmed / confirmed (%)")
        for ax in axes[:, col]:
            ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_reliability(path: pathlib.Path, records: dict[str, Records]) -> None:
    plt = _plt()
    fig, (ax, axh) = plt.subplots(
        2, 1, figsize=(5.6, 6.4), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    ax.plot([0, 1], [0, 1], color="k", lw=0.8, ls=":", label="perfect calibration")
    width = 0.1 / (len(METHODS) + 1)
    for k, m in enumerate(METHODS):
        mean_s, frac, count = reliability(records[m])
        seen = count > 0
        ax.plot(mean_s[seen], frac[seen], label=f"{m} (Brier {brier(records[m]):.3f})", **_style(m))
        axh.bar(np.arange(10) / 10 + (k + 0.5) * width, count, width=width, color=_STYLE[m])
    ax.set_ylabel("fraction of pairs right")
    ax.set_title("Reliability of `score`, all published pairs (10 bins)", fontsize=10)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="center right")
    axh.set_yscale("log")
    axh.set_xlabel("score")
    axh.set_ylabel("pairs")
    axh.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _run_all(scenes: list[DenseScene], workers: int, progress: Callable[[str], None]) -> list[SceneResult]:
    t0 = time.perf_counter()
    if workers <= 1 or len(scenes) <= 1:
        out = []
        for k, sc in enumerate(scenes):
            out.append(run_scene(sc))
            progress(f"  dense: scene {k + 1}/{len(scenes)} [{time.perf_counter() - t0:.0f} s]")
        return out
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(run_scene, sc) for sc in scenes]
        out = []
        for k, fut in enumerate(futures):
            out.append(fut.result())
            progress(f"  dense: scene {k + 1}/{len(scenes)} [{time.perf_counter() - t0:.0f} s]")
        return out


def run(
    out_dir: pathlib.Path,
    runs: int | None = None,
    seed: int = 0,
    progress: Callable[[str], None] = print,
    *,
    ratios: Sequence[float] = RATIOS,
    scans: int = 40,
    workers: int | None = None,
) -> str:
    """Run the study, write ``dense_*.png`` into ``out_dir``, return the markdown section.

    ``runs``: scenes per spacing ratio (None: 6, two formations of each size).  ``ratios``,
    ``scans`` and ``workers`` (processes; None: up to 2) make small runs for tests.
    """
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n = DEFAULT_RUNS if runs is None else max(int(runs), 1)
    t_start = time.perf_counter()
    scenes = make_scenes(n, seed, ratios, scans)
    workers = min(2, os.cpu_count() or 1) if workers is None else workers
    progress(f"dense: {len(scenes)} scenes ({n} per spacing ratio, {scans} scans), {workers} processes")
    results = _run_all(scenes, workers, progress)

    all_labels = [*labels(), *(stonesoup_label(t, one_to_one=False) for t in STONESOUP_THRESHOLDS_M)]
    pooled = {lab: Records() for lab in all_labels}
    for res in results:
        for lab in all_labels:
            pooled[lab].extend(res.records[lab])
    by_ratio: dict[str, list[tuple[float, float, int, int]]] = {
        lab: [rates(pooled[lab], r, r, SETTLED_AGE_S) for r in ratios] for lab in all_labels
    }
    plot_vs_spacing(
        out_dir / "dense_vs_spacing.png",
        list(ratios),
        {lab: [(c, f) for c, f, _, _ in by_ratio[lab]] for lab in labels()},
    )
    max_age = scans * scenes[0].scan_period_s
    plot_vs_age(out_dir / "dense_vs_age.png", pooled, max_age)
    plot_reliability(out_dir / "dense_reliability.png", pooled)

    sc0 = scenes[0]
    md: list[str] = [
        "## Dense formations: correct and false pairs vs spacing and track age",
        "",
        f"{len(scenes)} scenes: {len(ratios)} spacing ratios x {n} formation(s) per ratio (sizes "
        f"{', '.join(str(sc.aircraft) for sc in scenes[:: len(ratios)])} aircraft in turn); "
        f"{scans} scans of {sc0.scan_period_s:g} s.  Three radars (A, B, C) 100-180 km from one "
        "formation at bearings about 120 deg apart, each with unknown biases (azimuth 0.2-2 deg, "
        "range 50-500 m, elevation up to 0.1 deg, random signs), azimuth and elevation noise "
        f"0.1-0.3 deg, range noise {sc0.range_sigma_m:.0f} m, Pd 0.85-0.95 (one radar 0.7-0.8).  "
        "The formation flies one heading and speed (180-250 m/s) on a square lattice jittered by "
        f"+-{100 * sc0.jitter:.0f} % of the spacing, at one flight level.  Spacing = ratio x the "
        "scene's cross-range track error: the largest of the three radars' "
        f"`range x {sc0.track_noise_factor:g} x azimuth sigma` at the formation's mid-run position "
        f"({min(r.cross_range_m for r in results):.0f}-{max(r.cross_range_m for r in results):.0f} m "
        "in these scenes).",
        "",
        "Radar tracks (per radar and aircraft): bias plus an AR(1) error "
        f"({sc0.track_noise_factor:g} x the measurement sigmas, scan-to-scan correlation "
        f"{sc0.noise_correlation:g}) with the matching covariance; a track is confirmed at "
        f"{sc0.confirm_hits} detections; a missed detection leaves its row as it was (old `time_s` "
        f"and state: the tracker coasts), a tentative track is deleted after "
        f"{sc0.drop_tentative_misses} consecutive misses, a confirmed one after "
        f"{sc0.drop_confirmed_misses}, and the aircraft is re-acquired under a new id.  The "
        "correlators see only the track tables: no biases, no truth.",
        "",
        "Scoring by the simulator's truth, per radar pair (A-B, A-C, B-C) and scan: *common* = "
        "aircraft with a confirmed track on both radars; **correct rate = correct confirmed pairs / "
        "common aircraft**; **false rate = false confirmed pairs / confirmed pairs**; *age* = data "
        "time since both tracks (of the aircraft, or of the pair) were first reported confirmed.  "
        "Counts are pooled over scans, radar pairs and scenes.",
        "",
        "Methods: `svd-topology`, `gmm` and `nearest` are the service's `PairCorrelator` with "
        "default parameters, one per radar pair, all updated at the end of every scan (with the "
        "cycle step of three radars, as the correlation stage runs them); "
        f"`{SINGLE_UPDATES}` is `svd-topology` without the history evidence and the cycle step "
        "(every update decides alone, as before the evidence).  The peer is "
        "Stone Soup's `TrackToTrackCounting` (the open-source tracking framework's own "
        "track-to-track associator: an independent implementation of the counting technique, Sagild, "
        "Hem, Brekke, FUSION 2021) on the same tables: each confirmed track becomes a Stone Soup "
        "`Track` of `[x, vx, y, vy]` states at the scans' update times (the row extrapolated at "
        "constant velocity), measure = horizontal Euclidean distance, 3 consecutive scans within "
        "the threshold to associate, 2 consecutive misses to end, thresholds "
        f"{', '.join(f'{t / 1e3:g}' for t in STONESOUP_THRESHOLDS_M)} km.  An association counts as a "
        "confirmed pair from the scan of its third consecutive hit to the scan before its second "
        "consecutive miss (what the technique knew at that scan).  It is not one-to-one: *as is* "
        "every association counts; the main rows keep per scan the one-to-one assignment that "
        "maximises the time each association has lasted so far (the causal form of Stone Soup's "
        "own `one_to_one` deconfliction, which maximises whole association durations).",
        "",
        f"### Correct rate vs spacing (ages >= {SETTLED_AGE_S:.0f} s; `dense_vs_spacing.png`)",
        "",
        "| spacing / cross-range error | " + " | ".join(labels()) + " | common |",
        "|---:|" + "---:|" * (len(labels()) + 1),
    ]
    for k, r in enumerate(ratios):
        md.append(
            f"| {r:g} | "
            + " | ".join(_pct(by_ratio[lab][k][0]) for lab in labels())
            + f" | {by_ratio['svd-topology'][k][2]} |"
        )
    md += [
        "",
        f"### False rate vs spacing (ages >= {SETTLED_AGE_S:.0f} s)",
        "",
        "Per cell: false rate % (confirmed pairs).",
        "",
        "| spacing / cross-range error | " + " | ".join(labels()) + " |",
        "|---:|" + "---:|" * len(labels()),
    ]
    for k, r in enumerate(ratios):
        md.append(
            f"| {r:g} | "
            + " | ".join(f"{_pct(by_ratio[lab][k][1])} ({by_ratio[lab][k][3]})" for lab in labels())
            + " |"
        )
    md += [
        "",
        "Stone Soup as is (every association a confirmed pair), false rate %:",
        "",
        "| spacing / cross-range error | "
        + " | ".join(f"{t / 1e3:g} km" for t in STONESOUP_THRESHOLDS_M)
        + " |",
        "|---:|" + "---:|" * len(STONESOUP_THRESHOLDS_M),
    ]
    for k, r in enumerate(ratios):
        md.append(
            f"| {r:g} | "
            + " | ".join(_pct(by_ratio[stonesoup_label(t, False)][k][1]) for t in STONESOUP_THRESHOLDS_M)
            + " |"
        )
    goal = {lab: rates(pooled[lab], GOAL_RATIO, np.inf, SETTLED_AGE_S) for lab in labels()}
    goal_all = {lab: rates(pooled[lab], GOAL_RATIO, np.inf) for lab in labels()}
    md += [
        "",
        f"### The goal: >= {100 * GOAL_CORRECT:.0f} % correct, <= {100 * GOAL_FALSE:.0f} % false once the "
        f"spacing is >= {GOAL_RATIO:g}x the cross-range track error",
        "",
        f"| method | correct (ages >= {SETTLED_AGE_S:.0f} s) | false (ages >= {SETTLED_AGE_S:.0f} s) "
        "| correct (all ages) | false (all ages) | met (settled) |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for lab in labels():
        c, f, _, _ = goal[lab]
        ca, fa, _, _ = goal_all[lab]
        met = "yes" if c >= GOAL_CORRECT and f <= GOAL_FALSE else "no"
        md.append(f"| {lab} | {_pct(c)} | {_pct(f)} | {_pct(ca)} | {_pct(fa)} | {met} |")
    disp = np.concatenate([r.bias_displacement_m for r in results])
    md += [
        "",
        "Smallest spacing ratio from which the goal holds at every larger ratio of the table (ages "
        f">= {SETTLED_AGE_S:.0f} s): "
        + "; ".join(f"{lab} {goal_from(by_ratio[lab], ratios)}" for lab in labels())
        + ".",
        "",
        "Stone Soup's counting test compares absolute positions and has no bias model: the two radars' "
        "relative bias displacement at the formation (mostly the azimuth biases times the range; over "
        f"these scenes' radar pairs median {np.median(disp) / 1e3:.1f} km, 10-90 % "
        f"{np.percentile(disp, 10) / 1e3:.1f}-{np.percentile(disp, 90) / 1e3:.1f} km) is larger "
        "than the spacing, so a small threshold misses the right pair and a large one "
        "takes in the whole formation, where its one-to-one choice is close to a guess.  `nearest` "
        "fails the same way; `svd-topology` and `gmm` match the formation's shape, which is what a "
        "regular lattice makes ambiguous (a lattice shifted by one spacing looks almost the same).",
    ]
    g = f"{GOAL_RATIO:g}"
    md += [
        "",
        f"### Against time since both tracks were confirmed (`dense_vs_age.png`, {AGE_BIN_S:.0f} s bins)",
        "",
        f"| age (s) | svd correct < {g} | svd false < {g} | svd correct >= {g} | svd false >= {g} "
        f"| gmm correct >= {g} | nearest correct >= {g} |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for a in np.arange(0.0, max_age, 2 * AGE_BIN_S):
        lo = rates(pooled["svd-topology"], -np.inf, GOAL_RATIO - 1e-9, a, a + 2 * AGE_BIN_S)
        hi = rates(pooled["svd-topology"], GOAL_RATIO, np.inf, a, a + 2 * AGE_BIN_S)
        gm = rates(pooled["gmm"], GOAL_RATIO, np.inf, a, a + 2 * AGE_BIN_S)
        nn = rates(pooled["nearest"], GOAL_RATIO, np.inf, a, a + 2 * AGE_BIN_S)
        md.append(
            f"| {a:.0f}-{a + 2 * AGE_BIN_S:.0f} | {_pct(lo[0])} | {_pct(lo[1])} | {_pct(hi[0])} | "
            f"{_pct(hi[1])} | {_pct(gm[0])} | {_pct(nn[0])} |"
        )
    md += [
        "",
        "### Calibration of `score` (`dense_reliability.png`)",
        "",
        "Every published pair (tentative and confirmed) at every scan, radar pair and scene, its "
        "`score` read as the probability that the pair is right; 10 equal bins.",
        "",
        "| method | pairs | Brier score | mean score | fraction right |",
        "|---|---:|---:|---:|---:|",
    ]
    for m in METHODS:
        rec = pooled[m]
        md.append(
            f"| {m} | {len(rec.score)} | {brier(rec):.4f} | "
            f"{float(np.mean(rec.score)) if rec.score else float('nan'):.3f} | "
            f"{float(np.mean(rec.score_ok)) if rec.score_ok else float('nan'):.3f} |"
        )
    mean_s, frac, count = reliability(pooled["svd-topology"])
    md += [
        "",
        "svd-topology per bin:",
        "",
        "| score bin | pairs | mean score | fraction right |",
        "|---|---:|---:|---:|",
    ]
    for k in range(10):
        md.append(
            f"| {k / 10:.1f}-{(k + 1) / 10:.1f} | {count[k]:.0f} | "
            f"{'-' if not count[k] else f'{mean_s[k]:.3f}'} | {'-' if not count[k] else f'{frac[k]:.3f}'} |"
        )
    ev = CorrelationParams().evidence
    fit_a, fit_b = fit_calibration(pooled["svd-topology"], ev.calibration_slope, ev.calibration_offset)
    md += [
        "",
        f"The service's calibration (`EvidenceParams`): slope {ev.calibration_slope:g}, offset "
        f"{ev.calibration_offset:g}; the maximum-likelihood fit on these pairs: slope {fit_a:.3f}, "
        f"offset {fit_b:.3f} (equal when the scores are calibrated on these scenes).",
    ]
    cost = {m: float(np.mean([r.ms_per_update[m] for r in results])) for m in METHODS}
    md += [
        "",
        "Mean time of one radar pair's update (ms, this machine): "
        + ", ".join(f"{m} {cost[m]:.1f}" for m in METHODS)
        + ".",
        "",
        "Figures: `dense_vs_spacing.png`, `dense_vs_age.png`, `dense_reliability.png`, made by "
        f"`topofusion evaluate --only dense` (`--runs 1`: one 30-aircraft formation per ratio).  "
        f"Total time {time.perf_counter() - t_start:.0f} s.",
        "",
    ]
    return "\n".join(md)
