"""Neighbourhoods, candidates and prediction against plain reference forms."""

from __future__ import annotations

import numpy as np

from service.correlation.candidates import candidate_pairs
from service.correlation.prediction import predict_states
from service.correlation.topology import TopologyParams, neighbourhoods, sort_by_azimuth
from tests.reference_forms import brute_force_neighbours


def test_neighbourhoods_match_brute_force() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 100_000, (150, 3)) * np.array([1, 1, 0.05])
    prm = TopologyParams(radius_m=10_000.0, min_neighbours=3, max_radius_m=30_000.0, max_neighbours=6)
    nb = neighbourhoods(pts, prm)
    for i in range(len(pts)):
        want = brute_force_neighbours(pts, i, prm)
        assert list(nb[i][nb[i] >= 0]) == want


def test_sequences_sorted_by_azimuth() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 20_000, (30, 3))
    nb = neighbourhoods(pts, TopologyParams(max_neighbours=8))
    mask = nb >= 0
    # each track's topology sequence z_i = x_i - x_0 (the basic method's, basic_topology.py)
    z = np.where(mask[..., None], pts[np.maximum(nb, 0)] - pts[:, None, :], 0.0)
    order = sort_by_azimuth(z, mask)
    z, mask = np.take_along_axis(z, order[..., None], axis=1), np.take_along_axis(mask, order, axis=1)
    assert mask.sum() > len(pts)  # (neighbours to sort)
    az = np.mod(np.arctan2(z[..., 0], z[..., 1]), 2 * np.pi)
    for i in range(len(pts)):
        a = az[i][mask[i]]
        assert np.all(np.diff(a) >= 0)


def test_candidates_match_brute_force() -> None:
    rng = np.random.default_rng(2)
    a = rng.uniform(0, 50_000, (80, 3))
    b = rng.uniform(0, 50_000, (90, 3))
    ia, ib, d = candidate_pairs(a, b, 8_000.0)
    want = [(i, j) for i in range(80) for j in range(90) if np.linalg.norm(a[i] - b[j]) <= 8_000.0]
    assert list(zip(ia.tolist(), ib.tolist(), strict=True)) == want
    np.testing.assert_allclose(d, np.linalg.norm(a[ia] - b[ib], axis=1))
    e = candidate_pairs(np.empty((0, 3)), b, 1.0)
    assert len(e[0]) == 0


def test_prediction_matches_reference() -> None:
    rng = np.random.default_rng(3)
    n = 5
    pos = rng.normal(size=(n, 3))
    vel = rng.normal(size=(n, 3))
    a = rng.normal(size=(n, 6, 6))
    cov = a @ np.swapaxes(a, 1, 2)
    dt = rng.uniform(-3, 5, n)
    p, _v, c = predict_states(pos, vel, cov, dt, 2.0)
    for i in range(n):
        f = np.eye(6)
        f[:3, 3:] = dt[i] * np.eye(3)
        t = abs(dt[i])
        q = 2.0 * np.block(
            [[t**3 / 3 * np.eye(3), dt[i] * t / 2 * np.eye(3)], [dt[i] * t / 2 * np.eye(3), t * np.eye(3)]]
        )
        np.testing.assert_allclose(c[i], f @ cov[i] @ f.T + q, atol=1e-12)
        np.testing.assert_allclose(p[i], pos[i] + vel[i] * dt[i])
