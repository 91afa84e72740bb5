"""Umeyama / yaw similarity fits: batched vs plain reference, recovery, degenerate inputs."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from service.correlation.umeyama import rotation_weight, umeyama_batch, yaw_matrix, yaw_similarity_batch
from tests.reference_forms import umeyama_reference, yaw_similarity_reference


def test_batched_full_fit_matches_reference() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(0, 5000, (200, 7, 3))
    y = rng.normal(0, 5000, (200, 7, 3))
    fit = umeyama_batch(x, y)
    for p in range(200):
        m, c, t, e2 = umeyama_reference(x[p], y[p])
        np.testing.assert_allclose(fit.rotation[p], m, atol=1e-9)
        np.testing.assert_allclose(fit.scale[p], c, rtol=1e-9)
        np.testing.assert_allclose(fit.translation[p], t, atol=1e-9 * 5000)
        np.testing.assert_allclose(fit.residual[p], max(e2, 0.0), rtol=1e-9, atol=1e-6)


def test_batched_yaw_fit_matches_reference() -> None:
    rng = np.random.default_rng(2)
    x = rng.normal(0, 5000, (200, 5, 3))
    y = rng.normal(0, 5000, (200, 5, 3))
    fit, yaw = yaw_similarity_batch(x, y)
    for p in range(200):
        yr, cr, tr = yaw_similarity_reference(x[p], y[p])
        np.testing.assert_allclose(yaw[p], yr, atol=1e-9)
        np.testing.assert_allclose(fit.scale[p], cr, rtol=1e-9)
        np.testing.assert_allclose(fit.translation[p], tr, atol=1e-9 * 5000)


def test_weights_select_points() -> None:
    rng = np.random.default_rng(3)
    x = rng.normal(0, 1000, (1, 6, 3))
    y = rng.normal(0, 1000, (1, 6, 3))
    w = np.array([[1, 1, 0, 1, 1, 0]], dtype=float)
    fit = umeyama_batch(x, y, w)
    keep = w[0] > 0
    m, c, _t, _ = umeyama_reference(x[0, keep], y[0, keep])
    np.testing.assert_allclose(fit.rotation[0], m, atol=1e-9)
    np.testing.assert_allclose(fit.scale[0], c, rtol=1e-9)


def test_recovers_known_similarity() -> None:
    rng = np.random.default_rng(4)
    rot = Rotation.from_euler("zyx", [20.0, -10.0, 5.0], degrees=True).as_matrix()
    x = rng.normal(0, 3000, (1, 8, 3))
    y = 1.07 * x @ rot.T + np.array([100.0, -250.0, 40.0])
    fit = umeyama_batch(x, y)
    np.testing.assert_allclose(fit.rotation[0], rot, atol=1e-12)
    np.testing.assert_allclose(fit.scale[0], 1.07, rtol=1e-12)
    np.testing.assert_allclose(fit.translation[0], [100.0, -250.0, 40.0], atol=1e-8)
    assert fit.valid[0] and fit.residual[0] < 1e-12 * 3000**2
    yaw_rot = yaw_matrix(np.radians(3.0))
    y2 = 0.99 * x @ yaw_rot.T + np.array([10.0, 20.0, 30.0])
    fit2, yaw = yaw_similarity_batch(x, y2)
    np.testing.assert_allclose(yaw[0], np.radians(3.0), atol=1e-12)
    np.testing.assert_allclose(fit2.scale[0], 0.99, rtol=1e-12)
    np.testing.assert_allclose(fit2.translation[0], [10.0, 20.0, 30.0], atol=1e-8)


def test_degenerate_inputs_are_invalid_not_exceptions() -> None:
    line = np.array([[[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [2000.0, 0.0, 0.0], [3000.0, 0.0, 0.0]]])
    same = np.zeros((1, 4, 3))
    two = np.array([[[0.0, 0.0, 0.0], [1000.0, 500.0, 0.0]]])
    for x in (line, same):
        fit = umeyama_batch(x, x + 10.0)
        assert not fit.valid[0]
    assert not umeyama_batch(two, two).valid[0]  # 2 points < 3 for a 3-D rotation
    fit, _ = yaw_similarity_batch(same, same)
    assert not fit.valid[0]
    fit, _ = yaw_similarity_batch(np.zeros((1, 0, 3)), np.zeros((1, 0, 3)))
    assert not fit.valid[0]


def test_constrained_yaw_fit_stays_within_bounds() -> None:
    rng = np.random.default_rng(5)
    x = rng.normal(0, 3000, (50, 4, 3))
    y = x @ yaw_matrix(np.radians(15.0)).T * 1.2
    fit, yaw = yaw_similarity_batch(x, y, max_yaw_rad=np.radians(5.0), max_scale_deviation=0.03)
    np.testing.assert_allclose(yaw, np.radians(5.0))
    np.testing.assert_allclose(fit.scale, 1.03)


def test_rotation_weight() -> None:
    assert rotation_weight(np.eye(3)) == 1.0
    assert rotation_weight(yaw_matrix(np.radians(6.0))) > 0.92 > rotation_weight(yaw_matrix(np.radians(8.0)))
