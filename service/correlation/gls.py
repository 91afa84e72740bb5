"""Covariance-weighted similarity fit with a physical prior (the calibrated form behind the F test).

The SVD paper's fit (Section 1.3, Eq. 7, :mod:`.umeyama`) is *unweighted* least squares.  Its
matching test (Section 1.4) compares the residual variance with the variance the radars'
random errors explain; that comparison is only a chi-square (F) statistic with the stated
degrees of freedom if the residual is the minimum of the *same* covariance-weighted norm
(generalised least squares, GLS).  With the radars' strongly anisotropic errors (range
200 m, cross-range 500-800 m at 150 km) the unweighted minimiser leaves a residual that is
stochastically larger than chi-square: measured on the Fig. 1 scenario, the shape test of
nominal size 1 % rejected 2.5-3.5 % of true pairs.

This module solves the weighted problem in closed form.  With ``a = c cos(yaw)`` and
``b = c sin(yaw)`` the horizontal part of ``y = c M_yaw x + t`` is *linear* in
``(a, b, t)``: ``y = a x + b J x + t`` with ``J x = (-x_n, x_e, 0)``; the vertical uses
``c ~ a`` (``1 - cos(yaw) < 0.4 %`` for ``|yaw| <= 5 deg``).  Per candidate::

    H = sum_k w_k A_k^T W_k A_k + Lambda,   g = sum_k w_k A_k^T W_k y_k + Lambda theta_0,
    theta = H^-1 g,   A_k = [x_k, J x_k, I_3],   W_k = S_k^-1,

with a Gaussian prior ``Lambda = diag(1/sigma_c^2, 1/sigma_yaw^2, 0, 0, 0)`` around
``theta_0 = (1, 0, 0, 0, 0)``: the physical bounds of Section 1.5 (a rotation far from the
identity and a scale far from 1 are impossible) as a soft constraint, the translation free.
The minimised objective ``Q = sum_k w_k r_k^T W_k r_k + (a - 1)^2 / sigma_c^2 + b^2 /
sigma_yaw^2`` is, under the hypothesis with the truth at the prior mean, a sum of
``3 m - 5`` unit chi-square terms plus two terms with weights in (0, 1); its mean is
``3 m - tr(H^-1 H_data)`` (the effective degrees of freedom of a regularised fit), and the
test uses a chi-square with that (non-integer) number of degrees of freedom.
``Cov(theta) = H^-1``; its translation block is the uncertainty of the fitted ``t`` that the
position test of :mod:`.svd_topology` needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.correlation.base import BoolArray, FloatArray
from service.linalg import inv3, matvec3, quad3_large

#: Parameters: a, b, t_e, t_n, t_u.
N_PARAMS = 5
#: A normal matrix whose diagonally normalised determinant is below this is called singular.
SINGULAR_RTOL = 1e-10


@dataclass(frozen=True)
class GlsFit:
    """Batched weighted fit: ``theta (P, 5)``, ``cov (P, 5, 5)``, objective parts, effective dof."""

    theta: FloatArray
    cov: FloatArray
    q_residual: FloatArray
    q_prior: FloatArray
    df_model: FloatArray
    valid: BoolArray

    @property
    def scale(self) -> FloatArray:
        return np.hypot(self.theta[:, 0], self.theta[:, 1])

    @property
    def yaw(self) -> FloatArray:
        return np.arctan2(self.theta[:, 1], self.theta[:, 0])

    @property
    def translation(self) -> FloatArray:
        return self.theta[:, 2:]

    def apply(self, x: FloatArray) -> FloatArray:
        """``a x + b J x + t`` for points ``(P, K, 3)``."""
        return _design_apply(x, self.theta)


def _jx(x: FloatArray) -> FloatArray:
    out = np.zeros_like(x)
    out[..., 0] = -x[..., 1]
    out[..., 1] = x[..., 0]
    return out


def _design_apply(x: FloatArray, theta: FloatArray) -> FloatArray:
    return theta[:, None, 0, None] * x + theta[:, None, 1, None] * _jx(x) + theta[:, None, 2:]


def similarity_gls_batch(
    x: FloatArray,
    y: FloatArray,
    w: FloatArray,
    s_inv: FloatArray,
    sigma_scale: float,
    sigma_yaw_rad: float,
) -> GlsFit:
    """Weighted fit for every stack entry: ``x, y (P, K, 3)``, ``w (P, K)``, ``s_inv (P, K, 3, 3)``."""
    p = x.shape[0]
    # Normal equations block by block (A_k = [x, Jx, I3] is sparse; W symmetric), without
    # forming the (P, K, 3, 5) design: W x, W J x and their inner products.
    jx = _jx(x)
    ww = s_inv * w[..., None, None]
    wx = matvec3(ww, x)
    wjx = matvec3(ww, jx)
    h_data = np.zeros((p, N_PARAMS, N_PARAMS))
    h_data[:, 0, 0] = np.einsum("pki,pki->p", x, wx)
    h_data[:, 0, 1] = h_data[:, 1, 0] = np.einsum("pki,pki->p", jx, wx)
    h_data[:, 1, 1] = np.einsum("pki,pki->p", jx, wjx)
    h_data[:, 0, 2:] = h_data[:, 2:, 0] = np.einsum("pki->pi", wx)
    h_data[:, 1, 2:] = h_data[:, 2:, 1] = np.einsum("pki->pi", wjx)
    h_data[:, 2:, 2:] = np.einsum("pkij->pij", ww)
    g = np.empty((p, N_PARAMS))
    g[:, 0] = np.einsum("pki,pki->p", wx, y)
    g[:, 1] = np.einsum("pki,pki->p", wjx, y)
    g[:, 2:] = np.einsum("pki->pi", matvec3(ww, y))
    lam = np.array([1.0 / sigma_scale**2, 1.0 / sigma_yaw_rad**2, 0.0, 0.0, 0.0])
    theta0 = np.array([1.0, 0.0, 0.0, 0.0, 0.0])
    h = h_data + np.diag(lam)
    g = g + lam * theta0
    # Solve by eliminating the translation (Schur complement): H_tt^-1 by the closed-form 3x3
    # inverse, then a 2x2 system for (a, b); far cheaper than a batched 5x5 inverse.
    # Singular systems (no points, all weights zero, collinear points with a flat prior) are
    # flagged, never raised.
    htt_inv, t_ok = inv3(h[:, 2:, 2:])
    hpt = h[:, :2, 2:]
    k_gain = hpt @ htt_inv  # (P, 2, 3)
    sp = h[:, :2, :2] - k_gain @ np.swapaxes(hpt, 1, 2)
    gp = g[:, :2] - (k_gain @ g[:, 2:, None])[..., 0]
    det = sp[:, 0, 0] * sp[:, 1, 1] - sp[:, 0, 1] * sp[:, 1, 0]
    valid = t_ok & (det > SINGULAR_RTOL * np.abs(sp[:, 0, 0] * sp[:, 1, 1])) & (w.sum(axis=1) > 0)
    safe = np.where(valid, det, 1.0)
    cov_pp = np.stack([sp[:, 1, 1], -sp[:, 0, 1], -sp[:, 1, 0], sp[:, 0, 0]], axis=1).reshape(-1, 2, 2)
    cov_pp = cov_pp / safe[:, None, None]
    theta_p = (cov_pp @ gp[..., None])[..., 0]
    theta_t = (htt_inv @ (g[:, 2:] - (np.swapaxes(hpt, 1, 2) @ theta_p[..., None])[..., 0])[..., None])[
        ..., 0
    ]
    theta = np.where(valid[:, None], np.concatenate([theta_p, theta_t], axis=1), theta0)
    cov_pt = -cov_pp @ k_gain
    cov = np.zeros((p, N_PARAMS, N_PARAMS))
    cov[:, :2, :2] = cov_pp
    cov[:, :2, 2:] = cov_pt
    cov[:, 2:, :2] = np.swapaxes(cov_pt, 1, 2)
    cov[:, 2:, 2:] = htt_inv + np.swapaxes(k_gain, 1, 2) @ cov_pp @ k_gain
    cov = np.where(valid[:, None, None], cov, 0.0)
    r = y - _design_apply(x, theta)
    q_res = np.einsum("pk,pk->p", w, quad3_large(r, s_inv))
    dth = theta - theta0
    q_pri = (lam * dth * dth).sum(-1)
    df_model = (cov * h_data).sum((1, 2))  # tr(H^-1 H_data), both symmetric
    nan = np.full(p, np.nan)
    return GlsFit(
        theta=np.where(valid[:, None], theta, np.nan),
        cov=cov,
        q_residual=np.where(valid, q_res, nan),
        q_prior=np.where(valid, q_pri, nan),
        df_model=np.where(valid, df_model, nan),
        valid=valid,
    )
