"""The vectorised CV Kalman filter against a plain per-track reference (to 1e-9)."""

from __future__ import annotations

import numpy as np

from service.tracking import kalman


def _reference_step(x, P, dt, q, z, R):
    F = np.eye(6)
    F[:3, 3:] = np.eye(3) * dt
    a = abs(dt)
    Q = np.zeros((6, 6))
    Q[:3, :3] = np.eye(3) * q * a**3 / 3
    Q[:3, 3:] = Q[3:, :3] = np.eye(3) * q * dt * a / 2
    Q[3:, 3:] = np.eye(3) * q * a
    x = F @ x
    P = F @ P @ F.T + Q
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    y = z - H @ x
    x = x + K @ y
    IKH = np.eye(6) - K @ H
    P = IKH @ P @ IKH.T + K @ R @ K.T
    return x, 0.5 * (P + P.T), float(y @ np.linalg.inv(S) @ y)


def test_filter_matches_reference_over_many_steps() -> None:
    rng = np.random.default_rng(1)
    n, steps, q = 7, 300, 25.0
    x = rng.normal(0, 1e4, (n, 6))
    P = np.tile(np.diag([1e4, 1e4, 1e4, 1e3, 1e3, 1e3]), (n, 1, 1))
    xr, Pr = x.copy(), P.copy()
    for _ in range(steps):
        dt = rng.uniform(-0.5, 5.0, n)
        z = x[:, :3] + rng.normal(0, 300, (n, 3))
        A = rng.normal(0, 1, (n, 3, 3))
        R = A @ np.swapaxes(A, 1, 2) * 1e4 + np.eye(3) * 100
        x, P = kalman.predict(x, P, dt, q)
        x, P, nis = kalman.update(x, P, z, R)
        for i in range(n):
            xr[i], Pr[i], nis_r = _reference_step(xr[i], Pr[i], dt[i], q, z[i], R[i])
            assert abs(nis[i] - nis_r) <= 1e-9 * max(1.0, abs(nis_r))
    np.testing.assert_allclose(x, xr, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(P, Pr, rtol=1e-9, atol=1e-9)


def test_process_noise_is_psd() -> None:
    Q = kalman.cv_process_noise(np.array([-3.0, 0.0, 0.1, 4.0, 60.0]), 25.0)
    assert np.all(np.linalg.eigvalsh(Q) >= -1e-9)
    np.testing.assert_allclose(Q, np.swapaxes(Q, 1, 2))
