"""The lab's bounds on association in formations (``topofusion_lab.evaluation.formation_bounds``):
the trackers told whose plots are whose, through the engine, against the default tracker on the
same messages; and the true-position cost against a plain loop."""

from __future__ import annotations

import numpy as np
import pytest

from service.config import EngineConfig
from service.correlation.partner_view import into_view
from service.tracking import make_tracker
from service.tracking.base import PlotColumns
from service.tracking.measurement import plots_to_measurements
from service.tracking.params import TrackerParams
from topofusion_lab.evaluation import formation as fs
from topofusion_lab.evaluation.formation_bounds import (
    BoundedTracker,
    RadarTruth,
    bounded_factory,
    main,
    registered_terms,
)
from topofusion_lab.evaluation.initiation_monostatic import SITE, MonostaticScenario, simulate
from topofusion_lab.scenarios.simulator import generate

POINT = fs.Point("2x", "lattice", 2.0)


def _run(variant: str) -> dict[str, float]:
    return fs.run_one(fs.Job(0, POINT, variant, 0, 1, 180.0, 10))


@pytest.mark.slow
def test_the_truth_bound_takes_no_plot_of_another_aircraft_and_the_tracker_does() -> None:
    """10 aircraft 806 m apart, 180 s: the tracker alone (the default without the aid of
    association) gives some of its tracks' plots to the wrong track; told the truth, none; told
    the true positions, or aided by the other radars' tracks, fewer than the tracker."""
    now, truth = _run("unaided"), _run("truth")
    assert now["joined_led"] > 100 and now["joined_other"] > 0
    assert truth["joined_led"] > 100 and truth["joined_other"] == 0
    for bound in ("true-position", "other-radar"):
        got = _run(bound)
        assert got["joined_led"] > 100 and got["joined_other"] < now["joined_other"], (bound, got, now)


def test_the_true_position_cost_is_a_plain_mahalanobis_distance_from_the_reference() -> None:
    batches, _, _ = simulate(
        MonostaticScenario(n_targets=5, clutter_per_scan=10, scans=2, sectors=1), np.random.default_rng(2)
    )
    plots = PlotColumns.concat([b for b, _ in batches])
    params = TrackerParams()
    meas = plots_to_measurements(SITE, plots, params.measurement)
    n = len(meas)
    places = {f"A{k}": SITE.enu_to_ecef(np.array([1000.0 * k, 40_000.0, 9_000.0])) for k in range(4)}

    def reference(names: object, t: np.ndarray) -> np.ndarray:
        out = np.array([places.get(str(name), np.full(3, np.nan)) for name in names])  # type: ignore[attr-defined]
        return out.reshape(len(t), 3)

    rng = np.random.default_rng(5)
    cols = rng.integers(0, n, 40)
    names = np.array([f"A{k}" for k in rng.integers(0, 5, 40)], dtype=object)  # A4: unknown
    uids = rng.integers(1, 6, 40).astype(np.int64)
    for offset_m in (0.0, 150.0):
        tracker = make_tracker(SITE, None, "logic", "M", params, kind=BoundedTracker)
        assert isinstance(tracker, BoundedTracker)
        tracker.truth = RadarTruth(reference, lambda ecef: ecef, lambda ecef: ecef)
        tracker.offset_m, tracker.seed = offset_m, 7
        got = tracker.reference_d2(uids, names, meas, cols)
        for i in range(40):
            if names[i] == "A4":
                assert got[i] == np.inf
                continue
            ref = SITE.ecef_to_enu(places[str(names[i])])
            if offset_m:
                ref = ref + np.r_[np.random.default_rng([7, int(uids[i])]).normal(0.0, offset_m, 2), 0.0]
            y = meas.enu_m[cols[i]] - ref
            want = float(y @ np.linalg.inv(meas.covariance[cols[i]]) @ y)
            assert got[i] == pytest.approx(want, rel=1e-9)


def test_a_bound_is_one_of_the_named_ones_and_the_command_prints_its_rows(
    capsys: pytest.CaptureFixture[str],
) -> None:
    nowhere = RadarTruth(lambda names, t: np.empty((0, 3)), lambda ecef: ecef, lambda ecef: ecef)
    with pytest.raises(ValueError, match="unknown bound 'oracle': one of truth, true-position, other-radar"):
        bounded_factory(EngineConfig(), "oracle", lambda radar, site: nowhere)
    args = ["--point", "2x", "--runs", "1", "--duration", "150", "--targets", "6", "--workers", "1"]
    assert main([*args, "--bound", "truth", "--bound", "paired-covariance", "--no-hold"]) == 0
    out = capsys.readouterr().out
    assert "| 2x | tracker |" in out and "| 2x | truth |" in out and "true-position" not in out
    assert "| 2x | paired-covariance |" in out
    with pytest.raises(SystemExit):
        main([*args, "--offset-m", "-1"])


def test_the_paired_bound_brings_a_partner_into_view_with_the_registered_terms() -> None:
    """Another radar's view of an aircraft, its registered terms taken out and this radar's put
    in (``paired``'s transform: the model's exact inverse, then its inverse with the terms'
    signs turned, right to first order), lands within a metre of where this radar sees the
    aircraft, for the formation's radars and biases; with no terms, hundreds of metres off."""
    sc = fs.scenario(POINT, 60.0)
    radars = {r.radar_id: r for r in sc.radars}
    sites = {rid: r.site() for rid, r in radars.items()}
    rng = np.random.default_rng(3)
    centre = sites["A"].enu_to_ecef(np.zeros(3))
    x = np.array([sites["A"].ecef_to_enu(centre)]) + rng.uniform(-60_000, 60_000, (50, 3)) * [1, 1, 0]
    x[:, 2] = 9_000.0
    ecef = sites["A"].enu_to_ecef(x)
    v = np.zeros_like(ecef)

    def terms(rid: str) -> np.ndarray:
        r = radars[rid]
        return registered_terms(
            {
                "range_bias_m": r.range_bias_m,
                "azimuth_bias_deg": r.azimuth_bias_deg,
                "elevation_bias_deg": r.elevation_bias_deg,
                "range_gain_ppm": r.range_gain_ppm,
                "time_bias_s": None,
            }
        )

    for own, peer in (("A", "C"), ("C", "B"), ("B", "A")):
        seen_by_peer = fs.apparent(radars[peer], sites[peer], ecef)
        want = fs.apparent(radars[own], sites[own], ecef)
        got = into_view(sites[peer], sites[own], seen_by_peer, v, terms(peer), terms(own))
        assert np.max(np.linalg.norm(got - want, axis=1)) < 1.0
        assert np.median(np.linalg.norm(seen_by_peer - want, axis=1)) > 200.0


def test_the_formation_in_traffic_keeps_its_aircraft_and_only_they_are_scored() -> None:
    """The lattice in traffic: the same formation (ids, start) among other aircraft; a run of it
    counts the formation's aircraft-samples exactly as the run without traffic does."""
    traffic = fs.Point("2x in traffic", "lattice", 2.0, traffic=8)
    plain_sc, busy_sc = fs.scenario(POINT, 150.0, 10), fs.scenario(traffic, 150.0, 10)
    assert busy_sc.targets == 18 and fs.focus_of(traffic, busy_sc) == {f"T{k}" for k in range(1, 11)}
    assert fs.focus_of(POINT, plain_sc) is None
    plain, busy = fs.TruthLog(plain_sc), fs.TruthLog(busy_sc)
    for log, sc in ((plain, plain_sc), (busy, busy_sc)):
        for m in generate(sc, 1, log):
            if m.kind == "plots":  # (the targets' first step is observed)
                break
    names, start = plain.aircraft(plain_sc.start_time_s)
    busy_names, _ = busy.aircraft(busy_sc.start_time_s)
    assert len(busy_names) == 18
    assert np.allclose(busy.ecef(names, np.full(len(names), busy_sc.start_time_s)), start)
    runs = [fs.run_one(fs.Job(0, p, "now", 0, 1, 150.0, 10)) for p in (POINT, traffic)]
    assert runs[0]["truths"] == runs[1]["truths"] > 0
    assert runs[1]["pairs_common"] <= runs[0]["pairs_common"] + 3 * 10


@pytest.mark.slow
def test_an_aid_from_further_back_than_the_run_is_no_aid() -> None:
    """``paired-covariance`` in traffic (10 aircraft in formation among 32 others, 240 s) with
    the correlation's answers as they come changes the association; taken an hour back
    (``aid_lag_s``) it has nothing to go by, and its tracks, plots and pairs are the default
    tracker's (the default without the aid of association), to the count."""
    point = fs.Point("2x in traffic", "lattice", 2.0, traffic=32)
    keys = ("joined_led", "joined_other", "switches", "tracked", "pairs_found", "pairs_false", "err2")

    def run(variant: str, lag_s: float) -> list[float]:
        got = fs.run_one(fs.Job(0, point, variant, 0, 1, 240.0, 10, aid_lag_s=lag_s))
        return [got[k] for k in keys]

    now = run("unaided", 0.0)
    assert run("paired-covariance", 0.0) != now
    assert run("paired-covariance", 3600.0) == now
