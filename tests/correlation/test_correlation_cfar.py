"""CA-CFAR confidential association (service/correlation/cfar.py): reference forms and a sea scene."""

from __future__ import annotations

import numpy as np
import pytest

from service.correlation.cfar import (
    CfarParams,
    bias_least_squares,
    ca_cfar_thresholds,
    cfar_associate,
    cfar_statistics,
    confident_pairs,
    distance_matrix,
)

# -- plain reference forms -------------------------------------------------------------------


def cfar_loop(diffs: np.ndarray, p: CfarParams) -> tuple[np.ndarray, np.ndarray]:
    mu = np.full(diffs.size, np.nan)
    det = np.zeros(diffs.size, dtype=bool)
    for k in range(diffs.size):
        window = [diffs[q] for q in range(k - p.guard_cells - p.reference_cells, k - p.guard_cells) if q >= 0]
        if len(window) >= p.min_reference_cells:
            mu[k] = sum(window) / len(window)
            det[k] = diffs[k] > p.coefficient * max(mu[k], np.finfo(float).tiny)
    return mu, det


def test_cfar_statistics_match_loop() -> None:
    rng = np.random.default_rng(1)
    diffs = rng.exponential(20.0, 60)
    diffs[25] = 900.0
    for p in (CfarParams(), CfarParams(reference_cells=3, guard_cells=1, min_reference_cells=2)):
        mu, det = cfar_statistics(diffs, p)
        mu_ref, det_ref = cfar_loop(diffs, p)
        np.testing.assert_allclose(mu, mu_ref, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(det, det_ref)


def test_thresholds_find_the_jump() -> None:
    same = np.linspace(500.0, 700.0, 15)
    different = np.linspace(3000.0, 40000.0, 50)
    thr = ca_cfar_thresholds(np.concatenate([same, different]))
    assert thr.detected
    assert thr.jump_index == 14
    assert thr.same_source_m == pytest.approx(700.0)
    assert thr.different_source_m == pytest.approx(3000.0)  # max(2 * 700, 3000)
    assert not ca_cfar_thresholds(np.linspace(0.0, 1.0, 40)).detected
    assert not ca_cfar_thresholds(np.array([5.0])).detected


def test_confident_pairs_match_loop() -> None:
    rng = np.random.default_rng(2)
    d = rng.uniform(1600.0, 10_000.0, (9, 11))
    d[2, 3], d[5, 7], d[6, 1] = 300.0, 400.0, 350.0
    d[6, 0] = 900.0  # track 6 has a second radar track within 1500 m: not confidential
    d[0, 4], d[1, 4] = 500.0, 1200.0  # radar track 4: a second reference within 1500 m
    ci, cj = confident_pairs(d, 1000.0, 1500.0)
    ref = []
    for i in range(9):
        j = int(np.argmin(d[i]))
        if int(np.argmin(d[:, j])) != i or d[i, j] > 1000.0:
            continue
        if np.sort(d[i])[1] > 1500.0 and np.sort(d[:, j])[1] > 1500.0:
            ref.append((i, j))
    assert list(zip(ci.tolist(), cj.tolist(), strict=True)) == ref
    assert (2, 3) in ref and (5, 7) in ref and (6, 1) not in ref and (0, 4) not in ref


def test_bias_least_squares_is_exact_and_wraps() -> None:
    ref = np.array([[10_000.0, 359.8], [25_000.0, 0.1], [40_000.0, 180.0]])
    rad = np.column_stack([ref[:, 0] + 321.0, np.mod(ref[:, 1] + 0.45, 360.0)])
    est = bias_least_squares(ref, rad)
    assert est.range_bias_m == pytest.approx(321.0, abs=1e-9)
    assert est.azimuth_bias_deg == pytest.approx(0.45, abs=1e-9)
    assert est.n_pairs == 3
    assert np.isnan(bias_least_squares(np.empty((0, 2)), np.empty((0, 2))).range_bias_m)


# -- sparse sea scene ------------------------------------------------------------------------

RANGE_BIAS_M, AZIMUTH_BIAS_DEG = 500.0, 0.5
RANGE_SIGMA_M, AZIMUTH_SIGMA_DEG = 30.0, 0.1


def sea_scene(rng: np.random.Generator, n: int = 30) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` vessels uniform over 100 x 100 km (east -50..50 km, north 10..110 km of the radar);
    80 % carry AIS (reference, true position), the radar holds a track on 90 %, with range bias
    500 m, azimuth bias 0.5 deg and track errors 30 m / 0.1 deg.  Ids are for evaluation only."""
    xy = np.column_stack([rng.uniform(-50e3, 50e3, n), rng.uniform(10e3, 110e3, n)])
    r = np.hypot(xy[:, 0], xy[:, 1])
    az = np.mod(np.degrees(np.arctan2(xy[:, 0], xy[:, 1])), 360.0)
    ais = np.flatnonzero(rng.random(n) < 0.8)
    rad = np.flatnonzero(rng.random(n) < 0.9)
    ref = np.column_stack([r[ais], az[ais]])
    meas = np.column_stack(
        [
            r[rad] + RANGE_BIAS_M + RANGE_SIGMA_M * rng.standard_normal(rad.size),
            np.mod(az[rad] + AZIMUTH_BIAS_DEG + AZIMUTH_SIGMA_DEG * rng.standard_normal(rad.size), 360.0),
        ]
    )
    return ref, meas, ais, rad


def test_sea_scene_recovery_and_bias() -> None:
    rng = np.random.default_rng(2015)
    correct = wrong = common = 0
    for _ in range(10):
        ref, meas, ids_ref, ids_rad = sea_scene(rng)
        res = cfar_associate(ref, meas)
        assert res, res.reason
        ok = ids_ref[res.index_ref] == ids_rad[res.index_radar]
        correct += int(ok.sum())
        wrong += int((~ok).sum())
        common += len(np.intersect1d(ids_ref, ids_rad))
        assert res.confident.any()
        assert res.same_source_threshold_m < res.different_source_threshold_m
        # Tolerance: 10 % of the bias, or 4 standard errors of a mean over the confidential pairs
        # (sigma / sqrt(n)), whichever is larger.
        n_conf = int(res.confident.sum())
        assert abs(res.range_bias_m - RANGE_BIAS_M) <= max(
            0.1 * RANGE_BIAS_M, 4 * RANGE_SIGMA_M / n_conf**0.5
        )
        assert abs(res.azimuth_bias_deg - AZIMUTH_BIAS_DEG) <= max(
            0.1 * AZIMUTH_BIAS_DEG, 4 * AZIMUTH_SIGMA_DEG / n_conf**0.5
        )
    print(f"CFAR sea scene: correct {correct / common:.3f} ({correct}/{common}), wrong {wrong}")
    assert correct / common >= 0.9
    assert wrong / (correct + wrong) <= 0.05


def test_compensation_removes_most_of_the_error() -> None:
    ref, meas, ids_ref, ids_rad = sea_scene(np.random.default_rng(3))
    res = cfar_associate(ref, meas)
    _, i, j = np.intersect1d(ids_ref, ids_rad, return_indices=True)  # true pairs (evaluation)
    before = distance_matrix(ref[i], meas[j]).diagonal()
    comp = meas[j] - np.array([res.range_bias_m, res.azimuth_bias_deg])
    after = distance_matrix(ref[i], comp).diagonal()
    print(f"CFAR registration: mean error {before.mean():.0f} m -> {after.mean():.0f} m")
    assert after.mean() < 0.3 * before.mean()  # the paper: nearly 90 % less error


def test_deterministic() -> None:
    ref, meas, _, _ = sea_scene(np.random.default_rng(4))
    r1, r2 = cfar_associate(ref, meas), cfar_associate(ref, meas)
    np.testing.assert_array_equal(r1.index_ref, r2.index_ref)
    assert r1.range_bias_m == r2.range_bias_m


@pytest.mark.parametrize(
    ("ref", "rad", "fragment"),
    [
        (np.empty((0, 2)), np.array([[1000.0, 10.0]]), "no tracks"),
        (np.array([[1000.0, 10.0]]), np.empty((0, 2)), "no tracks"),
        (np.array([[1000.0, 10.0]]), np.array([[1100.0, 10.0]]), "no same-source"),
        (np.array([[1000.0, np.nan]]), np.array([[1100.0, 10.0]]), "non-finite"),
        (np.ones((3, 3)), np.ones((3, 2)), "must be"),
        (np.array([[-5.0, 1.0]]), np.array([[5.0, 1.0]]), "negative range"),
        (np.tile([[20_000.0, 45.0]], (5, 1)), np.tile([[20_500.0, 45.5]], (5, 1)), "no same-source"),
    ],
)
def test_degenerate_inputs_give_empty_result(ref: np.ndarray, rad: np.ndarray, fragment: str) -> None:
    res = cfar_associate(ref, rad)
    assert not res
    assert res.index_ref.size == res.index_radar.size == res.confident.size == 0
    assert res.index_ref.dtype == np.intp
    assert fragment in res.reason
