"""The registration study's fused error (``topofusion_lab.evaluation.registration_model``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.geo import enu_rotation, geodetic_to_ecef
from topofusion_lab.evaluation import registration_model as rm

LAT, LON, ALT = 31.7, 118.9, 8000.0


def _truth_at() -> np.ndarray:
    return np.asarray(geodetic_to_ecef(LAT, LON, ALT), dtype=float).reshape(3)


def _offset(enu: tuple[float, float, float]) -> list[float]:
    """The truth moved by ``enu`` metres (east, north, up)."""
    return (_truth_at() + enu_rotation(LAT, LON) @ np.asarray(enu)).tolist()


def test_horizontal_error_leaves_out_the_vertical() -> None:
    assert rm.horizontal_error(_offset((30.0, 40.0, 0.0)), _truth_at()) == pytest.approx(50.0, abs=1e-6)
    assert rm.horizontal_error(_offset((30.0, 40.0, 500.0)), _truth_at()) == pytest.approx(50.0, abs=1e-6)
    assert rm.horizontal_error(_offset((0.0, 0.0, 500.0)), _truth_at()) == pytest.approx(0.0, abs=1e-6)


def test_fused_sample_scores_pure_confirmed_tracks_only() -> None:
    def track(sid: str, status: str, members: list[tuple[str, str]], enu: tuple[float, float, float]) -> dict:
        return {
            "system_track_id": sid,
            "status": status,
            "position_ecef_m": _offset(enu),
            "position_sigma_m": 20.0,
            "members": [{"radar_id": r, "track_id": t} for r, t in members],
        }

    body = {
        "time_s": 100.0,
        "system_tracks": [
            track("T-1", "confirmed", [("A", "A-1"), ("B", "B-1"), (rm.ADSB_ID, "x")], (60.0, 80.0, 30.0)),
            track("T-2", "confirmed", [("A", "A-2"), ("B", "B-2")], (3.0, 4.0, 0.0)),
            track("T-3", "confirmed", [("A", "A-3"), ("B", "B-3")], (1000.0, 0.0, 0.0)),  # mixed
            track("T-4", "tentative", [("C", "C-1")], (2000.0, 0.0, 0.0)),
        ],
    }
    label = {
        ("A", "A-1"): "T1",
        ("B", "B-1"): "T1",
        (rm.ADSB_ID, "x"): "T1",
        ("A", "A-2"): "T2",
        ("B", "B-2"): "T2",
        ("A", "A-3"): "T3",
        ("B", "B-3"): "T4",
        ("C", "C-1"): "T5",
    }
    res = rm.RunResult(0, 0, [])
    rm.fused_sample(res, body, label, lambda name, t: _truth_at())
    assert res.fused_err == pytest.approx([100.0, 5.0], abs=1e-6)
    assert res.fused_err_radar == pytest.approx([5.0], abs=1e-6)
    assert res.fused_tracks == {"T-1", "T-2"}
    assert (res.pure, res.mixed, res.updates) == (2, 1, 1)
    rms, p95, radar, tracks, purity = rm.fused_error([res])
    assert rms == pytest.approx(math.sqrt((100.0**2 + 5.0**2) / 2))
    assert p95 == pytest.approx(float(np.percentile([100.0, 5.0], 95.0)))
    assert radar == pytest.approx(5.0)
    assert (tracks, purity) == (2, pytest.approx(2 / 3))


def test_five_terms_lower_the_fused_error_of_a_biased_scene() -> None:
    """+-1000 ppm and +-1.5 s in the data, 90 s of one seed: the three-term model leaves the
    gains and time biases in the fused tracks (deterministic for the seed)."""
    large = next(c for c in rm.CONDITIONS if c.label == "+-1000 ppm, +-1.5 s, ADS-B 60 %")
    five = rm.run_one(rm.Job(0, large, 7, 90.0))
    three = rm.run_one(rm.Job(0, rm.replace(large, full_model=False), 7, 90.0))
    for res in (five, three):
        assert res.errors == 0
        assert res.updates > 10
        assert len(res.fused_tracks) >= 50
        assert res.fused_err and all(math.isfinite(e) for e in res.fused_err)
    rms5, _, radar5, _, purity5 = rm.fused_error([five])
    rms3, _, radar3, _, _ = rm.fused_error([three])
    assert purity5 >= 0.95
    assert rms5 == pytest.approx(math.sqrt(float(np.mean(np.square(five.fused_err)))))
    assert rms5 < 0.8 * rms3
    assert radar5 < 0.8 * radar3
    row = next(
        line for line in rm.markdown([rm.Job(0, large, 7, 90.0)], [five], 90.0) if "| 5 terms |" in line
    )
    assert row.rstrip(" |").endswith(f"{rm.fused_cells([five])}")
