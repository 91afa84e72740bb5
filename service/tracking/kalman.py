"""Constant-velocity Kalman filter over stacks of tracks (pure numpy, vectorised).

State ``x = [e, n, u, ve, vn, vu]`` in the radar's ENU frame, covariance ``P`` 6x6.
Transition ``F(dt) = [[I, dt I], [0, I]]``.  Process noise: continuous white-noise
acceleration with spectral density ``q`` per axis (Bar-Shalom, Li, Kirubarajan, *Estimation
with Applications to Tracking and Navigation*, 2001, Eq. 6.2.2-12):
``Q(dt) = q [[|dt|^3/3 I, dt|dt|/2 I], [dt|dt|/2 I, |dt| I]]`` (``|dt|`` keeps ``Q`` positive
semi-definite when a plot is older than the state).  Measurement ``z = H x + w`` with
``H = [I 0]`` and ``w ~ N(0, R)`` from :mod:`service.tracking.measurement`.  The update uses
the Joseph form ``P+ = (I - K H) P (I - K H)^T + K R K^T``, which stays symmetric PSD.
"""

from __future__ import annotations

import numpy as np

from service.geo import FloatArray
from service.linalg import inv3, mahalanobis3

_I3 = np.eye(3)


#: Row and column indices of the three position-velocity couplings (``F`` and ``Q``).
_POS = np.arange(3)
_VEL = _POS + 3


def cv_transition(dt: FloatArray) -> FloatArray:
    """``F(dt)`` for each ``dt``, shape ``(n, 6, 6)``."""
    dt = np.asarray(dt, dtype=float)
    f = np.broadcast_to(np.eye(6), (*dt.shape, 6, 6)).copy()
    f[..., _POS, _VEL] = dt[..., None]
    return f


def cv_process_noise(dt: FloatArray, q: float | FloatArray) -> FloatArray:
    """``Q(dt)`` of the CWNA model for each ``dt``, shape ``(n, 6, 6)`` (``q``: one for all,
    or one per ``dt``)."""
    dt = np.asarray(dt, dtype=float)
    a = np.abs(dt)
    out = np.zeros((*dt.shape, 6, 6))
    pv = (q * dt * a / 2.0)[..., None]
    out[..., _POS, _POS] = (q * a**3 / 3.0)[..., None]
    out[..., _POS, _VEL] = pv
    out[..., _VEL, _POS] = pv
    out[..., _VEL, _VEL] = (q * a)[..., None]
    return out


def predict(
    x: FloatArray, P: FloatArray, dt: FloatArray, q: float | FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Predict states ``(n, 6)`` and covariances ``(n, 6, 6)`` over ``dt`` ``(n,)``."""
    f = cv_transition(dt)
    x_new = np.einsum("nij,nj->ni", f, x)
    p_new = f @ P @ np.swapaxes(f, -1, -2) + cv_process_noise(dt, q)
    return x_new, p_new


def innovation(x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Innovation ``y = z - H x`` and its covariance ``S = H P H^T + R``."""
    return z - x[..., :3], P[..., :3, :3] + R


def mahalanobis2(y: FloatArray, S: FloatArray) -> FloatArray:
    """``y^T S^-1 y`` for stacks of vectors and covariances (NaN where ``S`` is singular or not
    finite: it passes no gate).  3x3: from the cofactors (:func:`service.linalg.mahalanobis3`;
    a batched solve pays per matrix, and the gates and the filter ask for thousands a batch)."""
    if S.shape[-1] == 3:
        q, ok = mahalanobis3(y, S)
        return np.where(ok, q, np.nan)
    return np.einsum("ni,ni->n", y, np.linalg.solve(S, y[..., None])[..., 0])


def update(
    x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Kalman update of each state with its plot; returns ``(x+, P+, nis)`` (Joseph form)."""
    y, S = innovation(x, P, z, R)
    return (*update_innovation(x, P, R, y, S), mahalanobis2(y, S))


def update_state(x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray) -> tuple[FloatArray, FloatArray]:
    """:func:`update` without the NIS (the same ``x+`` and ``P+``), for callers that do not
    use it."""
    y, S = innovation(x, P, z, R)
    return update_innovation(x, P, R, y, S)


def update_innovation(
    x: FloatArray, P: FloatArray, R: FloatArray, y: FloatArray, S: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The update of :func:`update_state` from the innovation ``y`` and its covariance ``S``
    already at hand (:func:`innovation`)."""
    # K = P H^T S^-1 with the closed-form inverse of S (a singular S, which a plot's own
    # covariance R > 0 never gives, leaves the state as it is: K = 0)
    return joseph_update(x, P, R, y, inv3(S)[0], slice(0, 3))


def joseph_update(
    x: FloatArray, P: FloatArray, R: FloatArray, y: FloatArray, s_inv: FloatArray, measured: slice
) -> tuple[FloatArray, FloatArray]:
    """Kalman update in the Joseph form (module docstring) with a measurement of the state's
    components ``measured`` (``H`` selects them: the position here, the horizontal velocity
    in :func:`service.tracking.formation.velocity_update`): the innovation ``y``, the inverse
    of its covariance ``s_inv`` and the measurement's covariance ``R``.  ``K = P H^T S^-1``,
    ``x + K y``, ``(I - K H) P (I - K H)^T + K R K^T`` made symmetric."""
    K = P[..., :, measured] @ s_inv  # (n, 6, m)
    x_new = x + np.einsum("nij,nj->ni", K, y)
    ikh = np.broadcast_to(np.eye(P.shape[-1]), P.shape).copy()
    ikh[..., :, measured] -= K
    p_new = ikh @ P @ np.swapaxes(ikh, -1, -2) + K @ R @ np.swapaxes(K, -1, -2)
    p_new = 0.5 * (p_new + np.swapaxes(p_new, -1, -2))
    return x_new, p_new
