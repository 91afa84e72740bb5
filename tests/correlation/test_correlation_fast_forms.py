"""The hot path's fast forms against plain ones: same neighbours, same decisions, same numbers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from service.chi2 import chi2_upper
from service.correlation.base import NO_DECISION_REASONS, Reason, no_decision
from service.correlation.correlator import _near
from service.correlation.pairs import _isin
from service.correlation.svd_topology import svd_match
from service.correlation.topology import TopologyParams, gather_points, neighbourhoods
from service.linalg import (
    congruence,
    det3,
    inv3,
    mahalanobis2_h,
    mahalanobis3,
    matvec3,
    quad3,
    quad3_large,
)
from tests.reference_forms import brute_force_neighbours
from topofusion_lab.evaluation.correlation_scenario import Biases, make_sites, single_match_batch


def _clustered(rng: np.random.Generator, n: int) -> np.ndarray:
    """Sparse traffic plus a few dense clusters (so both neighbour searches are exercised)."""
    pts = rng.uniform(0, 200_000, (n, 3)) * np.array([1, 1, 0.05])
    centres = rng.uniform(0, 200_000, (4, 3)) * np.array([1, 1, 0.05])
    cl = centres[rng.integers(0, 4, n // 3)] + rng.normal(0, 3_000, (n // 3, 3)) * np.array([1, 1, 0.1])
    return np.concatenate([pts, cl])


def test_neighbourhoods_match_brute_force_default_params_and_rows() -> None:
    rng = np.random.default_rng(5)
    pts = _clustered(rng, 240)
    prm = TopologyParams()
    full = neighbourhoods(pts, prm)
    dense = 0
    for i in range(len(pts)):
        want = brute_force_neighbours(pts, i, prm)
        assert list(full[i][full[i] >= 0]) == want
        dense += len(want) > prm.min_neighbours
    assert dense > 10  # the second (radius) search ran
    rows = np.unique(rng.integers(0, len(pts), 60))
    part = neighbourhoods(pts, prm, rows=rows)
    assert part.shape == full.shape
    np.testing.assert_array_equal(part[rows], full[rows])
    others = np.setdiff1d(np.arange(len(pts)), rows)
    assert np.all(part[others] == -1)


@pytest.mark.parametrize("seed", [5, 11, 12])
def test_neighbourhoods_scan_matches_tree_and_brute_force(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The full-distance-scan path for a few queried rows gives the tree's neighbourhoods."""
    from service.correlation import topology

    rng = np.random.default_rng(seed)
    pts = _clustered(rng, 300)
    prm = TopologyParams()
    rows = np.unique(rng.integers(0, len(pts), 12))
    assert len(rows) * len(pts) <= topology.BRUTE_FORCE_MAX_DISTANCES  # the scan path
    scan = neighbourhoods(pts, prm, rows=rows)
    monkeypatch.setattr(topology, "BRUTE_FORCE_MAX_DISTANCES", 0)  # the tree path
    tree = neighbourhoods(pts, prm, rows=rows)
    np.testing.assert_array_equal(scan, tree)
    for i in rows:
        assert list(scan[i][scan[i] >= 0]) == brute_force_neighbours(pts, int(i), prm)
    # no row, and fewer tracks than a full neighbourhood
    assert np.all(neighbourhoods(pts, prm, rows=np.empty(0, dtype=np.intp)) == -1)
    few = pts[:5]
    monkeypatch.setattr(topology, "BRUTE_FORCE_MAX_DISTANCES", 20_000)
    np.testing.assert_array_equal(neighbourhoods(few, prm, rows=np.arange(5)), neighbourhoods(few, prm))


def test_gather_points_trim_drops_only_padding() -> None:
    rng = np.random.default_rng(6)
    pts = _clustered(rng, 90)
    cov = np.broadcast_to(np.eye(3) * 4e4, (len(pts), 3, 3)).copy()
    nbr = neighbourhoods(pts, TopologyParams())
    ref = rng.integers(0, len(pts), 40)
    p0, c0, m0 = gather_points(pts, cov, nbr, ref)
    p1, c1, m1 = gather_points(pts, cov, nbr, ref, trim=True)
    k = p1.shape[1]
    assert k <= p0.shape[1] and not m0[:, k:].any()
    np.testing.assert_array_equal(p1, p0[:, :k])
    np.testing.assert_array_equal(c1, c0[:, :k])
    np.testing.assert_array_equal(m1, m0[:, :k])
    # padding: zero point, identity covariance
    assert np.all(p0[~m0] == 0.0) and np.all(c0[~m0] == np.eye(3))


@pytest.mark.parametrize("stack", [(40, 5), (3,), (90, 8)])  # small (fewest calls) and large (in place) paths
def test_small_linear_algebra_matches_numpy(stack: tuple[int, ...]) -> None:
    rng = np.random.default_rng(7)
    a = rng.normal(size=(*stack, 3, 3))
    s = a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(3)
    flat = s.reshape(-1, 3, 3)
    flat[0] = np.diag([1.0, 1.0, 0.0])  # singular
    flat[1] = np.nan
    inv, ok = inv3(s)
    assert not ok.flat[0] and not ok.flat[1] and ok.sum() == ok.size - 2
    np.testing.assert_allclose(inv[ok], np.linalg.inv(s[ok]), rtol=1e-9, atol=1e-12)
    assert np.all(inv[~ok] == 0.0)
    inv1, ok1 = inv3(flat[2])  # a single matrix
    assert ok1 and np.allclose(inv1, np.linalg.inv(flat[2]))
    v = rng.normal(size=(*stack, 3))
    np.testing.assert_allclose(matvec3(s, v), (s @ v[..., None])[..., 0], rtol=1e-12)
    good = s[ok]
    np.testing.assert_allclose(quad3_large(v[ok], good), quad3(v[ok], good), rtol=1e-12)
    # r^T S^-1 r without the inverse: each row against a plain solve; singular rows 0 with the
    # flag of inv3
    q, q_ok = mahalanobis3(v, s)
    np.testing.assert_array_equal(q_ok, ok)
    rows_v, rows_s = v.reshape(-1, 3), s.reshape(-1, 3, 3)
    want_q = np.array(
        [r @ np.linalg.solve(m, r) if k else 0.0 for r, m, k in zip(rows_v, rows_s, ok.ravel(), strict=True)]
    )
    np.testing.assert_allclose(q.ravel(), want_q, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(det3(good), np.linalg.det(good), rtol=1e-9, atol=1e-12)
    r = rng.normal(size=(3, 3))
    np.testing.assert_allclose(congruence(r, good), r @ good @ r.T, rtol=1e-9, atol=1e-12)
    d = rng.normal(size=(*stack, 2)).reshape(-1, 2)
    sf = s.reshape(-1, 3, 3)
    want = np.array(
        [d[k] @ np.linalg.inv(sf[k, :2, :2]) @ d[k] if ok.flat[k] else np.inf for k in range(len(sf))]
    )
    got = mahalanobis2_h(d[:, 0], d[:, 1], sf[:, 0, 0], sf[:, 0, 1], sf[:, 1, 1])
    fine = np.isfinite(want)
    np.testing.assert_allclose(got[fine], want[fine], rtol=1e-9)


def test_string_isin_and_chi2_quantile() -> None:
    rng = np.random.default_rng(8)
    x = np.array([f"T{k}" for k in rng.integers(0, 300, 200)])
    y = np.array([f"T{k}" for k in rng.integers(0, 300, 150)])
    np.testing.assert_array_equal(_isin(x, y), np.isin(x, y))
    assert _isin(x, y[:0]).shape == x.shape and not _isin(x, y[:0]).any()
    assert _isin(x[:0], y).shape == (0,)
    dof = np.linspace(0.5, 30.0, 60)
    for alpha in (0.005, 1e-3, 1e-4):
        np.testing.assert_array_equal(chi2_upper(alpha, dof), chi2.ppf(1.0 - alpha, dof))
        assert chi2_upper(alpha, 3) == chi2.ppf(1.0 - alpha, 3)


def test_svd_match_pre_rotated_a_is_the_same_decision() -> None:
    """decide() turns A into B's orientation per track and passes M0 = I: same results."""
    rng = np.random.default_rng(9)
    a, b = make_sites()
    ba = Biases.random_sign(rng, 200, 100.0, 0.1)
    bb = Biases.random_sign(rng, 200, 100.0, 0.1)
    m = single_match_batch(rng, a, b, 6, 200, ba, bb, pd_neighbour=0.8)[0]
    r0 = svd_match(m.pa, m.ca, m.ma, m.pb, m.cb, m.mb, m.m0)
    r1 = svd_match(m.pa @ m.m0.T, congruence(m.m0, m.ca), m.ma, m.pb, m.cb, m.mb, np.eye(3))
    np.testing.assert_array_equal(r0.reason, r1.reason)
    np.testing.assert_array_equal(r0.matched, r1.matched)
    for name in ("statistic", "cost", "chi2_shape", "chi2_ref", "rotation_weight", "scale", "yaw_rad"):
        np.testing.assert_allclose(getattr(r1, name), getattr(r0, name), rtol=1e-9, atol=1e-9)


def test_svd_match_per_candidate_independent_of_grouping_and_width() -> None:
    """decide() matches candidates in groups of similar sequence length: same results."""
    rng = np.random.default_rng(10)
    pts = _clustered(rng, 150)
    pts_b = pts + rng.normal(0, 150.0, pts.shape)
    cov = np.broadcast_to(np.diag([4e4, 4e4, 9e4]), (len(pts), 3, 3)).copy()
    prm = TopologyParams()
    nbr_a, nbr_b = neighbourhoods(pts, prm), neighbourhoods(pts_b, prm)
    ref = np.arange(len(pts))
    width = np.maximum((nbr_a >= 0).sum(1), (nbr_b >= 0).sum(1))
    assert len(np.unique(width)) > 1

    def run(rows: np.ndarray):  # type: ignore[no-untyped-def]
        pa, ca, ma = gather_points(pts, cov, nbr_a, ref[rows], trim=True)
        pb, cb, mb = gather_points(pts_b, cov, nbr_b, ref[rows], trim=True)
        return svd_match(pa, ca, ma, pb, cb, mb, np.eye(3))

    whole = run(ref)
    narrow = np.flatnonzero(width <= np.median(width))
    wide = np.flatnonzero(width > np.median(width))
    assert narrow.size and wide.size
    for rows in (narrow, wide):
        part = run(rows)
        np.testing.assert_array_equal(part.reason, whole.reason[rows])
        np.testing.assert_array_equal(part.matched, whole.matched[rows])
        for name in ("statistic", "cost", "chi2_shape", "chi2_ref", "scale", "yaw_rad"):
            np.testing.assert_allclose(getattr(part, name), getattr(whole, name)[rows], rtol=1e-9, atol=1e-9)
    assert whole.accepted.mean() > 0.5


def test_prediction_blocks_match_the_full_prediction() -> None:
    """The snapshot's two covariance blocks against the 6x6 prediction (itself tested against
    ``F P F^T + Q`` per track)."""
    from service.correlation.prediction import predict_blocks, predict_states

    rng = np.random.default_rng(21)
    n = 300
    pos, vel = rng.normal(size=(n, 3)) * 1e5, rng.normal(size=(n, 3)) * 200
    a = rng.normal(size=(n, 6, 6))
    cov = a @ np.swapaxes(a, 1, 2)
    dt = rng.uniform(-3, 8, n)
    p, v, c = predict_states(pos, vel, cov, dt, 1.5)
    p2, v2, pc, vc = predict_blocks(pos, vel, cov, dt, 1.5)
    np.testing.assert_array_equal(p2, p)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_allclose(pc, c[:, :3, :3], rtol=1e-13, atol=1e-9)
    np.testing.assert_allclose(vc, c[:, 3:, 3:], rtol=1e-13, atol=1e-12)


def test_polar_jacobian_from_enu_matches_the_trigonometric_one() -> None:
    from service.correlation.registration import bias_jacobian, polar_jacobian_enu
    from service.geo import enu_to_polar, polar_jacobian

    rng = np.random.default_rng(22)
    enu = rng.normal(size=(400, 3)) * np.array([1.5e5, 1.5e5, 6e3])
    enu[0] = [0.0, 0.0, 9_000.0]  # straight above the site
    enu[1] = [0.0, 80_000.0, 0.0]  # on the horizon, due north
    r, az, el = enu_to_polar(enu)
    want = polar_jacobian(r, az, el)
    np.testing.assert_allclose(polar_jacobian_enu(enu), want, rtol=1e-9, atol=1e-6)
    site, _ = make_sites()
    pos = site.enu_to_ecef(enu)
    g = bias_jacobian(site, pos)
    for k in range(2, 400, 37):  # (not above the site: there the azimuth is ill-conditioned)
        rk, ak, ek = (x[0] for x in site.ecef_to_polar(pos[k : k + 1]))
        np.testing.assert_allclose(g[k], site.rotation @ polar_jacobian(rk, ak, ek), rtol=1e-8, atol=1e-4)


def test_compensation_covariance_matches_per_track_product() -> None:
    """``G C G^T`` of :func:`compensate` against the per-track product, and the compensated
    positions against :func:`remove_bias`."""
    from service.correlation.base import PredictedTracks
    from service.correlation.registration import bias_jacobian, compensate, remove_bias

    rng = np.random.default_rng(23)
    site, _ = make_sites()
    n = 50
    enu = rng.normal(size=(n, 3)) * np.array([1e5, 1e5, 4e3]) + np.array([0, 0, 9e3])
    pos = site.enu_to_ecef(enu)
    vel = rng.normal(size=(n, 3)) * 200
    cov = np.broadcast_to(np.eye(3) * 1e4, (n, 3, 3)).copy()
    snap = PredictedTracks(
        np.array([f"t{k}" for k in range(n)]), pos, vel, cov, cov.copy(), site, enu, vel @ site.rotation
    )
    bias = np.array([400.0, np.radians(0.3), np.radians(0.1)])
    half = rng.normal(size=(3, 3)) * np.array([10.0, 1e-4, 1e-4])
    bias_cov = half @ half.T
    out, extra = compensate(snap, bias, bias_cov)
    g = bias_jacobian(site, pos)
    for k in range(n):
        np.testing.assert_allclose(extra[k], g[k] @ bias_cov @ g[k].T, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out.position, remove_bias(site, pos, bias), atol=1e-6)
    np.testing.assert_allclose(out.enu, site.ecef_to_enu(out.position), atol=1e-6)


def test_no_decision_lookup_matches_isin_for_every_int8_code() -> None:
    # every reason the methods give, and every other int8 code (negative ones included)
    codes = np.arange(-128, 128, dtype=np.int8)
    assert np.array_equal(no_decision(codes), np.isin(codes, NO_DECISION_REASONS))
    reasons = np.array([r.value for r in Reason], dtype=np.int8)
    assert no_decision(reasons).sum() == len(NO_DECISION_REASONS)
    assert no_decision(np.empty(0, dtype=np.int8)).shape == (0,)


@pytest.mark.parametrize("anchors", [0, 1, 3, 8, 9, 40])
def test_near_anchors_match_a_plain_loop(anchors: int) -> None:
    # the direct form (a few anchors) and the product form (many) against every distance taken
    # one at a time; NaN rows and anchors are never near
    rng = np.random.default_rng(anchors)
    positions = rng.normal(0.0, 30_000.0, (60, 3)) + np.array([4.0e6, 3.0e5, 4.9e6])
    positions[5] = np.nan
    a = positions[rng.integers(0, 60, anchors)] + rng.normal(0.0, 20_000.0, (anchors, 3))
    if anchors > 2:
        a[1] = np.nan
    got = _near(positions, a, 25_000.0)
    want = np.array(
        [[bool(np.sum((p - q) ** 2) <= 25_000.0**2) for q in a] for p in positions], dtype=bool
    ).reshape(len(positions), anchors)
    assert got.shape == want.shape and np.array_equal(got, want)
