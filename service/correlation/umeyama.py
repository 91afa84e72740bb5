"""Least-squares similarity fits ``y_i = c M x_i + t`` (SVD paper Section 1.3, Eq. 7).

Two models, both batched over a stack of candidate pairs (no Python loop over pairs):

* :func:`umeyama_batch` -- the paper's full 3-D fit (Umeyama 1991, Arun 1987): means,
  variances and the cross-covariance ``Sigma_xy = 1/n sum (y_i - mu_y)(x_i - mu_x)^T``
  (Section 1.3 step 1), ``Sigma_xy = U D V^T`` with ``np.linalg.svd`` on the ``(P, 3, 3)``
  stack (step 2), ``S`` from the sign of ``det`` (step 3), ``M = U S V^T``,
  ``c = tr(D S) / sigma_x^2``, ``t = mu_y - c M mu_x``, ``e^2 = sigma_y^2 - tr(D S)^2 /
  sigma_x^2`` (step 4; the extraction garbles this last formula, Umeyama's Eq. 41 is used).
* :func:`yaw_similarity_batch` -- the same fit constrained to a rotation about the local
  vertical (what an azimuth bias produces): the closed-form 2-D Umeyama on the east/north
  components, with the scale also applied to the vertical.  Topology vectors of aircraft
  are nearly horizontal, so the full 3-D rotation is ill-conditioned about the horizontal
  axes; the constrained fit has 5 parameters (yaw, scale, 3 translations) instead of 7.

Points carry weights ``w >= 0`` (0 = absent, padding), so candidates with different
neighbour counts share one stack.  Degenerate inputs (fewer than the minimum points,
coincident or collinear points) give ``valid = False``, never an exception.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.correlation.base import BoolArray, FloatArray
from service.linalg import matvec3

#: Relative singular-value floor under which a cross-covariance is called rank deficient.
RANK_RTOL = 1e3 * np.finfo(float).eps ** 0.5


@dataclass(frozen=True)
class SimilarityFit:
    """Batched result; ``rotation`` (P,3,3), ``scale`` (P,), ``translation`` (P,3)."""

    rotation: FloatArray
    scale: FloatArray
    translation: FloatArray
    residual: FloatArray  # e^2, mean squared residual (Umeyama Eq. 41)
    valid: BoolArray

    def apply(self, x: FloatArray) -> FloatArray:
        """Transform points ``x`` (P, K, 3): ``c M x + t``."""
        return self.scale[:, None, None] * matvec3(self.rotation[:, None], x) + self.translation[:, None, :]


def _weighted_moments(
    x: FloatArray, y: FloatArray, w: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    wsum = w.sum(axis=1)
    wn = w / np.where(wsum > 0, wsum, 1.0)[:, None]
    mx = np.einsum("pk,pkd->pd", wn, x)
    my = np.einsum("pk,pkd->pd", wn, y)
    xc = x - mx[:, None, :]
    yc = y - my[:, None, :]
    return wn, mx, my, xc, yc, wsum


def umeyama_batch(
    x: FloatArray, y: FloatArray, w: FloatArray | None = None, min_points: int = 3
) -> SimilarityFit:
    """Full 3-D similarity fit for every stack entry; see the module docstring."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    p, k, _ = x.shape
    w = np.ones((p, k)) if w is None else np.asarray(w, dtype=float)
    wn, mx, my, xc, yc, _ = _weighted_moments(x, y, w)
    var_x = (wn * (xc * xc).sum(-1)).sum(-1)
    var_y = (wn * (yc * yc).sum(-1)).sum(-1)
    sigma = np.swapaxes(wn[..., None] * yc, 1, 2) @ xc  # Section 1.3 step 1
    u, d, vt = np.linalg.svd(sigma)  # step 2
    s = np.ones((p, 3))
    # Step 3, with Umeyama's rank-2 rule: for a rank-deficient Sigma use det(U) det(V).
    s[:, 2] = np.where(np.linalg.det(u) * np.linalg.det(vt) < 0, -1.0, 1.0)
    rot = (u * s[:, None, :]) @ vt  # step 4: M = U S V^T
    tr_ds = (d * s).sum(axis=1)
    npts = (w > 0).sum(axis=1)
    floor = np.finfo(float).tiny
    valid = (npts >= min_points) & (var_x > floor) & (d[:, 1] > RANK_RTOL * np.maximum(d[:, 0], floor))
    c = np.where(valid, tr_ds / np.where(var_x > floor, var_x, 1.0), np.nan)
    t = my - c[:, None] * (rot @ mx[..., None])[..., 0]
    e2 = var_y - tr_ds**2 / np.where(var_x > floor, var_x, 1.0)
    return SimilarityFit(rot, c, t, np.maximum(e2, 0.0), valid)


def yaw_matrix(angle_rad: FloatArray) -> FloatArray:
    """Rotations about the up axis, counter-clockwise seen from above (east towards north)."""
    a = np.asarray(angle_rad, dtype=float)
    ca, sa = np.cos(a), np.sin(a)
    m = np.zeros((*a.shape, 3, 3))
    m[..., 0, 0] = ca
    m[..., 0, 1] = -sa
    m[..., 1, 0] = sa
    m[..., 1, 1] = ca
    m[..., 2, 2] = 1.0
    return m


def yaw_similarity_batch(
    x: FloatArray,
    y: FloatArray,
    w: FloatArray | None = None,
    min_points: int = 2,
    max_yaw_rad: float | None = None,
    max_scale_deviation: float | None = None,
    residual: bool = True,
) -> tuple[SimilarityFit, FloatArray]:
    """Similarity fit with the rotation constrained to the vertical axis; returns (fit, yaw rad).

    2-D Umeyama on (east, north): ``a = sum w (x_e y_e + x_n y_n)``, ``b = sum w (x_e y_n -
    x_n y_e)`` over centred points, yaw ``= atan2(b, a)``, ``c = sqrt(a^2 + b^2) /
    sigma_xh^2``; the vertical follows ``y_u = c x_u + t_u``.

    Optional physical bounds make it a *constrained* least-squares fit: the residual is
    ``sigma_y^2 - 2 c (a cos(yaw) + b sin(yaw)) + c^2 sigma_x^2``, so for any ``c > 0`` the best
    admissible yaw is the unconstrained one clipped to ``+-max_yaw_rad``, and the best scale
    given that yaw, ``(a cos + b sin) / sigma_xh^2``, clipped to ``1 +- max_scale_deviation``.

    ``residual=False`` skips ``e^2`` (returned as NaN) for callers that judge the fit otherwise.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    p, k, _ = x.shape
    w = np.ones((p, k)) if w is None else np.asarray(w, dtype=float)
    wn, mx, my, xc, yc, _ = _weighted_moments(x, y, w)
    a = np.einsum("pk,pk->p", wn, xc[..., 0] * yc[..., 0] + xc[..., 1] * yc[..., 1])
    b = np.einsum("pk,pk->p", wn, xc[..., 0] * yc[..., 1] - xc[..., 1] * yc[..., 0])
    var_xh = np.einsum("pk,pk->p", wn, xc[..., 0] ** 2 + xc[..., 1] ** 2)
    yaw_hat = np.arctan2(b, a)
    yaw = yaw_hat if max_yaw_rad is None else np.clip(yaw_hat, -max_yaw_rad, max_yaw_rad)
    npts = (w > 0).sum(axis=1)
    floor = np.finfo(float).tiny
    norm_ab = np.hypot(a, b)
    valid = (npts >= min_points) & (var_xh > floor) & (norm_ab > RANK_RTOL * var_xh)
    c = norm_ab * np.cos(yaw - yaw_hat) / np.where(var_xh > floor, var_xh, 1.0)
    if max_scale_deviation is not None:
        c = np.clip(c, 1.0 - max_scale_deviation, 1.0 + max_scale_deviation)
    c = np.where(valid, c, np.nan)
    rot = yaw_matrix(yaw)
    t = my - c[:, None] * (rot @ mx[..., None])[..., 0]
    fit = SimilarityFit(rot, c, t, np.full(p, np.nan), valid)
    if not residual:
        return fit, yaw
    var_y = (wn * (yc * yc).sum(-1)).sum(-1)
    resid = y - fit.apply(x)
    e2 = (wn * (resid * resid).sum(-1)).sum(-1)
    return SimilarityFit(rot, c, t, np.where(np.isfinite(e2), e2, var_y), valid), yaw


def rotation_weight(m: FloatArray) -> FloatArray:
    """Section 1.5: ``weight = sum_i m_ii / sum_ij |m_ij|`` (1 for the identity)."""
    m = np.asarray(m, dtype=float)
    return np.trace(m, axis1=-2, axis2=-1) / np.abs(m).sum(axis=(-2, -1))
