"""Calibrated tests of the topology methods, their numerics against plain reference forms,
the cached registration normal equations and the data-time solve schedule."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
from scipy.stats import chi2

from service.correlation import PairCorrelator
from service.correlation.basic_topology import _sequence_chi2, basic_match, search_span
from service.correlation.gls import similarity_gls_batch
from service.correlation.registration import RegistrationMemory, RegistrationParams, solve_biases
from service.correlation.svd_topology import svd_match
from service.correlation.umeyama import yaw_matrix
from service.linalg import congruence, inv3, yaw_congruence
from tests.correlation_support import snapshot_of
from tests.reference_forms import sequence_chi2_reference, similarity_gls_reference
from topofusion_lab.evaluation.correlation_scenario import (
    Biases,
    around,
    make_sites,
    sample_references,
    single_match_batch,
)
from topofusion_lab.evaluation.correlation_stream import RadarTrackSim, StreamScenario, make_targets


def _spd(rng: np.random.Generator, shape: tuple[int, ...], scale: float) -> np.ndarray:
    a = rng.normal(size=(*shape, 3, 3))
    return (a @ np.swapaxes(a, -1, -2) + np.eye(3)) * scale


def test_gls_batch_matches_reference() -> None:
    rng = np.random.default_rng(0)
    p, k = 6, 5
    x = rng.normal(size=(p, k, 3)) * 5_000.0
    y = (x @ yaw_matrix(np.array(0.02)).T) * 1.01 + rng.normal(size=(p, k, 3)) * 300.0 + 50.0
    s = _spd(rng, (p, k), 1e5)
    w = np.ones((p, k))
    w[0, 4] = w[1, 0] = 0.0
    fit = similarity_gls_batch(x, y, w, inv3(s)[0], 0.03, np.radians(5.0))
    assert fit.valid.all()
    for i in range(p):
        m = w[i] > 0
        theta, cov, q, df = similarity_gls_reference(x[i][m], y[i][m], s[i][m], 0.03, np.radians(5.0))
        np.testing.assert_allclose(fit.theta[i], theta, rtol=1e-8, atol=1e-6)
        np.testing.assert_allclose(fit.cov[i], cov, rtol=1e-7, atol=1e-12)
        assert np.isclose(fit.q_residual[i] + fit.q_prior[i], q, rtol=1e-8)
        assert np.isclose(fit.df_model[i], df, rtol=1e-8)
        assert 3.0 < df < 5.0  # translation + partly determined yaw and scale


def test_gls_degenerate_is_flagged() -> None:
    x = np.zeros((1, 3, 3))
    eye = np.broadcast_to(np.eye(3), (1, 3, 3, 3))
    fit = similarity_gls_batch(x, x.copy(), np.zeros((1, 3)), eye, 0.03, 0.1)
    assert not fit.valid[0] and np.isnan(fit.q_residual[0])


def test_congruence_forms() -> None:
    rng = np.random.default_rng(1)
    s = rng.normal(size=(4, 6, 3, 3))
    r = rng.normal(size=(3, 3))
    np.testing.assert_allclose(congruence(r, s), r @ s @ r.T, atol=1e-12)
    yaw = rng.normal(size=4)
    rm = yaw_matrix(yaw)
    np.testing.assert_allclose(yaw_congruence(yaw, s), rm[:, None] @ s @ np.swapaxes(rm, 1, 2)[:, None])
    np.testing.assert_allclose(yaw_congruence(yaw, s[:, 0]), rm @ s[:, 0] @ np.swapaxes(rm, 1, 2))


def test_basic_joint_chi2_matches_dense_reference() -> None:
    rng = np.random.default_rng(2)
    p, k = 5, 4
    r = rng.normal(size=(p, k, 3)) * 500.0
    d = _spd(rng, (p, k), 1e5)
    c0 = _spd(rng, (p,), 1e5)
    valid = np.ones((p, k), dtype=bool)
    valid[0, 3] = False
    d_inv = np.where(valid[..., None, None], inv3(d)[0], 0.0)
    common = inv3(inv3(c0)[0] + d_inv.sum(1))[0]
    q = _sequence_chi2(r, valid, d_inv, common)
    for i in range(p):
        m = valid[i]
        assert np.isclose(q[i], sequence_chi2_reference(r[i][m], d[i][m], c0[i]), rtol=1e-8)


def _fig1(n: int, trials: int, seed: int, model: str = "disc"):
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    ba = Biases.random_sign(rng, trials, 100.0, 0.1)
    bb = Biases.random_sign(rng, trials, 100.0, 0.1)
    return single_match_batch(rng, a, b, n, trials, ba, bb, neighbour_model=model)[0]


def test_svd_statistics_calibrated_on_true_pairs() -> None:
    """Shape statistic ~ chi-square(effective dof), position ~ chi-square(3); size <= ~1 %."""
    m = _fig1(5, 400, 3)
    r = svd_match(m.pa, m.ca, m.ma, m.pb, m.cb, m.mb, m.m0)
    ok = np.isfinite(r.chi2_shape)
    assert ok.mean() > 0.97
    assert abs(np.mean(r.chi2_shape[ok] / r.dof_shape[ok]) - 1.0) < 0.15
    assert abs(np.mean(r.chi2_ref[ok]) - 3.0) < 0.5
    assert r.accepted.mean() >= 0.96


def test_basic_statistic_calibrated_without_order_errors() -> None:
    """Two neighbours far apart in azimuth cannot swap: the joint chi-square has mean ~3 n."""
    m = _fig1(2, 400, 4)
    za = m.pa[:, 1:] - m.pa[:, :1]
    az = np.arctan2(za[..., 0], za[..., 1])
    apart = np.abs(np.angle(np.exp(1j * (az[:, 0] - az[:, 1])))) > np.radians(60)
    rb = basic_match(m.pa, m.ca, m.ma, m.pb, m.cb, m.mb, m.m0, search_span(0.2, 200.0))
    q = rb.chi2[apart]
    assert abs(np.mean(q) / 6.0 - 1.0) < 0.15
    assert np.mean(q > chi2.ppf(0.99, 6)) < 0.03


def test_search_span_covers_the_differential_bias() -> None:
    p = search_span(0.2, 200.0)
    assert (p.max_azimuth_bias_deg, p.max_range_bias_m) == (0.25, 200.0)
    assert search_span(0.0, 0.0).max_azimuth_bias_deg == 0.25


def test_paper_neighbour_model_is_a_ball() -> None:
    rng = np.random.default_rng(5)
    a, b = make_sites()
    ref = sample_references(rng, a, b, 50)
    nb = around(rng, a, ref, 6, model="sphere")
    d = np.linalg.norm(nb - ref[:, None, :], axis=-1)
    assert d.max() <= 10_000.0 + 1e-6
    assert np.ptp(a.ecef_to_enu(nb.reshape(-1, 3))[:, 2]) > 8_000.0  # spans heights, not a disc


def _dense_solve(mem: RegistrationMemory, prior: np.ndarray, iterations: int = 1) -> np.ndarray:
    """Plain weighted least squares (tests only): stacked rows, one loop per row; the first
    iteration is the linear model's solution, later ones Gauss-Newton steps on the exact
    residual (each row's biases removed through its own polar coordinates)."""
    a_site, b_site = mem.site_a, mem.site_b
    assert b_site is not None
    rows, wts = [], []
    for i in range(len(mem.time)):
        rows.append(np.hstack([mem.g_a[i], -mem.g_b[i]]))
        wts.append(np.linalg.inv(mem.s[i]))
    h = np.diag(prior)
    for a_i, w_i in zip(rows, wts, strict=True):
        h += a_i.T @ w_i @ a_i
    bias = np.zeros(6)
    for _ in range(iterations):
        g = -prior * bias
        for i, (a_i, w_i) in enumerate(zip(rows, wts, strict=True)):
            pa, pb = [], []
            for site, p, b in ((a_site, mem.p_a[i], bias[:3]), (b_site, mem.p_b[i], bias[3:])):
                r, az, el = (float(np.ravel(x)[0]) for x in site.ecef_to_polar(p[None]))
                q = site.polar_to_ecef(r - b[0], az - np.degrees(b[1]), el - np.degrees(b[2]))
                (pa if site is a_site else pb).append(np.ravel(q))
            g += a_i.T @ w_i @ (pa[0] - pb[0])
        bias = bias + np.linalg.solve(h, g)
    return bias.reshape(2, 3)


def test_cached_normal_equations_match_dense_solve() -> None:
    rng = np.random.default_rng(6)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 60)
    ba = np.array([300.0, np.radians(0.3), np.radians(0.05)])
    bb = np.array([-200.0, np.radians(-0.2), np.radians(-0.05)])
    # the three-term model (its own dense form; the whole model: tests/correlation/test_registration_model.py)
    prm = RegistrationParams(outlier_chi2=1e12, estimate_range_gain=False, estimate_time_bias=False)
    mem = RegistrationMemory(a, b)
    idx = np.arange(60)
    for t in (0.0, 5.0, 10.0):
        mem.add(t, snapshot_of(a, truth, ba, rng, 50.0), snapshot_of(b, truth, bb, rng, 50.0), idx, idx, prm)
    prior = np.tile(
        [1 / prm.prior_range_m**2, 1 / np.radians(prm.prior_azimuth_deg) ** 2, 1 / np.radians(3.0) ** 2], 2
    )
    linear = solve_biases([mem], 10.0, dataclasses.replace(prm, max_iterations=1))
    assert linear is not None
    np.testing.assert_allclose(linear.bias, _dense_solve(mem, prior), rtol=1e-7, atol=1e-9)
    sol = solve_biases([mem], 10.0, prm)
    assert sol is not None
    # converged: equal to the fixed point within the stopping rule (1 % of each 1-sigma)
    assert sol.model_covariance is not None
    sigma = np.sqrt(np.diag(sol.model_covariance)).reshape(2, 3)
    fixed_point = _dense_solve(mem, prior, iterations=10)
    assert np.all(np.abs(sol.bias - fixed_point) <= 0.02 * sigma)
    assert np.any(np.abs(linear.bias - fixed_point) > 0.05 * sigma)  # the exact model matters here
    assert len(mem.time) == 180


def test_memory_forgets_whole_updates_by_data_time_and_rows() -> None:
    rng = np.random.default_rng(7)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 10)
    z = np.zeros(3)
    prm = RegistrationParams(memory_s=20.0, max_rows=25)
    mem = RegistrationMemory(a, b)
    idx = np.arange(10)
    for t in (0.0, 10.0, 20.0, 30.0):
        mem.add(t, snapshot_of(a, truth, z, rng, 10.0), snapshot_of(b, truth, z, rng, 10.0), idx, idx, prm)
    assert sorted(set(mem.time.tolist())) == [20.0, 30.0]  # 10.0 fell to the row cap, 0.0 to time


def test_pair_solve_follows_a_data_time_schedule() -> None:
    n = 60
    sc = StreamScenario(sparse_targets=n, box_m=200_000.0, cluster_targets=0, confirm_scans=1)
    rng = np.random.default_rng(8)
    a, b = make_sites()
    pos0, vel = make_targets(rng, sc, a)
    ra = RadarTrackSim(rng, a, sc.bias_a, n, sc)
    rb = RadarTrackSim(rng, b, sc.bias_b, n, sc)
    corr = PairCorrelator("svd-topology", a, b)
    interval = corr.params.registration.solve_interval_s
    solved = []
    updates = int(2.5 * interval / 4.0) + 4  # registered early, then two re-solves at least
    for k in range(updates):
        t = 4.0 * k
        before = corr.solution
        was_registered = corr.registered
        corr.update(ra.table(a, pos0, vel, t), rb.table(a, pos0, vel, t), t + 4.0)
        if corr.solution is not before:
            solved.append((t + 4.0, was_registered))
    assert corr.registered
    times = [t for t, reg in solved if reg]
    assert len(times) >= 2 and all(t1 - t0 >= interval for t0, t1 in itertools.pairwise(times))
    assert len(solved) < updates
