"""A radar's sigmas grown when its tracks' innovations say they are too small
(service/tracking/noise.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from service.geo import Site
from service.tracking.noise import NIS_MEDIAN, NoiseMeter, next_scale
from service.tracking.params import NoiseParams

P = NoiseParams()


def test_the_consistent_median_is_chi_square_with_three_degrees() -> None:
    assert pytest.approx(chi2.median(3), rel=1e-6) == NIS_MEDIAN


def test_the_scale_grows_by_the_innovations_and_shrinks_back_never_below_one() -> None:
    assert next_scale(1.0, 2.4, P) == 1.0 and next_scale(1.0, 4.0, P) == 1.0  # within the band
    assert next_scale(1.0, 4 * NIS_MEDIAN, P) == pytest.approx(2.0)  # sigmas half the truth
    assert next_scale(1.0, 100 * NIS_MEDIAN, P) == 2.0  # at most twice a step
    assert next_scale(8.0, 100 * NIS_MEDIAN, P) == P.max_scale
    assert next_scale(4.0, NIS_MEDIAN / 4, P) == pytest.approx(2.0)  # grown too far: back
    assert next_scale(1.2, 0.1, P) == 1.0 and next_scale(1.0, 0.1, P) == 1.0


def feed(
    meter: NoiseMeter, rng: np.random.Generator, variance: float, seconds: float, t0: float = 0.0
) -> float:
    """Batches of 20 associations a second whose NIS is chi-square(3) times ``variance`` (the
    true errors' variance over the ones measured with), as long as the scale leaves it so."""
    t = t0
    while t < t0 + seconds:
        meter.add(rng.chisquare(3, 20) * variance / meter.scale**2, t)
        t += 1.0
    return t


def test_sigmas_declared_a_third_of_the_truth_grow_to_it() -> None:
    meter, rng = NoiseMeter(P), np.random.default_rng(1)
    feed(meter, rng, 9.0, 300.0)
    assert meter.scale == pytest.approx(3.0, rel=0.35)
    declared = Site("B", 31.2, 120.6, 30.0, 100.0, 0.1, 0.1, 4.0)
    site = meter.site(declared)
    assert site.range_sigma_m == pytest.approx(100.0 * meter.scale)
    assert site.azimuth_sigma_deg == pytest.approx(0.1 * meter.scale)
    assert np.array_equal(site.rotation, declared.rotation) and meter.site(declared) is site


def test_an_honest_radar_keeps_its_sites_sigmas() -> None:
    meter, rng = NoiseMeter(P), np.random.default_rng(2)
    feed(meter, rng, 1.0, 600.0)
    feed(meter, rng, 1.6, 600.0, 600.0)  # a busier filter than consistent: still within the band
    declared = Site("A", 31.0, 121.0)
    assert meter.scale == 1.0 and meter.site(declared) is declared


def test_off_or_too_few_associations_change_nothing() -> None:
    off, rng = NoiseMeter(NoiseParams(enabled=False)), np.random.default_rng(3)
    feed(off, rng, 25.0, 300.0)
    assert off.scale == 1.0
    few = NoiseMeter(P)
    for t in range(0, 300, 10):
        few.add(rng.chisquare(3, 3) * 25.0, float(t))  # 30 associations in all
    assert few.scale == 1.0


def test_innovations_a_growth_does_not_bring_down_undo_it_and_hold() -> None:
    """Clutter in the gates: the NIS stays high whatever the sigmas (here it does not depend on
    the scale at all).  One growth, then the next reading shows it did nothing: back to the
    site's sigmas, and held there."""
    meter, rng = NoiseMeter(P), np.random.default_rng(4)
    t = 0.0
    while t < 600.0:
        meter.add(rng.chisquare(3, 20) * 4.0, t)
        t += 1.0
    assert meter.held and meter.scale == 1.0
