"""The dense-formation study (lab/topofusion_lab/evaluation/dense.py): its scoring on
hand-built cases, the Stone Soup peer's causal reading, and a tiny end-to-end run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.correlation import CorrelationParams
from service.correlation.cycles import CycleParams
from service.geo import Site
from service.tracking.base import TrackTable
from topofusion_lab.evaluation import dense


def _table(
    ids: list[str],
    truth: list[str],
    confirmed: list[bool],
    xy: list[tuple[float, float]],
    site: Site,
    time_s: float = 0.0,
) -> TrackTable:
    n = len(ids)
    enu = np.array([[x, y, 9_000.0] for x, y in xy]) if n else np.empty((0, 3))
    return TrackTable(
        track_id=np.array(ids, dtype=str),
        confirmed=np.array(confirmed, dtype=bool),
        time_s=np.full(n, time_s),
        position_ecef_m=site.enu_to_ecef(enu) if n else np.empty((0, 3)),
        velocity_ecef_mps=np.zeros((n, 3)),
        covariance=np.tile(np.eye(6), (n, 1, 1)),
        plots=np.full(n, 3, dtype=np.int64),
        truth_id=np.array(truth, dtype=object),
    )


SITE = Site("O", 31.0, 118.0, 0.0)


def test_rates_count_correct_over_common_and_false_over_confirmed() -> None:
    xy = [(0.0, 0.0)] * 4
    # Scan 1 (t=10): A1..A3 confirmed; B3 tentative.  Scan 2 (t=20): B3 confirmed too.
    a = _table(["A1", "A2", "A3", "A4"], ["T1", "T2", "T3", "T4"], [True, True, True, False], xy, SITE)
    b1 = _table(["B1", "B2", "B3"], ["T1", "T2", "T3"], [True, True, False], xy[:3], SITE)
    b2 = _table(["B1", "B2", "B3"], ["T1", "T2", "T3"], [True, True, True], xy[:3], SITE)
    scorer = dense.Scorer(ratio=2.0)
    rec = dense.Records()
    scorer.see({"A": a, "B": b1}, 10.0)
    # Common: T1, T2 (T3 tentative on B, T4 tentative on A).  One right pair, one false.
    scorer.score(
        rec,
        ("A", "B"),
        {"A": a, "B": b1},
        10.0,
        [("A1", "B1"), ("A2", "B3")],
        [("A1", "B1", 0.9), ("A2", "B3", 0.2)],
    )
    assert dense.rates(rec) == (0.5, 0.5, 2, 2)
    scorer.see({"A": a, "B": b2}, 20.0)
    # Common: T1, T2, T3 (ages 10, 10, 0); all three pairs right.
    scorer.score(rec, ("A", "B"), {"A": a, "B": b2}, 20.0, [("A1", "B1"), ("A2", "B2"), ("A3", "B3")])
    assert sorted(rec.common_age) == [0.0, 0.0, 0.0, 10.0, 10.0]
    assert dense.rates(rec) == (4 / 5, 1 / 5, 5, 5)
    # Only the second scan's pairs are >= 5 s old except A3-B3 (confirmed on B at t=20).
    assert dense.rates(rec, age_min=5.0) == (1.0, 0.0, 2, 2)
    # Other spacing ratios select nothing.
    c, f, common, conf = dense.rates(rec, ratio_min=3.0)
    assert (common, conf) == (0, 0) and np.isnan(c) and np.isnan(f)
    # Calibration: scores 0.9 (right) and 0.2 (wrong).
    assert dense.brier(rec) == pytest.approx((0.1**2 + 0.2**2) / 2)
    mean_s, frac, count = dense.reliability(rec)
    assert count[9] == 1 and count[2] == 1 and count.sum() == 2
    assert frac[9] == 1.0 and frac[2] == 0.0 and mean_s[9] == pytest.approx(0.9)


def test_stonesoup_pairs_are_confirmed_at_the_third_hit_and_end_at_the_second_miss() -> None:
    frames = []
    for k in range(10):
        a = _table(["A1", "A2"], ["T1", "T2"], [True, True], [(0.0, 0.0), (20_000.0, 0.0)], SITE, 10.0 * k)
        away = 5_000.0 if k in (5, 6) else 0.0  # B2 leaves the threshold at scans 5 and 6
        b = _table(["B1", "B2"], ["T1", "T2"], [True, True], [(100.0, 0.0), (20_000.0, away)], SITE, 10.0 * k)
        frames.append(({"A": a, "B": b}, 10.0 * k))
    as_is, one = dense.stonesoup_pairs(frames, ("A", "B"), SITE, threshold_m=1_000.0)
    assert as_is == one
    for k in range(10):
        want = set()
        if k >= 2:
            want.add(("A1", "B1"))
        # Hits at 0-4: confirmed from 2; misses at 5 (first) and 6 (second: ended), so
        # confirmed through 5; hits again at 7, 8, 9: confirmed again at 9.
        if 2 <= k <= 5 or k == 9:
            want.add(("A2", "B2"))
        assert set(one[k]) == want, k


def test_stonesoup_one_to_one_keeps_the_longer_association() -> None:
    frames = []
    for k in range(8):
        a = _table(["A1"], ["T1"], [True], [(0.0, 0.0)], SITE, 10.0 * k)
        ids, truth, xy = ["B1"], ["T1"], [(200.0, 0.0)]
        if k >= 3:  # B2 appears later, also within the threshold of A1
            ids, truth, xy = ["B1", "B2"], ["T1", "T2"], [(200.0, 0.0), (-200.0, 0.0)]
        b = _table(ids, truth, [True] * len(ids), xy, SITE, 10.0 * k)
        frames.append(({"A": a, "B": b}, 10.0 * k))
    as_is, one = dense.stonesoup_pairs(frames, ("A", "B"), SITE, threshold_m=1_000.0)
    assert set(as_is[7]) == {("A1", "B1"), ("A1", "B2")}
    assert all(p == [("A1", "B1")] for p in one[2:])


def test_update_scan_updates_every_radar_pair() -> None:
    seen = []

    class Fake:
        """A correlator that records its updates (the cycle step off: no books to join)."""

        params = CorrelationParams(cycles=CycleParams(enabled=False))

        def __init__(self, key: tuple[str, str]) -> None:
            self.key = key

        def update(self, ta: TrackTable, tb: TrackTable, t: float, implied: object = None) -> None:
            seen.append((self.key, ta, tb, t))

    tables = {r: TrackTable.empty() for r in "ABC"}
    keys = dense.radar_pairs(["A", "B", "C"])
    assert keys == [("A", "B"), ("A", "C"), ("B", "C")]
    dense.update_scan({k: Fake(k) for k in keys}, tables, 40.0)
    assert [(k, ta is tables[k[0]], tb is tables[k[1]], t) for k, ta, tb, t in seen] == [
        (k, True, True, 40.0) for k in keys
    ]


def test_unbiased_wide_formation_is_paired_by_nearest_neighbour() -> None:
    """The simulator and scoring end to end: no biases, spacing far above the track errors."""
    scene = dense.DenseScene(aircraft=10, ratio=20.0, seed=(7, 0, 0), scans=12, bias_scale=0.0)
    res = dense.run_scene(scene, thresholds=(1_000.0,))
    correct, false, common, _ = dense.rates(res.records["nearest"], age_min=30.0)
    assert common > 100
    assert correct >= 0.9 and false == 0.0
    assert res.spacing_m == pytest.approx(20.0 * res.cross_range_m)


def test_tiny_run_writes_figures_and_tables(tmp_path: Path) -> None:
    md = dense.run(tmp_path, runs=1, seed=3, progress=lambda m: None, ratios=(4.0,), scans=8, workers=1)
    for name in ("dense_vs_spacing.png", "dense_vs_age.png", "dense_reliability.png"):
        assert (tmp_path / name).stat().st_size > 1000, name
    assert "## Dense formations" in md
    assert "| 4 |" in md and "Brier score" in md
    for label in dense.labels():
        assert label in md


def test_goal_from_is_the_smallest_ratio_after_which_every_ratio_meets_the_goal() -> None:
    ok, bad = (0.96, 0.01, 1, 1), (0.5, 0.01, 1, 1)
    noisy = (0.99, 0.05, 1, 1)  # correct enough, too many false
    assert dense.goal_from([bad, ok, ok], (1.0, 2.0, 3.0)) == "2"
    assert dense.goal_from([ok, noisy, ok], (1.0, 2.0, 3.0)) == "3"
    assert dense.goal_from([ok, ok, bad], (1.0, 2.0, 3.0)) == "not met up to 3"


@pytest.mark.slow
def test_score_is_calibrated_on_held_out_formations() -> None:
    """The calibration was fitted on other seeds (EvidenceParams): on these formations the
    scores of the pairs with accumulated evidence match how often they are right."""
    from service.correlation.pairkeys import find

    scores: list[float] = []
    right: list[bool] = []
    for k, ratio in enumerate((2.0, 3.0)):
        scene = dense.DenseScene(aircraft=30, ratio=ratio, seed=(101, k, 0), scans=30)
        setup = dense.draw_scene(scene)
        sites = {r.site.site_id: r.site for r in setup.radars}
        keys = dense.radar_pairs(list(sites))
        corr = {key: dense.PairCorrelator("svd-topology", sites[key[0]], sites[key[1]]) for key in keys}
        for tables, t in dense.simulate(setup):
            dense.update_scan(corr, tables, t)
            for (a, b), c in corr.items():
                ev = c.evidence
                assert ev is not None
                have = find(ev.keys, c.book.keys) >= 0
                truth_a = dict(zip(tables[a].track_id, tables[a].truth_id, strict=True))
                truth_b = dict(zip(tables[b].track_id, tables[b].truth_id, strict=True))
                for i in np.flatnonzero(have):
                    scores.append(float(c.book.score[i]))
                    right.append(truth_a.get(c.book.track_a[i]) == truth_b.get(c.book.track_b[i]))
    rec = dense.Records(score=scores, score_ok=right)
    assert len(scores) > 2_000
    assert dense.brier(rec) < 0.08
    mean_s, frac, count = dense.reliability(rec)
    well = count >= 200  # bins with enough pairs to judge
    assert well.sum() >= 2 and np.all(np.abs(mean_s[well] - frac[well]) < 0.15)
