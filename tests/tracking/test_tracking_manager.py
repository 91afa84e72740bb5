"""The tracker end to end: API, ids, truth carry, sector misses, and the monostatic goal."""

from __future__ import annotations

import numpy as np
import pytest

from service.evaluation.truth import TruthLabelledTracker
from service.tracking import DEFAULT_WINDOW_S, INITIATORS, make_tracker
from topofusion_lab.evaluation.initiation_monostatic import SITE, MonostaticScenario, run_monostatic, simulate


def test_unknown_initiator_is_a_clear_value_error() -> None:
    with pytest.raises(ValueError, match="logic"):
        make_tracker(SITE, initiator="nope")
    assert "logic" in INITIATORS and DEFAULT_WINDOW_S > 0


def test_tracks_ids_truth_and_covariance() -> None:
    scn = MonostaticScenario(n_targets=15, clutter_per_scan=20, scans=8)
    batches, truth, _ = simulate(scn, np.random.default_rng(11))
    tr = TruthLabelledTracker(make_tracker(SITE, id_prefix="A"))
    seen: set[str] = set()
    for plots, tb in batches:
        tr.update(plots, tb)
        tab = tr.tracks()
        assert len(set(tab.track_id.tolist())) == len(tab)
        seen |= set(tab.track_id.tolist())
    tab = tr.tracks()
    assert tab.confirmed.sum() >= 12
    conf = tab.take(tab.confirmed)
    assert all(t in truth.names for t in conf.truth_id)
    nums = sorted(int(s.split("-")[1]) for s in seen)
    assert nums[0] >= 1 and all(s.startswith("A-") for s in seen)
    assert np.all(np.linalg.eigvalsh(tab.covariance) > 0)
    np.testing.assert_allclose(tab.covariance, np.swapaxes(tab.covariance, 1, 2), atol=1e-6)
    assert np.all(tab.plots >= 3) and tr.window_plots >= 0


def test_deterministic() -> None:
    scn = MonostaticScenario(n_targets=10, clutter_per_scan=20, scans=6)
    batches, _, _ = simulate(scn, np.random.default_rng(12))
    out = []
    for _ in range(2):
        tr = make_tracker(SITE)
        for plots, tb in batches:
            tr.update(plots, tb)
        out.append(tr.tracks())
    np.testing.assert_array_equal(out[0].track_id, out[1].track_id)
    np.testing.assert_array_equal(out[0].position_ecef_m, out[1].position_ecef_m)


def test_monostatic_goal_logic() -> None:
    """Goal: 100 targets with clutter, completeness >= 95 %, false confirmed <= 2 %."""
    r = run_monostatic(MonostaticScenario(), "logic", seed=1)
    assert r.completeness >= 0.95
    assert r.false_ratio <= 0.02


@pytest.mark.parametrize("initiator", ["hough-velocity", "pg-hough", "classic-hough"])
def test_hough_initiators_in_the_streaming_tracker(initiator: str) -> None:
    """Local Hough initiation (clusters of the window's plots) confirms the targets."""
    scn = MonostaticScenario(n_targets=15, clutter_per_scan=20, scans=8)
    batches, truth, _ = simulate(scn, np.random.default_rng(13))
    tr = TruthLabelledTracker(make_tracker(SITE, initiator=initiator))
    for plots, tb in batches:
        tr.update(plots, tb)
    conf = tr.tracks().take(tr.tracks().confirmed)
    assert len(set(conf.truth_id.tolist()) & set(truth.names)) >= 12
    assert all(t in truth.names for t in conf.truth_id)
