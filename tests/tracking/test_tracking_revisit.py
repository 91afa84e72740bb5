"""The revisit period a radar's plots show (service/tracking/revisit.py): the vectorised
measurement against a plain one, on a rotating radar's plots, and the meter's rules."""

from __future__ import annotations

import numpy as np
import pytest

from service.tracking.params import RevisitParams
from service.tracking.revisit import RevisitMeter, contradicted, gaps, observed_period

P = RevisitParams()


def measured(xy: np.ndarray, t: np.ndarray, p: RevisitParams = P) -> tuple[float, int] | None:
    return observed_period(np.sort(gaps(xy, t, p)), p)


def reference_period(xy: np.ndarray, t: np.ndarray, p: RevisitParams) -> tuple[float, int] | None:
    """The same measurement plot by plot and gap by gap: the gaps to the ``neighbours + 1``
    plots nearest in space (itself included) within ``radius_m`` and at least ``min_dt_s``
    earlier; the span of ``peak_width`` holding most of them; a span at half of it holding at
    least half as many instead; none unless it holds ``prominence`` times the gaps half a period
    beyond it, which the gaps reach."""
    found = []
    for i in range(len(t)):
        d = np.hypot(*(xy - xy[i]).T)
        near = [j for j in np.argsort(d, kind="stable")[: p.neighbours + 1] if d[j] <= p.radius_m]
        found += [t[i] - t[j] for j in near if t[i] - t[j] >= p.min_dt_s]
    g = sorted(found)
    if len(g) < p.min_samples:
        return None
    best: list[float] = []
    for lo in g:
        inside = [x for x in g if lo <= x <= lo * (1 + p.peak_width)]
        if len(inside) > len(best):
            best = inside
    period, count = float(np.median(best)), len(best)
    while True:
        half = [
            x for x in g if period / 2 / (1 + p.peak_width / 2) <= x < period / 2 * (1 + p.peak_width / 2)
        ]
        if len(half) < max(count / 2, p.min_samples):
            break
        period, count = float(np.median(half)), len(half)
    beyond = [
        x for x in g if 1.5 * period / (1 + p.peak_width / 2) <= x < 1.5 * period * (1 + p.peak_width / 2)
    ]
    if g[-1] < 1.5 * period * (1 + p.peak_width / 2) or p.prominence * len(beyond) > count:
        return None
    return (period, count) if count >= p.min_samples else None


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
    xy, t = rotating_radar(rng, float(rng.uniform(1, 12)), int(rng.integers(5, 40)), 6, 0.8, clutter=3)
    p = RevisitParams(
        neighbours=int(rng.integers(1, 10)), radius_m=float(rng.uniform(1e3, 20e3)), min_samples=5
    )
    got, want = measured(xy, t, p), reference_period(xy, t, p)
    assert (got is None) == (want is None)
    if got is not None and want is not None:
        assert got[1] == want[1] and got[0] == pytest.approx(want[0], abs=1e-9)


@pytest.mark.parametrize(
    ("period_s", "aircraft", "pd", "clutter"), [(4.0, 200, 0.9, 0), (1.0, 60, 0.7, 20), (12.0, 400, 0.8, 50)]
)
def test_a_rotating_radar_shows_its_period(period_s: float, aircraft: int, pd: float, clutter: int) -> None:
    xy, t = rotating_radar(np.random.default_rng(1), period_s, aircraft, 8, pd, clutter)
    got = measured(xy, t)
    assert got is not None and got[0] == pytest.approx(period_s, rel=0.03)


def test_a_formation_in_trail_two_looks_apart_keeps_the_declared_period() -> None:
    """Rows of three aircraft in trail, each where the one ahead was two looks before: a plot's
    nearest earlier plots are two and four looks old as often as one, so the gaps crowd at a
    multiple too; the declared period, with gaps at it, stands.  One too short is corrected."""
    period_s, speed, k = 6.0, 200.0, np.arange(20)
    heading = np.array([1.0, 0.0])
    xy, t = [], []
    for row in range(10):
        for a in range(3):  # aircraft a trails its row's leader by a * 2 looks of flight
            start = np.array([60e3, 20e3 + 8e3 * row]) - heading * speed * 2 * period_s * a
            t.append(k * period_s + 0.01 * a + 0.002 * row)
            noise = np.random.default_rng(10 * row + a).normal(0, 50, (20, 2))
            xy.append(start + np.outer(t[-1], heading * speed) + noise)
    g = np.sort(gaps(np.concatenate(xy), np.concatenate(t), P))
    seen = observed_period(g, P)
    assert seen is not None and min(abs(seen[0] - period_s), abs(seen[0] - 2 * period_s)) < 0.2
    assert not contradicted(g, seen, period_s, P)
    assert contradicted(g, seen, 2.0, P) and contradicted(g, seen, 1.0, P)


def test_a_quiet_sky_measures_nothing_and_the_declared_period_stands() -> None:
    xy, t = rotating_radar(np.random.default_rng(2), 4.0, 3, 4, 1.0)
    assert measured(xy, t) is None
    meter = RevisitMeter(P)
    meter.add(xy, t, float(t[-1]), 1.0)
    assert meter.observed_s is None and meter.period(1.0) == 1.0


def test_the_meter_keeps_the_declared_period_unless_the_plots_contradict_it() -> None:
    xy, t = rotating_radar(np.random.default_rng(3), 4.0, 200, 40, 0.9)
    meter = RevisitMeter(RevisitParams(max_plots=1_500))
    for lo in range(0, len(t), 60):  # batches of 60 plots, each at its newest plot's time
        meter.add(xy[lo : lo + 60], t[lo : lo + 60], float(t[lo : lo + 60].max()), 1.0)
    assert meter.observed_s == pytest.approx(4.0, rel=0.03)
    assert meter.period(1.0) == meter.observed_s  # too short: every track would die
    assert meter.period(4.5) == 4.5  # within a quarter: the site's stands
    assert meter.period(2.0) == meter.observed_s  # no gap at 2 s
    assert meter.period(12.0) == 12.0  # a whole multiple: its gaps are real, it stands
    assert meter.period(6.0) == meter.observed_s  # longer, but no gap at 6 s
    meter.clear()  # (the radar expired) its plots go, the decision for the declared one stays
    assert meter.period(6.0) == meter.observed_s
    assert meter.period(3.0) == 3.0  # a new declaration, and no plots to judge it by
    off = RevisitMeter(RevisitParams(enabled=False))
    off.add(xy, t, float(t[-1]), 1.0)
    assert off.observed_s is None and off.period(1.0) == 1.0
