"""The system-track study (lab/topofusion_lab/evaluation/system.py): its scoring on a hand-built
case with a known answer, the truth source, and a tiny end-to-end run."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from service.geo import Site, geodetic_to_ecef
from service.tracking.base import TrackTable
from topofusion_lab.evaluation import system

SITE = Site("A", 31.2, 118.5, 30.0)
P = geodetic_to_ecef(31.5, 119.0, 8000.0)  # every aircraft's true position (one point will do)


def track(
    sid: str,
    members: list[tuple[str, str]],
    offset: tuple[float, float, float],
    sigma: float,
    status: str = "confirmed",
) -> dict[str, Any]:
    return {
        "system_track_id": sid,
        "status": status,
        "position_ecef_m": (P + np.array(offset)).tolist(),
        "position_sigma_m": sigma,
        "members": [{"radar_id": r, "track_id": t} for r, t in members],
    }


def test_score_on_a_known_case() -> None:
    body = {
        "time_s": 1000.0,
        "system_tracks": [
            track("T-1", [("A", "a1"), ("B", "b1")], (30.0, 40.0, 0.0), 50.0),  # pure X: 50 m
            track("T-2", [("A", "a2"), ("B", "b2")], (0.0, 0.0, 0.0), 10.0),  # mixed Y + Z
            track("T-3", [("C", "c1")], (0.0, 0.0, 0.0), 10.0),  # clutter only
            track("T-4", [("A", "a3")], (0.0, 0.0, 100.0), 100.0),  # W (pure), not linked with T-5
            track("T-5", [("B", "b3")], (0.0, 0.0, 0.0), 10.0),  # W again: no true position known
            track("T-6", [("A", "a4")], (0.0, 0.0, 0.0), 10.0),  # V
            track("T-7", [("A", "a5")], (0.0, 0.0, 0.0), 10.0),  # V again, a second track of radar A
            track("T-8", [("C", "c2")], (0.0, 0.0, 0.0), 10.0, "tentative"),  # not scored
            track("T-9", [("A", "a6"), ("C", "c3")], (0.0, 0.0, 0.0), 10.0),  # mixed: S + clutter
            # mixed: R, R and a track of Q that now follows R (a radar track gone over to R)
            track("T-10", [("A", "a7"), ("B", "b7"), ("C", "c7")], (0.0, 0.0, 0.0), 10.0),
            # K only in two tentative system tracks (two radars' young tracks holding each other back)
            track("T-11", [("A", "a8")], (0.0, 0.0, 0.0), 10.0, "tentative"),
            track("T-12", [("B", "b8")], (0.0, 0.0, 0.0), 10.0, "tentative"),
        ],
    }
    label = {
        ("A", "a1"): "X",
        ("B", "b1"): "X",
        ("A", "a2"): "Y",
        ("B", "b2"): "Z",
        ("C", "c1"): None,
        ("A", "a3"): "W",
        ("B", "b3"): "W",
        ("A", "a4"): "V",
        ("A", "a5"): "V",
        ("C", "c2"): "U",
        ("A", "a6"): "S",
        ("C", "c3"): None,
        ("A", "a7"): "R",
        ("B", "b7"): "R",
        ("C", "c7"): "Q",
        ("A", "a8"): "K",
        ("B", "b8"): "K",
    }
    # U, K: a confirmed radar track in tentative system tracks only; O: in no system track at all
    seen = {"X", "Y", "Z", "W", "V", "U", "K", "O"}
    raw = {
        ("A", "a1"): P + np.array([300.0, 400.0, 0.0]),  # 500 m
        ("B", "b1"): P + np.array([0.0, 0.0, 500.0]),  # 500 m
        ("A", "a3"): P + np.array([0.0, 0.0, 1000.0]),  # 1000 m
        ("B", "b3"): P,  # no truth for W's second track (T-5): not scored
        ("A", "a4"): P + np.array([0.0, 0.0, 200.0]),
        ("A", "a5"): P + np.array([0.0, 0.0, 200.0]),
        ("C", "c7"): P + np.array([0.0, 0.0, 300.0]),  # 300 m from R, 10 km from Q
    }
    asked: list[tuple[str, float]] = []

    def true(name: str, t: float) -> np.ndarray | None:
        asked.append((name, t))
        if name == "W" and asked.count((name, t)) == 2:
            return None  # W's second system track (T-5): no true position
        return P + np.array([10_000.0, 0.0, 0.0]) if name == "Q" else P

    age = {("A", "a3"): 300.0, ("B", "b3"): 12.0, ("A", "a4"): 200.0, ("A", "a5"): 100.0}
    s = system.score(body, label, seen, raw, true, age, {("A", "a7"): 30.0})
    assert (s.tracks, s.pure, s.mixed, s.mixed_swapped, s.clutter) == (9, 5, 3, 1, 1)
    assert s.purity == pytest.approx(5 / 8)
    assert s.aircraft == 8  # X, Y, Z, W, V, S, R, Q
    assert (s.duplicated, s.dup_radar, s.dup_mixed, s.dup_unlinked) == (2, 1, 0, 1)
    assert s.duplicates == pytest.approx(2 / 8)
    # W's stray track (B/b3, of the track with fewer of its members: a tie, the first one kept)
    # is 12 s old; V's stray track is 100 s old
    assert sorted(s.stray_age) == [12.0, 100.0] and s.dup_young == 1
    assert (s.seen, s.covered, s.uncovered_mixed) == (8, 3, 2)
    assert (s.uncovered_held, s.uncovered_held_apart, s.uncovered_absent) == (2, 1, 1)
    assert s.coverage == pytest.approx(3 / 8)
    assert {t for _, t in asked} == {1000.0}
    # pure tracks with a truth: T-1 (50 m, 2 members), T-4 (100 m), T-6, T-7 (0 m); T-5 has none
    assert sorted(s.fused_err) == pytest.approx([0.0, 0.0, 50.0, 100.0])
    assert sorted(s.raw_err) == pytest.approx([200.0, 200.0, 500.0, 500.0, 1000.0])
    assert sorted(s.members) == [1, 1, 1, 2]
    assert (s.single_age, s.single_dup) == ([300.0, 200.0, 100.0], [True, True, True])
    assert sorted(s.track_raw) == pytest.approx([200.0, 200.0, 500.0, 1000.0])
    assert s.ratio_members(2) == pytest.approx(50.0 / 500.0)
    fused = math.sqrt((50.0**2 + 100.0**2) / 4)
    raw_rms = math.sqrt((2 * 200.0**2 + 2 * 500.0**2 + 1000.0**2) / 5)
    assert s.ratio == pytest.approx(fused / raw_rms)
    # e^2 / (3 sigma^2): 2500 / 7500, 10000 / 30000, 0, 0
    assert system.nees(s) == pytest.approx((1 / 3 + 1 / 3) / 4)
    kinds = [k for k, _ in s.cases]
    assert kinds.count("mixed") == 2
    assert kinds.count("uncovered, in tentative system tracks only") == 2
    swap = next(t for k, t in s.cases if k == "mixed, a member now following the track's aircraft")
    assert "a7=R (last plot 30 s before)" in swap and "c7 is 0.3 km from R, 10.0 km from Q" in swap
    assert kinds.count("largest fused error") == 4
    assert next(t for k, t in s.cases if k == "largest fused error").startswith("100 m, sigma 100 m: T-4")
    assert "duplicate: radar track duplicate" in kinds
    assert "duplicate: tracks of different radars not linked" in kinds
    # what-if: one-member tracks of radar tracks younger than 150 s held back (T-5, T-7)
    held = system.score(body, label, seen, raw, true, age, hold_young_s=150.0)
    assert (held.tracks, held.duplicated, held.covered) == (7, 0, 3)
    # pooled, two of it: the same rates, twice the counts
    both = system.merge([s, s])
    assert (both.snapshots, both.tracks, both.purity, both.coverage) == (2, 18, s.purity, s.coverage)
    v = system.verdict([s])
    assert v.purity == (False, False) and v.coverage == (False, False)


def test_snapshot_inputs_labels_and_predicts() -> None:
    n = 3
    pos = SITE.enu_to_ecef(np.array([[0.0, 50_000.0, 5000.0], [10_000.0, 0.0, 5000.0], [0.0, 0.0, 1000.0]]))
    table = TrackTable(
        track_id=np.array(["A-1", "A-2", "A-3"]),
        confirmed=np.array([True, False, True]),
        time_s=np.array([98.0, 100.0, 99.0]),
        position_ecef_m=pos,
        velocity_ecef_mps=np.tile([100.0, 0.0, 0.0], (n, 1)),
        covariance=np.tile(np.eye(6), (n, 1, 1)),
        plots=np.full(n, 5, dtype=np.int64),
        truth_id=np.array(["T1", "T2", None], dtype=object),
    )
    got = system.snapshot_inputs({"A": table}, 100.0, 1.0, {"A": 4.0})
    assert got.label == {("A", "A-1"): "T1", ("A", "A-2"): "T2", ("A", "A-3"): None}
    assert got.seen == {"T1"}  # T2 only tentative, A-3 clutter
    assert got.raw[("A", "A-1")] == pytest.approx(pos[0] + np.array([200.0, 0.0, 0.0]))
    assert got.raw[("A", "A-2")] == pytest.approx(pos[1])
    assert got.age_s == {("A", "A-1"): 20.0, ("A", "A-2"): 20.0, ("A", "A-3"): 20.0}
    assert got.stale_s == {("A", "A-1"): 2.0, ("A", "A-2"): 0.0, ("A", "A-3"): 1.0}


def test_truth_interpolates_and_extrapolates() -> None:
    truth = system.Truth(keep_s=5.0)
    for t in range(10, 20):
        lat = 31.0 + 0.001 * t  # straight, at constant speed
        truth.add(
            {
                "reports": {
                    "time_s": [float(t), float(t)],
                    "icao24": ["abc", "def"],
                    "latitude_deg": [lat, 30.0],
                    "longitude_deg": [119.0, 119.0],
                    "altitude_m": [9000.0, 9000.0],
                }
            }
        )
    want = geodetic_to_ecef(31.0 + 0.001 * 17.25, 119.0, 9000.0)
    assert truth.position("abc", 17.25) == pytest.approx(want, abs=0.05)
    ahead = geodetic_to_ecef(31.0 + 0.001 * 19.5, 119.0, 9000.0)
    assert truth.position("abc", 19.5) == pytest.approx(ahead, abs=0.05)
    assert truth.position("abc", 10.5) is None  # forgotten (older than keep_s)
    assert truth.position("xyz", 17.0) is None


def test_a_tiny_run(tmp_path: Path) -> None:
    tiny = (system.Condition("three-radar, tiny", "three-radar", 70.0),)
    md = system.run(tmp_path, runs=1, seed=3, progress=lambda _: None, conditions=tiny, workers=1)
    assert "## System tracks" in md and "### Goals" in md
    assert "three-radar, tiny, final" in md
    assert (tmp_path / "system_vs_time.png").is_file()
    assert (tmp_path / "system_errors.png").is_file()
