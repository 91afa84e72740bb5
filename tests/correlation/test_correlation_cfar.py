"""CA-CFAR confidential association (service/correlation/cfar.py): reference forms, a sea scene,
a wide air scene (the ADS-B study's dropouts), and the stream's re-check of confirmed pairs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2

from service.correlation import cfar as cfar_module
from service.correlation.base import DecisionContext, PredictedTracks
from service.correlation.cfar import (
    CfarParams,
    bias_least_squares,
    ca_cfar_thresholds,
    cfar_associate,
    cfar_statistics,
    confident_pairs,
    consistent_pairs,
    distance_matrix,
    isolated_mutual_pairs,
    jump_log_bound,
    pair_chi2,
    polar_covariance,
    unambiguous,
)
from service.correlation.correlator import PairCorrelator
from service.correlation.external import CfarCorrelator
from service.geo import enu_to_polar
from tests.correlation_support import snapshot_of
from tests.reference_forms import (
    cfar_consistency_reference,
    cfar_jump_log_bound_reference,
    cfar_pair_chi2_reference,
)
from topofusion_lab.evaluation.correlation_scenario import make_sites
from topofusion_lab.evaluation.correlation_stream import (
    RadarBias,
    RadarTrackSim,
    StreamScenario,
    make_targets,
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


# -- covariance-based parts: plain reference forms -------------------------------------------


def _spd(rng: np.random.Generator, n: int, scale: np.ndarray) -> np.ndarray:
    """``n`` random symmetric positive definite 2x2 matrices, axis scales ``scale`` (m, deg)."""
    g = rng.normal(size=(n, 2, 2)) * scale[None, :, None]
    return np.einsum("nij,nkj->nik", g, g) + np.diag(scale**2 * 0.05)


def test_polar_covariance_is_the_jacobian_congruence() -> None:
    """``J P J^T`` with ``J`` the numerical derivative of ``[range, azimuth_deg]`` by ENU."""
    rng = np.random.default_rng(5)
    enu = np.column_stack([rng.uniform(-2e5, 2e5, 12), rng.uniform(-2e5, 2e5, 12), rng.uniform(0, 1.2e4, 12)])
    g = rng.normal(size=(12, 3, 3)) * 150.0
    cov = np.einsum("nij,nkj->nik", g, g)
    got = polar_covariance(enu, cov)
    h = 1e-3
    for k in range(12):
        jac = np.zeros((2, 3))
        for c in range(3):
            up, dn = enu[k].copy(), enu[k].copy()
            up[c] += h
            dn[c] -= h
            r1, a1, _ = enu_to_polar(up)
            r0, a0, _ = enu_to_polar(dn)
            jac[:, c] = [(r1 - r0) / (2 * h), ((a1 - a0 + 180.0) % 360.0 - 180.0) / (2 * h)]
        np.testing.assert_allclose(got[k], jac @ cov[k] @ jac.T, rtol=1e-5, atol=1e-12)


def test_jump_log_bound_matches_loop() -> None:
    rng = np.random.default_rng(6)
    s = np.sort(rng.uniform(0.0, 3000.0, 300))
    s1 = rng.uniform(20.0, 300.0, 300)
    s2 = s1 + rng.uniform(0.0, 800.0, 300)
    s1[::17] = 0.0  # no stated error: no constraint
    jumps = np.array([0, 3, 40, 41, 150, 299])
    np.testing.assert_allclose(
        jump_log_bound(s, s1, s2, jumps), cfar_jump_log_bound_reference(s, s1, s2, jumps.tolist()), rtol=1e-12
    )
    # Sigmas of a prefix only: the entries beyond it are left out of the product.
    np.testing.assert_allclose(
        jump_log_bound(s, s1[:50], s2[:50], jumps),
        cfar_jump_log_bound_reference(s, s1[:50], s2[:50], jumps.tolist()),
        rtol=1e-12,
    )
    assert np.all(jump_log_bound(s, s1[:50], s2[:50], jumps) >= jump_log_bound(s, s1, s2, jumps) - 1e-12)


@pytest.mark.parametrize("inflate", [True, False])
def test_consistent_pairs_match_loop(inflate: bool) -> None:
    rng = np.random.default_rng(7)
    n = 40
    cov = _spd(rng, n, np.array([150.0, 0.15]))
    bias = np.array([300.0, 0.4])
    x = bias + np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(n, 2))) * 1.6
    x[::9] += np.array([2500.0, -1.5])  # wrong pairs
    prm = CfarParams(inflate_to_residuals=inflate)
    gate = float(chi2.ppf(0.999, 2))
    got = consistent_pairs(x, cov, gate, prm)
    b, bc, q, passed, f = cfar_consistency_reference(x, cov, gate, inflate, prm.min_pairs_for_inflation)
    np.testing.assert_allclose(got.chi2, q, rtol=1e-9)
    np.testing.assert_array_equal(got.passed, passed)
    np.testing.assert_allclose(got.bias, b, rtol=1e-12)
    np.testing.assert_allclose(got.bias_cov, bc, rtol=1e-12)
    assert got.inflation == pytest.approx(f)
    assert not got.passed[::9].any()
    assert got.passed.sum() >= (n - 5 - 2 if inflate else (n - 5) // 2)
    assert (got.inflation > 1.0) == inflate  # errors 1.6 x their covariance: the gates widen


def test_consistent_pairs_small_sets() -> None:
    prm = CfarParams()
    one = consistent_pairs(np.array([[100.0, 0.2]]), np.eye(2)[None] * [[1e4], [1e-2]], 13.8, prm)
    assert one.passed.tolist() == [True] and one.chi2.tolist() == [0.0]  # nothing to test it against
    np.testing.assert_allclose(one.bias, [100.0, 0.2])
    empty = consistent_pairs(np.empty((0, 2)), np.empty((0, 2, 2)), 13.8, prm)
    assert empty.passed.size == 0 and np.isnan(empty.bias).all()


def test_pair_chi2_matches_loop() -> None:
    rng = np.random.default_rng(8)
    ref = np.column_stack([rng.uniform(5e3, 2.5e5, 9), rng.uniform(0.0, 360.0, 9)])
    comp = np.column_stack([rng.uniform(5e3, 2.5e5, 11), rng.uniform(0.0, 360.0, 11)])
    ref[0, 1], comp[0, 1] = 359.9, 0.05  # across north
    cr = _spd(rng, 9, np.array([20.0, 0.01]))
    cd = _spd(rng, 11, np.array([200.0, 0.2]))
    extra = _spd(rng, 1, np.array([10.0, 0.01]))[0]
    np.testing.assert_allclose(
        pair_chi2(ref, comp, cr, cd, extra), cfar_pair_chi2_reference(ref, comp, cr, cd, extra), rtol=1e-9
    )


def test_unambiguous_matches_loop() -> None:
    rng = np.random.default_rng(9)
    cost = rng.uniform(0.0, 14.0, (8, 10))
    cost[rng.random(cost.shape) < 0.6] = np.inf
    r, c = np.arange(8), rng.permutation(10)[:8]
    cost[r, c] = rng.uniform(0.0, 3.0, 8)
    got = unambiguous(cost, r, c, 6.0)
    for k in range(8):
        others = [cost[r[k], j] for j in range(10) if j != c[k]] + [
            cost[i, c[k]] for i in range(8) if i != r[k]
        ]
        assert got[k] == all(o - cost[r[k], c[k]] >= 6.0 for o in others)
    assert unambiguous(cost, r, c, 0.0).all()


def test_isolated_mutual_pairs_match_loop() -> None:
    rng = np.random.default_rng(10)
    d = rng.uniform(100.0, 10_000.0, (14, 12))
    count = 0
    for i in range(14):
        j = int(np.argmin(d[i]))
        if (
            int(np.argmin(d[:, j])) == i
            and 2 * d[i, j] < np.sort(d[i])[1]
            and 2 * d[i, j] < np.sort(d[:, j])[1]
        ):
            count += 1
    assert isolated_mutual_pairs(d, 2.0) == count


# -- implausible detections and the second stage's gates ---------------------------------------


def test_implausible_early_detection_is_passed_over() -> None:
    """A chance gap among the first same-source distances: the paper's first detection; passed
    over when the pairs' covariances make it implausible, or by the isolated-pair count."""
    rng = np.random.default_rng(12)
    same = np.concatenate([np.linspace(60.0, 70.0, 8), 250.0 + 1150.0 * np.linspace(0.0, 1.0, 92) ** 2])
    s = np.concatenate([same, np.sort(rng.uniform(3000.0, 40_000.0, 400))])
    thr = ca_cfar_thresholds(s)
    assert thr.detected and thr.jump_index == 7  # the gap after the eighth distance
    sig = np.full(s.size, 150.0)  # pairs with 150 m errors are rarely within 70 m, never eight
    by_cov = ca_cfar_thresholds(s, None, sig, sig)
    assert by_cov.jump_index == 99 and by_cov.passed_over >= 1
    assert by_cov.same_source_m == pytest.approx(same[-1])
    by_count = ca_cfar_thresholds(s, None, expected_pairs=100)
    assert by_count.jump_index == 99
    # Small errors make the early detection plausible: the paper's choice stands.
    tiny = np.full(s.size, 5.0)
    assert ca_cfar_thresholds(s, None, tiny, tiny).jump_index == 7


def air_scene(
    rng: np.random.Generator, n: int = 120
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ADS-B study's lone radar in polar terms: ``n`` aircraft over 240 km (the radar 100 km
    west of the centre, ranges up to 250 km), all equipped (reference: 20 m), the radar with bias
    227 m / 0.19 deg and track errors 150 m / 0.15 deg, covariances given.  Ids for evaluation."""
    xy = np.column_stack([rng.uniform(-20e3, 220e3, n), rng.uniform(-120e3, 120e3, n)])
    r = np.hypot(xy[:, 0], xy[:, 1])
    az = np.mod(np.degrees(np.arctan2(xy[:, 0], xy[:, 1])), 360.0)
    seen = np.flatnonzero((r <= 250e3) & (r >= 5e3))
    ref_az_sd = np.degrees(20.0 / r)
    ref = np.column_stack(
        [r + 20.0 * rng.standard_normal(n), np.mod(az + ref_az_sd * rng.standard_normal(n), 360)]
    )
    cref = np.zeros((n, 2, 2))
    cref[:, 0, 0], cref[:, 1, 1] = 20.0**2, ref_az_sd**2
    rad = np.column_stack(
        [
            r[seen] + 227.0 + 150.0 * rng.standard_normal(seen.size),
            np.mod(az[seen] + 0.19 + 0.15 * rng.standard_normal(seen.size), 360.0),
        ]
    )
    crad = np.zeros((seen.size, 2, 2))
    crad[:, 0, 0], crad[:, 1, 1] = 150.0**2, 0.15**2
    return ref, rad, cref, crad, np.arange(n), seen


def test_air_scene_far_pairs_pass_whatever_the_detection() -> None:
    """The study's dropouts: the paper's first detection comes early (a chance gap among the
    same-source distances, spread as range x azimuth bias), and a distance gate of one value
    fails the far pairs.  With each candidate gated by its own covariance every aircraft is
    paired, none wrongly."""
    found = common = early = 0
    for seed in range(6):
        ref, rad, cref, crad, ids_ref, ids_rad = air_scene(np.random.default_rng(seed))
        first = ca_cfar_thresholds(np.sort(distance_matrix(ref, rad), axis=None))
        early += first.jump_index < ids_rad.size // 2
        res = cfar_associate(ref, rad, None, cref, crad)
        ok = ids_ref[res.index_ref] == ids_rad[res.index_radar]
        assert ok.all(), res.reason
        found += int(ok.sum())
        common += ids_rad.size
        assert abs(res.range_bias_m - 227.0) < 30.0 and abs(res.azimuth_bias_deg - 0.19) < 0.04
    assert early >= 3  # the scene does provoke early detections
    assert found >= 0.98 * common


def test_close_targets_stay_undecided_rather_than_guessed() -> None:
    """Two aircraft 200 m apart at 180 km (cross-range error 470 m): the second stage leaves them
    undecided (``ambiguity_margin``); the paper's plain assignment may swap them."""
    ref, rad, cref, crad, ids_ref, ids_rad = air_scene(np.random.default_rng(23))
    res = cfar_associate(ref, rad, None, cref, crad)
    assert (ids_ref[res.index_ref] == ids_rad[res.index_radar]).all()
    plain = cfar_associate(ref, rad, CfarParams(ambiguity_margin=0.0), cref, crad)
    assert plain.index_ref.size > res.index_ref.size


def test_known_pairs_carry_the_bias_and_keep_their_tracks() -> None:
    """Too few distances for a jump: the caller's known pair alone gives the bias; the known
    pair is not in the result and its tracks join no other pair."""
    ref = np.array([[20_000.0, 10.0], [60_000.0, 40.0], [90_000.0, 200.0]])
    rad = np.column_stack([ref[:, 0] + 400.0, ref[:, 1] + 0.5])
    assert not cfar_associate(ref, rad)  # 9 distances, no jump found
    res = cfar_associate(ref, rad, None, known_ref=np.array([0]), known_radar=np.array([0]))
    assert res.index_ref.tolist() == [1, 2] and res.index_radar.tolist() == [1, 2]
    assert res.range_bias_m == pytest.approx(400.0) and res.azimuth_bias_deg == pytest.approx(0.5)
    bad = cfar_associate(ref, rad, None, known_ref=np.array([0, 1]), known_radar=np.array([0, 0]))
    assert not bad and "two pairs" in bad.reason


# -- the correlator: re-check of confirmed pairs, reference rows --------------------------------


def _reference_snapshot(truth: np.ndarray, sigma: float, rng: np.random.Generator) -> PredictedTracks:
    n = len(truth)
    pos = truth + rng.normal(0.0, sigma, truth.shape)
    cov = np.broadcast_to(np.eye(3) * sigma**2, (n, 3, 3)).copy()
    return PredictedTracks(
        np.array([f"r{i}" for i in range(n)]),
        pos,
        np.zeros((n, 3)),
        cov,
        cov.copy(),
        None,
        pos,
        np.zeros((n, 3)),
    )


def _radar_and_reference(seed: int, n: int = 40) -> tuple[PredictedTracks, PredictedTracks]:
    rng = np.random.default_rng(seed)
    site, _ = make_sites()
    enu = np.column_stack(
        [rng.uniform(-20e3, 220e3, n), rng.uniform(-120e3, 120e3, n), rng.uniform(7e3, 12e3, n)]
    )
    truth = site.enu_to_ecef(enu)
    a = snapshot_of(site, truth, np.array([300.0, np.radians(0.3), 0.0]), rng, 150.0)
    return a, _reference_snapshot(truth, 20.0, rng)


def test_reverify_keeps_right_pairs_and_fails_a_swapped_one() -> None:
    a, b = _radar_and_reference(1)
    n = len(a)
    ia = np.arange(n, dtype=np.intp)
    ib = ia.copy()
    d = np.linalg.norm(b.position[:, None, :] - b.position[None, :, :], axis=2)
    far = int(np.argmax(d[0]))
    ib[[0, far]] = ib[[far, 0]]  # two confirmed pairs swapped between aircraft far apart
    corr = CfarCorrelator()
    dec = corr.reverify(a, b, ia, ib, DecisionContext(time_s=0.0))
    assert dec is not None
    wrong = np.zeros(n, dtype=bool)
    wrong[[0, far]] = True
    assert not dec.accepted[wrong].any()
    assert dec.accepted[~wrong].mean() >= 0.97  # 0.1 % per pair at keep_probability
    assert (dec.cost[dec.accepted] + 2.0 <= chi2.ppf(CfarParams().keep_probability, 2)).all()
    assert (dec.statistic == 1.0).all()
    few = corr.reverify(a, b, ia[:4], ib[:4], DecisionContext(time_s=0.0))
    assert few is None  # fewer than min_kept_pairs: every pair is decided afresh


def test_decide_honours_reference_rows_and_uses_kept_pairs() -> None:
    a, b = _radar_and_reference(2)
    n = len(a)
    kept = np.arange(0, n, 2, dtype=np.intp)  # rows 0, 2, ... kept by the re-check (same rows)
    free = np.arange(1, n, 2, dtype=np.intp)
    ctx = DecisionContext(time_s=0.0, confirmed_a=kept, confirmed_b=kept, reference_a=free, reference_b=free)
    dec = CfarCorrelator().decide(a, b, ctx)
    assert set(dec.index_a.tolist()) <= set(free.tolist()) and set(dec.index_b.tolist()) <= set(free.tolist())
    assert (dec.index_a == dec.index_b).all() and len(dec) >= 0.9 * free.size
    # The CA-CFAR itself finds nothing here (forced): the kept pairs alone give the bias.
    strict = CfarCorrelator(CfarParams(coefficient=1e9))
    assert not strict.decide(a, b, DecisionContext(time_s=0.0))
    again = strict.decide(a, b, ctx)
    assert (again.index_a == again.index_b).all() and len(again) >= 0.9 * free.size


def test_confirmed_pairs_survive_updates_where_the_cfar_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    """A right confirmed pair is not dropped because some updates' CA-CFAR found nothing: the
    re-check keeps it (before, ``drop_misses`` such updates in a row dropped every pair)."""
    sc = StreamScenario(sparse_targets=50, cluster_targets=0, confirm_scans=1, box_m=250_000.0)
    rng = np.random.default_rng(3)
    site, _ = make_sites()
    pos0, vel = make_targets(rng, sc, site)
    radar = RadarTrackSim(rng, site, RadarBias(400.0, 0.3, 0.0), len(pos0), sc)
    ref = RadarTrackSim(
        rng, site, RadarBias(0.0, 0.0, 0.0), len(pos0), dataclasses.replace(sc, track_noise_factor=0.1)
    )
    corr = PairCorrelator("cfar", site, None)
    fails = range(10, 10 + corr.params.book.drop_misses + 2)
    real = cfar_module.cfar_associate
    confirmed = []
    for k in range(22):
        t = 4.0 * k
        if k in fails:
            monkeypatch.setattr(cfar_module, "cfar_associate", lambda *_a, **_k: cfar_module._empty("forced"))
        else:
            monkeypatch.setattr(cfar_module, "cfar_associate", real)
        corr.update(radar.table(site, pos0, vel, t), ref.table(site, pos0, vel, t), t + 4.0)
        confirmed.append(int(np.count_nonzero(corr.book.confirmed)))
        if k in fails:
            assert corr.last_reverified >= 0.9 * confirmed[9]
    assert confirmed[9] >= 30
    assert min(confirmed[10:]) >= 0.9 * confirmed[9]
