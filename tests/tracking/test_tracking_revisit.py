"""The revisit period a radar's plots show (service/tracking/revisit.py): the vectorised
measurement against a plain one, on a rotating radar's plots, and the meter's rules."""

from __future__ import annotations

import numpy as np
import pytest

from service.tracking.params import RevisitParams
from service.tracking.revisit import RevisitMeter, observed_period

P = RevisitParams()


def reference_period(xy: np.ndarray, t: np.ndarray, p: RevisitParams) -> tuple[float, int] | None:
    """The same measurement plot by plot: among the ``neighbours + 1`` plots nearest in space
    (itself included) within ``radius_m``, the nearest at least ``min_dt_s`` earlier."""
    gaps = []
    for i in range(len(t)):
        d = np.hypot(*(xy - xy[i]).T)
        near = [j for j in np.argsort(d, kind="stable")[: p.neighbours + 1] if d[j] <= p.radius_m]
        earlier = [j for j in near if t[i] - t[j] >= p.min_dt_s]
        if earlier:
            gaps.append(t[i] - t[earlier[0]])
    return (float(np.median(gaps)), len(gaps)) if len(gaps) >= p.min_samples else None


def rotating_radar(
    rng: np.random.Generator, period_s: float, aircraft: int, scans: int, pd: float, clutter: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Plots of a radar turning once per ``period_s``: each aircraft (straight, 150-300 m/s) seen
    when the beam passes its azimuth, with probability ``pd``, 150 m noise; ``clutter`` plots a
    scan uniformly over the cover."""
    pos = rng.uniform(-150e3, 150e3, (aircraft, 2))
    heading = rng.uniform(0, 2 * np.pi, aircraft)
    vel = rng.uniform(150, 300, aircraft)[:, None] * np.c_[np.cos(heading), np.sin(heading)]
    xy, t = [], []
    for k in range(scans):
        az = np.mod(np.arctan2(pos[:, 0], pos[:, 1]), 2 * np.pi)
        when = (k + az / (2 * np.pi)) * period_s
        at = pos + vel * when[:, None]
        seen = rng.random(aircraft) < pd
        xy.append(at[seen] + rng.normal(0, 150, (int(seen.sum()), 2)))
        t.append(when[seen])
        xy.append(rng.uniform(-150e3, 150e3, (clutter, 2)))
        t.append(rng.uniform(k * period_s, (k + 1) * period_s, clutter))
    order = np.argsort(np.concatenate(t))
    return np.concatenate(xy)[order], np.concatenate(t)[order]


@pytest.mark.parametrize("seed", range(6))
def test_the_vectorised_measurement_is_the_plain_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    xy, t = rotating_radar(rng, float(rng.uniform(1, 12)), int(rng.integers(5, 60)), 6, 0.8, clutter=3)
    p = RevisitParams(
        neighbours=int(rng.integers(1, 10)), radius_m=float(rng.uniform(1e3, 20e3)), min_samples=5
    )
    got, want = observed_period(xy, t, p), reference_period(xy, t, p)
    assert (got is None) == (want is None)
    if got is not None and want is not None:
        assert got[1] == want[1] and got[0] == pytest.approx(want[0], abs=1e-9)


@pytest.mark.parametrize(
    ("period_s", "aircraft", "pd", "clutter"), [(4.0, 200, 0.9, 0), (1.0, 60, 0.7, 20), (12.0, 400, 0.8, 50)]
)
def test_a_rotating_radar_shows_its_period(period_s: float, aircraft: int, pd: float, clutter: int) -> None:
    xy, t = rotating_radar(np.random.default_rng(1), period_s, aircraft, 8, pd, clutter)
    got = observed_period(xy, t, P)
    assert got is not None and got[0] == pytest.approx(period_s, rel=0.03)


def test_a_quiet_sky_measures_nothing_and_the_declared_period_stands() -> None:
    xy, t = rotating_radar(np.random.default_rng(2), 4.0, 3, 4, 1.0)
    assert observed_period(xy, t, P) is None
    meter = RevisitMeter(P)
    meter.add(xy, t, float(t[-1]))
    assert meter.observed_s is None and meter.period(1.0) == 1.0


def test_the_meter_keeps_the_declared_period_unless_the_plots_contradict_it() -> None:
    xy, t = rotating_radar(np.random.default_rng(3), 4.0, 200, 40, 0.9)
    meter = RevisitMeter(RevisitParams(max_plots=1_500))
    for lo in range(0, len(t), 60):  # batches of 60 plots, each at its newest plot's time
        meter.add(xy[lo : lo + 60], t[lo : lo + 60], float(t[lo : lo + 60].max()))
    assert meter.observed_s == pytest.approx(4.0, rel=0.03)
    assert meter.period(4.5) == 4.5  # within a quarter: the site's stands
    assert meter.period(1.0) == meter.observed_s  # off by 4x: the plots' is used
    assert meter.period(12.0) == meter.observed_s
    meter.clear()  # (the radar expired) its plots go, its measured period stays
    assert meter.period(1.0) == meter.observed_s
    off = RevisitMeter(RevisitParams(enabled=False))
    off.add(xy, t, float(t[-1]))
    assert off.observed_s is None and off.period(1.0) == 1.0
