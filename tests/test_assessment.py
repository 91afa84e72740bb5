"""The performance assessment's numerics (service.assessment) against plain loop forms, and
through the engine: determinism, nothing without references, hostile input."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace

import numpy as np
import pytest

from service.assessment import Assessment, AssessmentParams, Requirements
from service.assessment.radar import RadarAssessment
from service.assessment.references import ReferenceHistory
from service.engine import Engine, EngineConfig
from service.geo import Site, ecef_to_geodetic
from tests.scenario_helpers import scenario_messages

SITE = Site("R", 45.0, 5.0, 100.0, range_sigma_m=100.0, azimuth_sigma_deg=0.1, scan_period_s=4.0)
T0 = 1_763_769_600.0


@dataclass
class Scene:
    """Aircraft flying straight in the radar's ENU frame, plots of a biased noisy radar."""

    ids: list[str]
    pos0: np.ndarray  # (n, 3) ENU at T0
    vel: np.ndarray  # (n, 3)
    codes: list[str]

    def enu(self, a: int, t: float) -> np.ndarray:
        return self.pos0[a] + self.vel[a] * (t - T0)


def make_scene(n: int = 12, seed: int = 3) -> Scene:
    rng = np.random.default_rng(seed)
    rho = rng.uniform(30_000.0, 140_000.0, n)
    az = rng.uniform(0.2, 2 * np.pi - 0.2, n)
    pos0 = np.column_stack([rho * np.sin(az), rho * np.cos(az), rng.uniform(5_000.0, 10_000.0, n)])
    # outbound along their radials: never across north, where a plot's scan is ambiguous
    vel = np.column_stack([200 * np.sin(az), 200 * np.cos(az), np.zeros(n)])
    ids = [f"{0xA00000 + k:06x}" for k in range(n)]
    codes = [f"{(k * 37) % 4096:04o}" for k in range(n)]
    return Scene(ids, pos0, vel, codes)


@dataclass
class Plot:
    aircraft: int
    time_s: float
    range_m: float
    azimuth_deg: float
    mode_3a: str | None
    flight_level: float


def make_plots(scene: Scene, duration_s: float, pd: float, seed: int = 5) -> list[Plot]:
    rng = np.random.default_rng(seed)
    plots = []
    period = SITE.scan_period_s
    for k in range(int(duration_s / period)):
        for a in range(len(scene.ids)):
            az = math.degrees(math.atan2(*scene.enu(a, T0 + k * period)[:2])) % 360.0
            t = T0 + k * period + az / 360.0 * period
            if rng.random() >= pd:
                continue
            e, n_, u = scene.enu(a, t)
            r = math.sqrt(e * e + n_ * n_ + u * u)
            true_az = math.degrees(math.atan2(e, n_)) % 360.0
            code = scene.codes[a] if rng.random() > 0.05 else "7777"
            fl = u / 30.48 + (10.0 if rng.random() < 0.1 else 0.0)
            plots.append(
                Plot(
                    a,
                    t,
                    r + 250.0 + rng.normal(0, SITE.range_sigma_m),
                    (true_az + 0.3 + rng.normal(0, SITE.azimuth_sigma_deg)) % 360.0,
                    code,
                    fl,
                )
            )
    return sorted(plots, key=lambda p: p.time_s)


def feed(
    assessment: Assessment, scene: Scene, plots: list[Plot], duration_s: float, every: float = 1.0
) -> None:
    """References every second (batches of 2 s), plot batches of ``every`` s, all aircraft paired."""
    t = T0
    i = 0
    while t < T0 + duration_s + 6.0:  # references on past the last plot
        t_next = t + every
        if round((t - T0) / 2.0, 6) == round((t - T0) / 2.0):  # a reference batch every 2 s
            times = np.arange(t - 2.0, t, 1.0) + 1.0
            ids, enus, ts = [], [], []
            for a in range(len(scene.ids)):
                for tr in times:
                    ids.append(scene.ids[a])
                    enus.append(scene.enu(a, tr))
                    ts.append(tr)
            lat, lon, alt = ecef_to_geodetic(SITE.enu_to_ecef(np.array(enus)))
            fl = np.array([enu[2] / 30.48 for enu in enus])
            m3a = np.array([scene.codes[scene.ids.index(x)] for x in ids], dtype=object)
            assessment.reference("adsb-1", "adsb", np.array(ts), np.array(ids), lat, lon, alt, m3a, fl, t)
            assessment.pairs("R", "adsb-1", list(scene.ids), t)  # as each correlation update says
        batch = []
        while i < len(plots) and plots[i].time_s <= t_next:
            batch.append(plots[i])
            i += 1
        assessment.plots(
            "R",
            SITE,
            np.array([p.time_s for p in batch]),
            np.array([p.range_m for p in batch]),
            np.array([p.azimuth_deg for p in batch]),
            np.array([p.mode_3a for p in batch], dtype=object),
            np.array([p.flight_level for p in batch]),
            t_next,
        )
        assessment.advance(None)
        t = t_next
    assessment.finish()


def reference_form(scene: Scene, plots: list[Plot], mode_c_tolerance_fl: float = 2.0) -> dict[str, float]:
    """The figures by plain loops over the plots, each with its true aircraft and the exact
    reference position at its time (every cell covered, every gap within max_gap_s)."""
    period = SITE.scan_period_s
    e_rho, k, rho, e_a, e_r = [], [], [], [], []
    m3a_ok = fl_ok = 0
    last: dict[int, float] = {}
    expected = detected = 0
    for p in plots:
        e, n_, u = scene.enu(p.aircraft, p.time_s)
        rr = math.sqrt(e * e + n_ * n_ + u * u)
        rh = math.hypot(e, n_)
        az = math.degrees(math.atan2(e, n_))
        e_rho.append(math.sqrt(max(p.range_m**2 - u * u, 0.0)) - rh)
        k.append(rr / rh)
        rho.append(rh)
        e_a.append(math.radians((p.azimuth_deg - az + 180.0) % 360.0 - 180.0))
        e_r.append(p.range_m - rr)
        m3a_ok += p.mode_3a == scene.codes[p.aircraft]
        fl_ok += abs(p.flight_level - u / 30.48) <= mode_c_tolerance_fl
        if p.aircraft in last:
            scans = round((p.time_s - last[p.aircraft]) / period)
            expected += scans
            detected += 1
        else:
            expected += 1
            detected += 1
        last[p.aircraft] = p.time_s
    n = len(plots)
    b_r = sum(a * b for a, b in zip(k, e_rho, strict=True)) / sum(a * a for a in k)
    b_a = sum(r * r * a for r, a in zip(rho, e_a, strict=True)) / sum(r * r for r in rho)
    d2 = [(x - kk * b_r) ** 2 + (r * (a - b_a)) ** 2 for x, kk, r, a in zip(e_rho, k, rho, e_a, strict=True)]
    mean_r = sum(e_r) / n
    mean_a = sum(e_a) / n
    return {
        "pd": detected / expected,
        "expected": expected,
        "rms_m": math.sqrt(sum(d2) / n),
        "median_m": float(np.median(np.sqrt(d2))),
        "rms_uncorrected_m": math.sqrt(
            sum(x * x + (r * a) ** 2 for x, r, a in zip(e_rho, rho, e_a, strict=True)) / n
        ),
        "range_rms_m": math.sqrt(sum((x - mean_r) ** 2 for x in e_r) / n),
        "azimuth_rms_deg": math.degrees(math.sqrt(sum((a - mean_a) ** 2 for a in e_a) / n)),
        "mode_3a": m3a_ok / n,
        "mode_c": fl_ok / n,
        "plots": n,
        "b_r": b_r,
        "b_a": math.degrees(b_a),
    }


def covered_assessment(params: AssessmentParams) -> Assessment:
    """An assessment whose radar ``R`` knows its whole coverage from the start (so that the
    plain form, which has no coverage, counts the same scans)."""
    assessment = Assessment(params)
    radar = assessment.assessments["R"] = RadarAssessment("R", params)
    radar.coverage[:] = True
    assessment.sites["R"] = SITE
    return assessment


def test_reference_interpolation_is_the_plain_linear_form() -> None:
    refs = ReferenceHistory(history_s=100.0, max_report_gap_s=5.0)
    rng = np.random.default_rng(1)
    ids = np.array(["a", "b", "c"] * 20)
    t = np.repeat(np.arange(20.0), 3) + rng.uniform(0, 0.5, 60)
    ecef = rng.normal(0, 1e6, (60, 3))
    fl = rng.uniform(100, 300, 60)
    refs.add(t, ids, ecef, fl, np.array(["1234"] * 60, dtype=object))
    refs.index(25.0)
    q_ids = ["a", "b", "c", "a", "zz"]
    q_t = np.array([3.3, 7.9, 19.9, -1.0, 5.0])
    got = refs.at(refs.known(q_ids), q_t)
    for i, (name, when) in enumerate(zip(q_ids, q_t, strict=True)):
        rows = [j for j in range(60) if ids[j] == name]
        rows.sort(key=lambda j: t[j])
        before = [j for j in rows if t[j] <= when]
        after = [j for j in rows if t[j] >= when]
        if not before or not after:
            assert not got.ok[i]
            continue
        j0, j1 = before[-1], after[0]
        w = 0.0 if t[j1] == t[j0] else (when - t[j0]) / (t[j1] - t[j0])
        assert got.ok[i]
        np.testing.assert_allclose(got.ecef[i], (1 - w) * ecef[j0] + w * ecef[j1], rtol=1e-12)
        assert got.flight_level[i] == pytest.approx((1 - w) * fl[j0] + w * fl[j1])


def test_window_figures_are_the_plain_form_of_every_plot() -> None:
    scene = make_scene()
    duration = 400.0
    plots = make_plots(scene, duration, pd=0.8)
    params = AssessmentParams(window_s=10_000.0, median_plots=100_000, max_gap_s=300.0, history_s=320.0)
    assessment = covered_assessment(params)
    feed(assessment, scene, plots, duration)
    ref = reference_form(scene, plots)
    got = assessment.view.of("R")
    assert got["position"]["plots"] == ref["plots"]  # every plot found its aircraft
    assert got["detection"]["expected"] == ref["expected"]
    assert got["detection"]["pd"] == pytest.approx(ref["pd"], abs=1e-4)
    pos = got["position"]
    for name in ("rms_m", "median_m", "rms_uncorrected_m", "range_rms_m"):
        assert pos[name] == pytest.approx(ref[name], abs=0.06), name
    assert pos["azimuth_rms_deg"] == pytest.approx(ref["azimuth_rms_deg"], abs=1e-4)
    assert got["mode_3a"]["rate"] == pytest.approx(ref["mode_3a"], abs=1e-4)
    assert got["mode_c"]["rate"] == pytest.approx(ref["mode_c"], abs=1e-4)
    # and the plain form is what was simulated
    assert abs(ref["pd"] - 0.8) < 3 * math.sqrt(0.16 / ref["expected"])
    assert ref["range_rms_m"] == pytest.approx(100.0, rel=0.1)
    assert ref["b_r"] == pytest.approx(250.0, abs=15.0) and ref["b_a"] == pytest.approx(0.3, abs=0.02)
    d = got["detection"]
    assert d["pd_sigma"] == pytest.approx(math.sqrt(d["pd"] * (1 - d["pd"]) / d["expected"]), abs=1e-4)


def test_learnt_coverage_leaves_pd_unbiased_and_the_verdict_follows_the_requirements() -> None:
    scene = make_scene(n=20, seed=8)
    plots = make_plots(scene, 600.0, pd=0.9, seed=9)
    req = Requirements(pd_min=0.95, mode_3a_min=0.9, mode_c_min=0.95)
    assessment = Assessment(AssessmentParams(requirements=req))
    feed(assessment, scene, plots, 600.0)
    got = assessment.view.of("R")
    assert got["detection"]["pd"] == pytest.approx(0.9, abs=0.03)
    assert got["verdict"] == {"pd": False, "mode_3a": True, "mode_c": False}
    assert got["requirements"] == {"pd_min": 0.95, "mode_3a_min": 0.9, "mode_c_min": 0.95}
    assert got["references"] == ["ads-b"] and got["aircraft"] == 20


def test_figures_do_not_depend_on_how_the_input_is_cut() -> None:
    """Data-time steps: the same figures whether batches are 1 s or 3 s and however often
    ``advance`` is called (replay = live)."""
    scene = make_scene()
    plots = make_plots(scene, 200.0, pd=0.85)
    a, b = Assessment(), Assessment()
    feed(a, scene, plots, 200.0, every=1.0)
    feed(b, scene, plots, 200.0, every=2.0)
    assert a.view.figures == b.view.figures
    assert a.view.of("R")["position"]["plots"] > 0


def test_nothing_is_held_without_a_reference_and_unknown_radars_have_empty_figures() -> None:
    assessment = Assessment()
    assessment.plots(
        "R", SITE, np.array([T0]), np.array([1e5]), np.array([10.0]), np.array([None]), np.array([1.0]), T0
    )
    assert not assessment.assessments and not assessment.advance(None)
    empty = assessment.view.of("R")
    assert empty["detection"]["pd"] is None and empty["position"]["rms_m"] is None
    assert empty["verdict"] == {"pd": None, "mode_3a": None, "mode_c": None}


def test_hostile_columns_cost_nothing() -> None:
    scene = make_scene(n=4)
    plots = make_plots(scene, 120.0, pd=1.0)
    assessment = Assessment()
    feed(assessment, scene, plots, 60.0)
    nan = np.array([np.nan, np.inf, T0 + 61.0])
    assessment.plots(
        "R",
        SITE,
        nan,
        np.array([np.nan, 1e5, -5.0]),
        np.array([1.0, np.nan, 720.0]),
        np.array([None, "x", 3], dtype=object),
        np.array([np.nan, 1e9, -1.0]),
        T0 + 62.0,
    )
    assessment.reference(
        "adsb-1",
        "adsb",
        np.array([np.nan]),
        np.array(["a00000"]),
        np.array([91.0]),
        np.array([0.0]),
        np.array([np.nan]),
        np.array([None], dtype=object),
        np.array([np.nan]),
        T0 + 62.0,
    )
    assessment.pairs("R", "never-seen", ["a00000"], T0 + 62.0)
    assessment.advance(None)
    assessment.finish()
    assert assessment.view.of("R")["position"]["plots"] > 0


# -- through the engine --------------------------------------------------------------------
def _adsb_stream(duration_s: float) -> list[tuple[str, bytes]]:
    from topofusion_lab.scenarios.simulator import AdsbSpec

    msgs = scenario_messages(
        "two-radar", duration_s=duration_s, adsb=(AdsbSpec("ads-b", identity=True),), targets=20
    )
    return msgs


def test_the_engine_assesses_each_radar_the_same_with_the_correlation_in_its_own_process() -> None:
    pytest.importorskip("topofusion_lab")
    msgs = _adsb_stream(150.0)
    views = []
    for process in (False, True):
        engine = Engine(EngineConfig(), correlation_process=process)
        try:
            for key, payload in msgs:
                engine.ingest(key, payload, receive_time_s=0.0)
            engine.flush()
            views.append(engine.snapshot().performance.figures)
        finally:
            engine.close()
    assert views[0] == views[1]
    fig = views[0]["A"]
    assert fig["detection"]["pd"] == pytest.approx(0.95, abs=0.04)  # the catalog radars' pd
    assert fig["mode_3a"] == {"checked": 0, "correct": 0, "rate": None}  # radar A sends no codes
    assert fig["position"]["range_rms_m"] == pytest.approx(200.0, rel=0.25)


def test_no_reference_source_costs_nothing_and_answers_nulls() -> None:
    msgs = scenario_messages("two-radar", duration_s=30.0)
    engine = Engine(EngineConfig())
    for key, payload in msgs:
        engine.ingest(key, payload)
    engine.flush()
    assert not engine.assessment.assessment.assessments
    snap = engine.snapshot()
    assert snap.radar_performance("A")["detection"]["pd"] is None  # type: ignore[index]
    assert snap.radar_performance("nope") is None


def test_settings_reach_the_assessment(monkeypatch: pytest.MonkeyPatch) -> None:
    from service.settings import Settings, engine_config

    monkeypatch.setenv("TOPOFUSION_PERFORMANCE_WINDOW_S", "300")
    monkeypatch.setenv("TOPOFUSION_PERFORMANCE_PD_MIN", "0.9")
    monkeypatch.setenv("TOPOFUSION_PERFORMANCE_MODE_3A_MIN", "0.97")
    monkeypatch.setenv("TOPOFUSION_PERFORMANCE_MODE_C_MIN", "0.95")
    params = engine_config(Settings()).assessment
    assert params.window_s == 300.0
    assert params.requirements == Requirements(pd_min=0.9, mode_3a_min=0.97, mode_c_min=0.95)
    assert replace(params, window_s=600.0, requirements=Requirements()) == AssessmentParams()
    json.dumps(Engine(EngineConfig(assessment=params)).snapshot().radar_performance("x"))
