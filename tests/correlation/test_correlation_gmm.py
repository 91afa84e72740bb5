"""GMM anti-bias association (service/correlation/gmm.py): reference forms and the paper's scene."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from service.correlation.gmm import (
    GmmParams,
    _e_step,
    gmm_associate,
    neighbour_vectors,
    ospa_subset_matrix,
)
from topofusion_lab.evaluation.correlation_gmm_scene import paper_scene

# -- plain reference forms -------------------------------------------------------------------


def ospa_subset_loop(fa: np.ndarray, fb: np.ndarray, subset: int, c: float, p: float) -> np.ndarray:
    """Per pair: cheapest partial matching of exactly ``subset`` pairs by linear_sum_assignment on the
    cost matrix augmented with ``K - subset`` free dummy rows and columns (dummy-dummy forbidden)."""
    m, k, _ = fa.shape
    n = fb.shape[0]
    out = np.empty((m, n))
    extra = k - subset
    for i in range(m):
        for j in range(n):
            cost = np.minimum(np.linalg.norm(fa[i][:, None] - fb[j][None], axis=2), c) ** p
            aug = np.zeros((k + extra, k + extra))
            aug[:k, :k] = cost
            aug[k:, k:] = np.inf
            r, col = linear_sum_assignment(aug)
            real = (r < k) & (col < k)
            assert real.sum() == subset
            out[i, j] = (cost[r[real], col[real]].sum() / subset) ** (1.0 / p)
    return out


def ospa_full_loop(u: np.ndarray, v: np.ndarray, c: float, p: float) -> float:
    """Textbook OSPA (Schuhmacher 2008) between two equal-size sets."""
    cost = np.minimum(np.linalg.norm(u[:, None] - v[None], axis=2), c) ** p
    r, col = linear_sum_assignment(cost)
    return float((cost[r, col].sum() / len(u)) ** (1.0 / p))


@pytest.mark.parametrize(
    ("k", "subset", "p", "d"), [(4, 3, 2.0, 2), (4, 4, 1.0, 2), (5, 3, 2.0, 3), (3, 1, 2.0, 2)]
)
def test_ospa_subset_matrix_matches_assignment_loop(k: int, subset: int, p: float, d: int) -> None:
    rng = np.random.default_rng(10 + k + subset + d)
    fa = rng.normal(0.0, 800.0, (7, k, d))
    fb = rng.normal(0.0, 800.0, (6, k, d))
    fb[2] = fa[3] + rng.normal(0.0, 30.0, (k, d))  # one near-identical neighbourhood
    fb[4] = fa[1][rng.permutation(k)]  # one permuted copy: distance 0
    vec = ospa_subset_matrix(fa, fb, subset, 1000.0, p, chunk_elements=500)  # small chunks: several blocks
    ref = ospa_subset_loop(fa, fb, subset, 1000.0, p)
    np.testing.assert_allclose(vec, ref, rtol=0, atol=1e-9)
    assert vec[1, 4] == pytest.approx(0.0, abs=1e-9)
    if subset == k:
        for i, j in itertools.product(range(7), range(6)):
            assert vec[i, j] == pytest.approx(ospa_full_loop(fa[i], fb[j], 1000.0, p), abs=1e-9)


def test_neighbour_vectors_match_brute_force() -> None:
    rng = np.random.default_rng(3)
    pos = rng.uniform(0.0, 5000.0, (15, 2))
    got = neighbour_vectors(pos, 4)
    for i in range(15):
        d = np.linalg.norm(pos - pos[i], axis=1)
        d[i] = np.inf
        nearest = np.argsort(d)[:4]
        np.testing.assert_allclose(got[i], pos[nearest] - pos[i], atol=1e-9)


def test_e_step_matches_per_pair_loop() -> None:
    rng = np.random.default_rng(4)
    x, t = rng.normal(size=(6, 2)), rng.normal(size=(5, 2))
    prior = rng.uniform(0.1, 1.0, (5, 6))
    prior /= prior.sum(axis=0)
    sigma2, omega = 0.7, 0.2
    post, _ = _e_step(x, t, prior, sigma2, omega)
    for i in range(6):
        g = [prior[j, i] * np.exp(-np.sum((x[i] - t[j]) ** 2) / (2 * sigma2)) for j in range(5)]
        c = (2 * np.pi * sigma2) * omega / ((1 - omega) * 6)
        for j in range(5):
            assert post[j, i] == pytest.approx(g[j] / (sum(g) + c), abs=1e-12)


# -- the paper's scenario (docs/references.md §3) ----------------------------------------------


def test_paper_scenario_correct_association_rate() -> None:
    rng = np.random.default_rng(2024)
    correct = common = wrong = 0
    for _ in range(10):
        pos_a, pos_b, ids_a, ids_b = paper_scene(rng)
        res = gmm_associate(pos_a, pos_b, GmmParams())
        ok = ids_a[res.index_a] == ids_b[res.index_b]
        correct += int(ok.sum())
        wrong += int((~ok).sum())
        common += len(np.intersect1d(ids_a, ids_b))
        assert res.displacement.shape == pos_b.shape
        assert 0.0 <= res.outlier_weight <= 1.0
    rate = correct / common
    print(f"GMM paper scenario: correct {rate:.3f} ({correct}/{common}), wrong pairs {wrong}")
    assert rate >= 0.8  # the paper reports about 0.9
    assert wrong / max(1, correct + wrong) <= 0.1


def test_rigid_motion_is_recovered_with_displacement() -> None:
    rng = np.random.default_rng(5)
    pos_a = rng.uniform(0.0, 20e3, (25, 2))
    ang = np.radians(1.5)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    perm = rng.permutation(25)[:20]  # B sees 20 of A's 25 targets, shuffled
    pos_b = (pos_a[perm] - 10e3) @ rot.T + 10e3 + np.array([2500.0, -1800.0])
    res = gmm_associate(pos_a, pos_b)
    assert res.converged, res.reason
    np.testing.assert_array_equal(np.sort(res.index_b), np.arange(20))
    np.testing.assert_array_equal(res.index_a, perm[res.index_b])
    np.testing.assert_allclose(pos_b + res.displacement, pos_a[perm], atol=5.0)


def test_three_dimensional_input() -> None:
    rng = np.random.default_rng(6)
    pos_a = rng.uniform(0.0, 10e3, (12, 3))
    pos_b = pos_a + np.array([700.0, -400.0, 50.0]) + rng.normal(0.0, 20.0, (12, 3))
    res = gmm_associate(pos_a, pos_b)
    assert np.array_equal(res.index_a, res.index_b)
    assert res.index_a.size == 12


def test_deterministic() -> None:
    pos_a, pos_b, _, _ = paper_scene(np.random.default_rng(7))
    r1, r2 = gmm_associate(pos_a, pos_b), gmm_associate(pos_a, pos_b)
    np.testing.assert_array_equal(r1.index_a, r2.index_a)
    np.testing.assert_array_equal(r1.posterior, r2.posterior)


@pytest.mark.parametrize(
    ("pos_a", "pos_b", "fragment"),
    [
        (np.empty((0, 2)), np.ones((3, 2)), "too few"),
        (np.ones((1, 2)), np.arange(6.0).reshape(3, 2), "too few"),
        (np.full((4, 2), 5.0), np.arange(8.0).reshape(4, 2), "identical"),
        (np.array([[0.0, 0.0], [np.nan, 1.0]]), np.eye(2), "non-finite"),
        (np.ones((3, 2)), np.ones((3, 3)), "must be"),
        (np.ones((3, 4)), np.ones((3, 4)), "must be"),
    ],
)
def test_degenerate_inputs_give_empty_result(pos_a: np.ndarray, pos_b: np.ndarray, fragment: str) -> None:
    res = gmm_associate(pos_a, pos_b)
    assert not res
    assert res.index_a.size == res.index_b.size == res.posterior.size == 0
    assert res.index_a.dtype == np.intp
    assert fragment in res.reason
    assert not res.converged


def test_outlier_weight_floor_from_counts() -> None:
    """With M samples and N < M centroids at least M - N samples are outliers: omega >= 1 - N/M."""
    rng = np.random.default_rng(9)
    pos_a, pos_b, _, _ = paper_scene(rng, at_period=0)  # the dense starting box
    m, n = len(pos_a), len(pos_b)
    assert n < m
    res = gmm_associate(pos_a, pos_b)
    assert res.outlier_weight >= 1.0 - n / m - 1e-12
    free = gmm_associate(pos_a, pos_b, GmmParams(omega_floor_from_counts=False))
    assert free.outlier_weight < 1.0 - n / m  # what the floor prevents


def test_dense_starting_box_better_with_floor() -> None:
    rng = np.random.default_rng(11)
    scenes = [paper_scene(rng, at_period=0) for _ in range(8)]

    def rate(params: GmmParams) -> float:
        ok = common = 0
        for pa, pb, ia, ib in scenes:
            r = gmm_associate(pa, pb, params)
            ok += int(np.sum(ia[r.index_a] == ib[r.index_b]))
            common += len(np.intersect1d(ia, ib))
        return ok / common

    assert rate(GmmParams()) > rate(GmmParams(omega_floor_from_counts=False))
