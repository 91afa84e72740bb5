"""The lab's bounds on association in formations (``topofusion_lab.evaluation.formation_bounds``):
the trackers told whose plots are whose, through the engine, against the default tracker on the
same messages; and the true-position cost against a plain loop."""

from __future__ import annotations

import numpy as np
import pytest

from service.config import EngineConfig
from service.tracking import make_tracker
from service.tracking.base import PlotColumns
from service.tracking.measurement import plots_to_measurements
from service.tracking.params import TrackerParams
from topofusion_lab.evaluation import formation as fs
from topofusion_lab.evaluation.formation_bounds import BoundedTracker, RadarTruth, bounded_factory, main
from topofusion_lab.evaluation.initiation_monostatic import SITE, MonostaticScenario, simulate

POINT = fs.Point("2x", "lattice", 2.0)


def _run(variant: str) -> dict[str, float]:
    return fs.run_one(fs.Job(0, POINT, variant, 0, 1, 180.0, 10))


def test_the_truth_bound_takes_no_plot_of_another_aircraft_and_the_tracker_does() -> None:
    """10 aircraft 806 m apart, 180 s: the default tracker gives some of its tracks' plots to
    the wrong track; told the truth, none; told the true positions, or aided by the other
    radars' tracks, fewer than the tracker."""
    now, truth = _run("now"), _run("truth")
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
    assert main([*args, "--bound", "truth", "--no-hold"]) == 0
    out = capsys.readouterr().out
    assert "| 2x | tracker |" in out and "| 2x | truth |" in out and "true-position" not in out
    with pytest.raises(SystemExit):
        main([*args, "--offset-m", "-1"])
