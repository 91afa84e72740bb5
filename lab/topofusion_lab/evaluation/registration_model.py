"""Registration model study: range gain and time-stamp bias with the real pipeline.

``python -m topofusion_lab.evaluation.registration_model [--runs N] [--duration S] [--workers W]``

Every run is a real stream of the simulator (the bytes of ``wire_messages``, through
:func:`topofusion_lab.evaluation.adsb.stream`) into the service's
:class:`~service.engine.Engine` with its default configuration, in process: the three-radar
catalog scenario (radars A, B, C, Mode S plots, light clutter on A and B) with per-radar range
offsets, range gains, azimuth and elevation offsets and time-stamp biases set by the condition,
and an ADS-B receiver hearing a share of the aircraft (or none).  The engine correlates every
radar pair (``svd-topology``) and every radar with the ADS-B source (``cfar``) and solves the
joint registration (:mod:`service.correlation.registration`); the study reads the ``/biases``
of the final snapshot and scores the radar-radar pairs by the simulator's truth.

Conditions (:data:`CONDITIONS`): the issue's scene (gains +800 / -600 / +400 ppm, time biases
+0.6 / -0.4 / +1.0 s, range offsets 120 / -180 / 250 m, azimuth offsets 0.15 / -0.20 / 0.10
deg, 60 % of the aircraft with ADS-B); larger terms (+-1 000 ppm, +-1.5 s); the equipage from
100 % to 10 % and none; and scenes with no gain and no time bias at all (the new terms should
then come out consistent with zero).  ``three-term`` rows run the same stream with the gain and
time terms switched off (``RegistrationParams.estimate_range_gain`` / ``estimate_time_bias``),
the model before this study: pair accuracy with and without the new terms.

Scoring per radar: each term's error against the truth and against its reported 1-sigma, and
per condition and term kind the distribution of error / sigma over radars and runs (RMS, share
within 2 sigma: an honest sigma has about 1 and 95 %).
Without ADS-B a time bias common to the three radars is not observable (module docstring of
the registration), so the time biases are then compared *relative to their mean* (estimate
minus the estimates' mean against truth minus the truths' mean).  Radar-radar pairs on the
final snapshot: *correct* = confirmed pairs whose two tracks follow the same aircraft / all
confirmed pairs; *false* = the rest / all confirmed; *complete* = aircraft with confirmed tracks
in both radars that have a correct confirmed pair / all such aircraft.

Fused error (:func:`fused_sample`): the scene also carries an exact ADS-B source (every
aircraft, no error, one report a second, as in :mod:`topofusion_lab.evaluation.system`) whose
messages are kept out of the engine and give each aircraft's true position (its draws change
the simulator's random stream: the same seed gives other noise than without it).  At every
system-track update of the engine in the second half of the run, each confirmed system track
whose members all follow one aircraft (a *pure* track, by the radar members' ``truth_id`` and
the ADS-B members' Mode S address) is compared with that aircraft's true position at the
batch's ``time_s``: the horizontal (local east-north) distance.  Per condition: its RMS and
95th percentile over every such sample of every run, the RMS over the tracks without an ADS-B
member (where only the radars' registration counts), the distinct system tracks behind them,
and the purity (pure / (pure + mixed) confirmed system tracks, summed over the same samples;
:func:`topofusion_lab.evaluation.system.score`).

Goals (the issue): every gain within max(25 %, 100 ppm) of the truth, every time bias within
max(20 %, 0.1 s), range and azimuth offsets within 10 %, pairs >= 0.97 complete and <= 0.02
false; with no gain and no time bias in the data the new terms within 2 sigma of zero.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from service.config import EngineConfig
from service.engine import Engine
from service.geo import ecef_to_geodetic, enu_rotation
from service.pipeline.read_model import Snapshot
from service.wire.keys import Keys
from topofusion_lab.evaluation.adsb import ADSB_ID, PREFIX, stream
from topofusion_lab.evaluation.jobs import ratio, run_jobs
from topofusion_lab.evaluation.system import TRUTH_ID, Truth, score, snapshot_inputs
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import AdsbSpec, Scenario, identity_of

#: Data seconds of every run: the registration memory's length (``RegistrationParams.memory_s``).
DURATION_S = 600.0
#: Aircraft in the scene.
TARGETS = 100
GOAL_GAIN_FRACTION, GOAL_GAIN_PPM = 0.25, 100.0
GOAL_TIME_FRACTION, GOAL_TIME_S = 0.20, 0.10
GOAL_OFFSET_FRACTION = 0.10
GOAL_COMPLETE, GOAL_FALSE = 0.97, 0.02
#: With no gain / time bias in the data, the estimate within this many sigma of zero.
GOAL_ZERO_SIGMA = 2.0
#: The per-radar fields of ``/biases`` and the simulator's ``RadarSpec`` for each term:
#: (label, estimate field, sigma field, truth field, format).
TERM_FIELDS = (
    ("range offset (m)", "range_bias_m", "range_bias_sigma_m", "range_bias_m", "{:.1f}"),
    ("range gain (ppm)", "range_gain_ppm", "range_gain_sigma_ppm", "range_gain_ppm", "{:.0f}"),
    ("azimuth offset (deg)", "azimuth_bias_deg", "azimuth_bias_sigma_deg", "azimuth_bias_deg", "{:.3f}"),
    (
        "elevation offset (deg)",
        "elevation_bias_deg",
        "elevation_bias_sigma_deg",
        "elevation_bias_deg",
        "{:.3f}",
    ),
    ("time bias (s)", "time_bias_s", "time_bias_sigma_s", "time_bias_s", "{:.2f}"),
)


@dataclass(frozen=True)
class Condition:
    label: str
    range_m: tuple[float, float, float] = (120.0, -180.0, 250.0)
    azimuth_deg: tuple[float, float, float] = (0.15, -0.20, 0.10)
    elevation_deg: tuple[float, float, float] = (0.05, -0.05, 0.0)
    gain_ppm: tuple[float, float, float] = (800.0, -600.0, 400.0)
    time_s: tuple[float, float, float] = (0.6, -0.4, 1.0)
    #: Share of the aircraft with ADS-B (None: no receiver).
    adsb_share: float | None = 0.6
    #: False: gain and time bias not estimated (the three-term model).
    full_model: bool = True

    @property
    def no_new_terms(self) -> bool:
        return not any(self.gain_ppm) and not any(self.time_s)


_LARGE = {"gain_ppm": (1000.0, -1000.0, 1000.0), "time_s": (1.5, -1.5, 1.5)}
_ZERO = {"gain_ppm": (0.0, 0.0, 0.0), "time_s": (0.0, 0.0, 0.0)}
CONDITIONS: tuple[Condition, ...] = (
    Condition("issue scene, ADS-B 60 %"),
    Condition("issue scene, ADS-B 60 %, three-term", full_model=False),
    Condition("+-1000 ppm, +-1.5 s, ADS-B 60 %", **_LARGE),  # type: ignore[arg-type]
    Condition("+-1000 ppm, +-1.5 s, ADS-B 60 %, three-term", full_model=False, **_LARGE),  # type: ignore[arg-type]
    Condition("issue scene, ADS-B 100 %", adsb_share=1.0),
    Condition("issue scene, ADS-B 10 %", adsb_share=0.1),
    Condition("issue scene, no ADS-B", adsb_share=None),
    Condition("no gain / time bias, ADS-B 60 %", **_ZERO),  # type: ignore[arg-type]
    Condition("no gain / time bias, no ADS-B", adsb_share=None, **_ZERO),  # type: ignore[arg-type]
)


@dataclass(frozen=True)
class Job:
    index: int
    condition: Condition
    seed: int
    duration_s: float


@dataclass
class RadarResult:
    radar_id: str
    truth: dict[str, float]
    #: The ``/biases`` entry's fields (None: no estimate for the radar, or a term not estimated).
    estimate: dict[str, float | None]
    sigma: dict[str, float | None]


@dataclass
class RunResult:
    index: int
    seed: int
    radars: list[RadarResult]
    confirmed: int = 0
    correct: int = 0
    common: int = 0
    found: int = 0
    seconds: float = 0.0
    errors: int = 0
    notes: list[str] = field(default_factory=list)
    #: Second half of the run (:func:`fused_sample`): horizontal error (m) of every pure
    #: confirmed system track at every system-track update, the distinct system tracks behind
    #: them, the confirmed pure / mixed system tracks summed over the updates, the updates.
    fused_err: list[float] = field(default_factory=list)
    #: ... of those without an ADS-B member (the radars' registration alone).
    fused_err_radar: list[float] = field(default_factory=list)
    fused_tracks: set[str] = field(default_factory=set)
    pure: int = 0
    mixed: int = 0
    updates: int = 0


def scenario_of(job: Job) -> Scenario:
    """The three-radar catalog scene with the condition's terms and ADS-B equipage."""
    c = job.condition
    base = get_scenario("three-radar")
    radars = tuple(
        replace(
            r,
            identity=True,
            range_bias_m=c.range_m[k],
            azimuth_bias_deg=c.azimuth_deg[k],
            elevation_bias_deg=c.elevation_deg[k],
            range_gain_ppm=c.gain_ppm[k],
            time_bias_s=c.time_s[k],
        )
        for k, r in enumerate(base.radars)
    )
    adsb = () if c.adsb_share is None else (AdsbSpec(ADSB_ID, equipped_share=c.adsb_share),)
    exact = AdsbSpec(
        TRUTH_ID, report_period_s=1.0, batch_period_s=1.0, position_sigma_m=0.0, height_sigma_m=0.0
    )
    return replace(base, radars=radars, targets=TARGETS, duration_s=job.duration_s, adsb=(*adsb, exact))


def engine_config(c: Condition) -> EngineConfig:
    """The default engine, with gain and time bias switched off for a three-term row."""
    cfg = EngineConfig()
    if c.full_model:
        return cfg
    reg = replace(cfg.correlation.registration, estimate_range_gain=False, estimate_time_bias=False)
    return replace(cfg, correlation=replace(cfg.correlation, registration=reg))


def horizontal_error(position_ecef_m: Sequence[float] | np.ndarray, true_ecef_m: np.ndarray) -> float:
    """Length of the position error's component in the local horizontal plane at the truth
    (east and north; the up component along the ellipsoid normal is left out), metres."""
    err = np.asarray(position_ecef_m, dtype=float) - true_ecef_m
    lat, lon, _ = ecef_to_geodetic(true_ecef_m)
    up = enu_rotation(float(lat), float(lon))[:, 2]
    return float(np.linalg.norm(err - float(err @ up) * up))


def fused_sample(
    res: RunResult,
    body: dict[str, Any],
    label: dict[tuple[str, str], str | None],
    true_position: Callable[[str, float], np.ndarray | None],
) -> None:
    """Add one ``SystemTrackBatch`` (``body``) to ``res``: the horizontal error of each
    confirmed system track whose members all follow one aircraft (``label``: each radar
    track's aircraft, None: clutter) against that aircraft's true position at the batch's
    ``time_s`` (None: not known, the track left out), and its pure / mixed counts."""
    when = float(body["time_s"])
    got = score(body, label, set(), {}, true_position, max_cases=0)
    res.pure += got.pure
    res.mixed += got.mixed
    res.updates += 1
    for s in body["system_tracks"]:
        if s["status"] != "confirmed":
            continue
        names = {label.get((m["radar_id"], m["track_id"])) for m in s["members"]}
        if len(names) != 1 or None in names:
            continue
        true = true_position(str(names.pop()), when)
        if true is None:
            continue
        res.fused_err.append(horizontal_error(s["position_ecef_m"], true))
        if all(m["radar_id"] != ADSB_ID for m in s["members"]):
            res.fused_err_radar.append(res.fused_err[-1])
        res.fused_tracks.add(str(s["system_track_id"]))


def _sample_engine(res: RunResult, snap: Snapshot, truth: Truth, from_s: float, accel_psd: float) -> None:
    """:func:`fused_sample` of the engine's system tracks now, if they are from ``from_s`` on."""
    body = snap.system_tracks("all")
    if body["time_s"] is None or float(body["time_s"]) < from_s:
        return
    tables = {rid: table for rid, (_, table) in snap.tracks.items()}
    label = snapshot_inputs(tables, float(body["time_s"]), accel_psd, {}).label
    # an ADS-B member's track id is the Mode S address its aircraft transmits
    names = {identity_of(n)[1]: n for n in set(label.values()) if n is not None}
    for s in body["system_tracks"]:
        for m in s["members"]:
            if m["radar_id"] == ADSB_ID:
                label[(m["radar_id"], m["track_id"])] = names.get(m["track_id"])

    def true(name: str, t: float) -> np.ndarray | None:
        return truth.position(identity_of(name)[1], t)

    fused_sample(res, body, label, true)


def run_one(job: Job) -> RunResult:
    """Stream one job's scene through an engine; its biases and radar-radar pairs at the end,
    and its fused error over the second half (module docstring)."""
    t_start = time.perf_counter()
    sc = scenario_of(job)
    engine = Engine(engine_config(job.condition))
    accel_psd = engine.config.correlation.prediction.accel_psd
    truth_key = Keys(PREFIX).input("adsb", TRUTH_ID)
    from_s = sc.start_time_s + job.duration_s / 2.0
    truth = Truth()
    res = RunResult(job.index, job.seed, [])
    errors = 0
    for _, key, payload, body in stream(sc, job.seed):
        if key == truth_key:  # the truth: never given to the engine
            truth.add(body)
            continue
        out = engine.ingest(key, payload, receive_time_s=0.0)
        errors += sum(o.key.endswith("/errors") for o in out)
        if any(o.key.endswith("/system/tracks") for o in out):
            _sample_engine(res, engine.snapshot(), truth, from_s, accel_psd)
    out = engine.flush()
    errors += sum(o.key.endswith("/errors") for o in out)
    if any(o.key.endswith("/system/tracks") for o in out):
        _sample_engine(res, engine.snapshot(), truth, from_s, accel_psd)
    snap = engine.snapshot()
    estimates = {b["radar_id"]: b for b in snap.biases()}
    radars = []
    for r in sc.radars:
        est = estimates.get(r.radar_id, {})
        radars.append(
            RadarResult(
                r.radar_id,
                {t[3]: float(getattr(r, t[3])) for t in TERM_FIELDS},
                {t[1]: est.get(t[1]) for t in TERM_FIELDS},
                {t[1]: est.get(t[2]) for t in TERM_FIELDS},
            )
        )
    res.radars, res.errors = radars, errors
    _score_pairs(res, snap, {r.radar_id for r in sc.radars})
    res.seconds = time.perf_counter() - t_start
    return res


def _score_pairs(res: RunResult, snap: Snapshot, radar_ids: set[str]) -> None:
    """Radar-radar confirmed pairs of the final snapshot against the simulator's truth."""
    tracks = snap.tracks
    for ps in snap.pair_sets(status="confirmed"):
        a, b = ps["radar_a"], ps["radar_b"]
        if a not in radar_ids or b not in radar_ids or a not in tracks or b not in tracks:
            continue
        ta, tb = tracks[a][1], tracks[b][1]
        truth_a = dict(zip(ta.track_id.tolist(), ta.truth_id.tolist(), strict=True))
        truth_b = dict(zip(tb.track_id.tolist(), tb.truth_id.tolist(), strict=True))
        right = set()
        for p in ps["pairs"]:
            x, y = truth_a.get(p["track_a"]), truth_b.get(p["track_b"])
            res.confirmed += 1
            if x is not None and x == y:
                res.correct += 1
                right.add(x)
        both = set(ta.truth_id[ta.confirmed].tolist()) & set(tb.truth_id[tb.confirmed].tolist()) - {None}
        res.common += len(both)
        res.found += len(both & right)


# -- summary ------------------------------------------------------------------------------


def _error(c: Condition, r: RadarResult, radars: Sequence[RadarResult], name: str, truth: str) -> float:
    """Estimate minus truth of one term; time bias without ADS-B relative to the radars' mean."""
    est = r.estimate[name]
    if est is None:
        return math.nan
    if name == "time_bias_s" and c.adsb_share is None:
        ests = [q.estimate[name] for q in radars]
        if any(e is None for e in ests):
            return math.nan
        mean_est = float(np.mean([float(e) for e in ests if e is not None]))
        mean_true = float(np.mean([q.truth[truth] for q in radars]))
        return (est - mean_est) - (r.truth[truth] - mean_true)
    return est - r.truth[truth]


def _within(name: str, err: float, truth: float, sigma: float | None, zero_scene: bool) -> bool:
    """Whether one term meets its goal (module docstring)."""
    if not math.isfinite(err):
        return False
    if name in ("range_gain_ppm", "time_bias_s") and zero_scene:
        return sigma is not None and sigma > 0 and abs(err) <= GOAL_ZERO_SIGMA * sigma
    if name == "range_gain_ppm":
        return abs(err) <= max(GOAL_GAIN_FRACTION * abs(truth), GOAL_GAIN_PPM)
    if name == "time_bias_s":
        return abs(err) <= max(GOAL_TIME_FRACTION * abs(truth), GOAL_TIME_S)
    if name in ("range_bias_m", "azimuth_bias_deg"):
        return abs(err) <= GOAL_OFFSET_FRACTION * abs(truth)
    return True  # elevation offsets: reported, no goal


def _fmt(fmt: str, x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else fmt.format(x)


def z_scores(c: Condition, runs: Sequence[RunResult], name: str, truth_name: str) -> tuple[list[float], int]:
    """Every radar's and run's error / reported 1-sigma of one term (:func:`_error`), and how
    many gains were held at zero (estimate exactly 0: reported with the whole model's sigma,
    their error then says nothing of it).  Left out: terms without an estimate or a sigma, and
    time biases without ADS-B (their error is relative to the radars' mean, their sigma the
    marginal one, which holds the unobservable common mode)."""
    zs: list[float] = []
    held = 0
    if name == "time_bias_s" and c.adsb_share is None:
        return zs, held
    for run in runs:
        for r in run.radars:
            est, sig = r.estimate[name], r.sigma[name]
            if est is None or not sig:
                continue
            if name == "range_gain_ppm" and est == 0.0:
                held += 1
                continue
            err = _error(c, r, run.radars, name, truth_name)
            if math.isfinite(err):
                zs.append(err / sig)
    return zs, held


def z_table(conditions: dict[int, Condition], by_index: dict[int, list[RunResult]]) -> list[str]:
    """Per condition and term kind the distribution of error / sigma over radars and runs."""
    out = [
        "| condition | term | n | held | mean z | RMS z | abs(z) <= 2 | max abs(z) |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for index in sorted(by_index):
        c = conditions[index]
        for label, name, _, truth_name, _ in TERM_FIELDS:
            if not c.full_model and name in ("range_gain_ppm", "time_bias_s"):
                continue
            zs, held = z_scores(c, by_index[index], name, truth_name)
            z = np.asarray(zs)
            if z.size == 0:
                out.append(f"| {c.label} | {label} | 0 | {held} | - | - | - | - |")
                continue
            out.append(
                f"| {c.label} | {label} | {z.size} | {held} | {z.mean():+.2f} | "
                f"{math.sqrt(float(np.mean(z**2))):.2f} | {np.mean(np.abs(z) <= GOAL_ZERO_SIGMA):.0%} | "
                f"{np.abs(z).max():.1f} |"
            )
    return out


def _rms(xs: Sequence[float]) -> float:
    return math.sqrt(float(np.mean(np.square(xs)))) if len(xs) else math.nan


def fused_error(runs: Sequence[RunResult]) -> tuple[float, float, float, int, float]:
    """RMS and 95th percentile (m) of the runs' fused horizontal errors pooled, the RMS of
    those without an ADS-B member, the system tracks behind them (distinct per run, summed
    over runs), and the purity."""
    err = [e for r in runs for e in r.fused_err]
    p95 = float(np.percentile(err, 95.0)) if err else math.nan
    radar = _rms([e for r in runs for e in r.fused_err_radar])
    pure = sum(r.pure for r in runs)
    purity = ratio(pure, pure + sum(r.mixed for r in runs))
    return _rms(err), p95, radar, sum(len(r.fused_tracks) for r in runs), purity


def fused_cells(runs: Sequence[RunResult]) -> str:
    rms, p95, radar, tracks, purity = fused_error(runs)
    return (
        f"{_fmt('{:.0f}', rms)} | {_fmt('{:.0f}', p95)} | {_fmt('{:.0f}', radar)} | {tracks} | "
        f"{_fmt('{:.3f}', purity)}"
    )


def markdown(jobs: Sequence[Job], results: Sequence[RunResult], duration_s: float) -> list[str]:
    """A summary per condition (largest errors, goals, radar-radar pairs), the distribution of
    error / sigma per condition and term kind (:func:`z_table`), then per condition, radar and
    term the truth, estimate, error, sigma and goal."""
    by_index: dict[int, list[RunResult]] = {}
    for res in results:
        by_index.setdefault(res.index, []).append(res)
    conditions = {j.index: j.condition for j in jobs}
    detail = [
        "| condition | radar | term | true | estimate | error | sigma | z | goal |",
        "|---|---|---|---:|---:|---:|---:|---:|---|",
    ]
    summary = [
        "| condition | model | max gain error (ppm) | max time-bias error (s) | max range-offset error "
        "| max azimuth-offset error | terms in goal | pairs correct | false | complete | all goals "
        "| fused RMS (m) | fused p95 (m) | fused RMS, no ADS-B member (m) | system tracks | purity |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|",
    ]
    for index in sorted(by_index):
        c = conditions[index]
        runs = by_index[index]
        worst: dict[str, float] = {}
        met = total = 0
        for k, rid in enumerate(r.radar_id for r in runs[0].radars):
            for label, name, _, truth_name, fmt in TERM_FIELDS:
                if not c.full_model and name in ("range_gain_ppm", "time_bias_s"):
                    continue
                errs = [_error(c, run.radars[k], run.radars, name, truth_name) for run in runs]
                oks = [
                    _within(name, e, q.radars[k].truth[truth_name], q.radars[k].sigma[name], c.no_new_terms)
                    for e, q in zip(errs, runs, strict=True)
                ]
                if name != "elevation_bias_deg":
                    met += sum(oks)
                    total += len(oks)
                truth = runs[0].radars[k].truth[truth_name]
                scale = abs(truth) if name in ("range_bias_m", "azimuth_bias_deg") and truth else 1.0
                worst[name] = max(worst.get(name, 0.0), float(np.nanmax(np.abs(errs))) / scale)
                pick = int(np.nanargmax(np.abs(errs))) if np.isfinite(errs).any() else 0
                r = runs[pick].radars[k]
                sig, err = r.sigma[name], errs[pick]
                z = err / sig if sig and math.isfinite(err) else math.nan
                detail.append(
                    f"| {c.label} | {rid} | {label} | {_fmt(fmt, r.truth[truth_name])} | "
                    f"{_fmt(fmt, r.estimate[name])} | {_fmt(fmt, err)} | {_fmt(fmt, sig)} | "
                    f"{_fmt('{:+.1f}', z)} | {'yes' if all(oks) else '**no**'} |"
                )
        conf = sum(r.confirmed for r in runs)
        correct = ratio(sum(r.correct for r in runs), conf)
        false = ratio(conf - sum(r.correct for r in runs), conf)
        complete = ratio(sum(r.found for r in runs), sum(r.common for r in runs))
        pairs_ok = correct >= GOAL_COMPLETE and false <= GOAL_FALSE and complete >= GOAL_COMPLETE
        summary.append(
            f"| {c.label} | {'5 terms' if c.full_model else '3 terms'} | "
            f"{_fmt('{:.0f}', worst.get('range_gain_ppm'))} | {_fmt('{:.2f}', worst.get('time_bias_s'))} | "
            f"{_fmt('{:.1%}', worst.get('range_bias_m'))} | "
            f"{_fmt('{:.1%}', worst.get('azimuth_bias_deg'))} | "
            f"{met}/{total} | {correct:.3f} | {false:.3f} | {complete:.3f} | "
            f"{'yes' if pairs_ok and met == total else '**no**'} | {fused_cells(runs)} |"
        )
    errors = sum(r.errors for r in results)
    return [
        f"### Registration terms (three-radar scene, {TARGETS} aircraft, {duration_s:.0f} s, "
        f"{len(results) // max(1, len(conditions))} run(s) per condition)",
        "",
        "*error* = estimate - truth (time bias without ADS-B: relative to the three radars' mean); "
        "offsets' errors relative to the truth; the largest over radars and runs.  *terms in goal*: "
        "gain within max(25 %, 100 ppm), time bias within max(20 %, 0.1 s), range and azimuth "
        "offsets within 10 %, and where the scene has no gain and no time bias those two within 2 "
        "sigma of zero (per radar and run; elevation: no goal).  Pairs: radar-radar confirmed pairs "
        "at the end, *complete* = aircraft tracked by both radars with a correct pair.  *Fused*: "
        "horizontal error of the confirmed system tracks whose members follow one aircraft "
        "against its true position, at every system-track update of the second half of each run "
        "(RMS and 95th percentile over those samples and the runs; *no ADS-B member*: the RMS "
        "over the tracks without an ADS-B member, the radars' registration alone; *system "
        "tracks*: distinct ones behind them, summed over runs); *purity*: pure / (pure + "
        "mixed) confirmed system tracks over the same updates.",
        "",
        *summary,
        "",
        "Error / reported 1-sigma (*z*) over every radar and run, per term: an honest sigma has "
        "RMS z near 1 and abs(z) <= 2 in about 95 % (*held*: gains held at zero, left out; time "
        "biases without ADS-B left out, their sigma holds the unobservable common mode):",
        "",
        *z_table(conditions, by_index),
        "",
        "Per radar and term (several runs: the run of the largest error; *z* = error / reported 1-sigma):",
        "",
        *detail,
        "",
        f"Rejected messages over all runs: {errors}.",
        "",
    ]


def make_jobs(runs: int, seed: int, conditions: Sequence[Condition], duration_s: float) -> list[Job]:
    return [Job(i, c, seed + 1000 * r + i, duration_s) for r in range(runs) for i, c in enumerate(conditions)]


def run(
    runs: int = 1,
    seed: int = 7,
    duration_s: float = DURATION_S,
    workers: int = 1,
    only: Sequence[str] = (),
    progress: Callable[[str], None] = print,
) -> list[str]:
    """Every condition (or those whose label contains one of ``only``) ``runs`` times; the
    markdown tables."""
    conditions = [c for c in CONDITIONS if not only or any(o in c.label for o in only)]
    jobs = make_jobs(runs, seed, conditions, duration_s)
    progress(f"registration model: {len(jobs)} runs of {duration_s:.0f} s data, {workers} worker(s)")
    results = sorted(
        run_jobs(run_one, jobs, workers, progress, "registration"), key=lambda r: (r.index, r.seed)
    )
    return markdown(jobs, results, duration_s)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1, help="runs (seeds) per condition")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--duration", type=float, default=DURATION_S, help="data seconds per run")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--only", action="append", default=[], help="conditions whose label contains this")
    ap.add_argument("--out", help="also write the tables to this markdown file")
    args = ap.parse_args(argv)

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    md = run(args.runs, args.seed, args.duration, args.workers, args.only, progress)
    text = "\n".join(md)
    print(text)
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
