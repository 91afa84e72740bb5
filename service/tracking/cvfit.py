"""Constant-velocity least-squares fits of many plot sets at once (2-D plane).

The consistency test behind the fixes of the Hough paper's velocity clustering (Section 2,
Steps 7-8, see :mod:`.clustering`): the paper's premise is that the plots of one track obey
"approximately uniform straight-line motion", i.e. ``x_p = x_0 + v (t_p - t_ref) + e_p`` with
``e_p ~ N(0, C_p)`` (``C_p`` the plot's location covariance, whose trace is the paper's
``delta^2``).  For a set of plots the weighted least-squares estimate of ``theta = [x_0, v]``
solves ``A theta = b`` with ``A = sum H_p^T W_p H_p``, ``b = sum H_p^T W_p z_p``,
``H_p = [I, tau_p I]``, ``W_p = C_p^-1`` (Bar-Shalom, Li, Kirubarajan 2001, Section 3.4), and
its residual is ``chi2 = sum z_p^T W_p z_p - b^T theta`` with ``2 n - 4`` degrees of freedom.

``A``, ``b`` and ``sum z^T W z`` are sums over the plots, so for a boolean membership matrix
``M`` (sets x plots) all sets are fitted by one matrix product ``M @ stats``: no loop over
sets.  Plots with equal time stamps need no special case: the fit asks them to agree within
their location errors (the paper's rule for equal time stamps, Section 2.1).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from service.chi2 import chi2_quantile
from service.geo import FloatArray

BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class PlotStats:
    """Per-plot terms of the normal equations, relative to ``t_ref``."""

    tau: FloatArray  # (n,) t - t_ref
    z: FloatArray  # (n, 2)
    W: FloatArray  # (n, 2, 2) inverse covariances
    AtA: FloatArray  # (n, 16) H^T W H flattened
    Atz: FloatArray  # (n, 4)   H^T W z
    z_w_z: FloatArray  # (n,)
    C: FloatArray  # (n, 2, 2) covariances (the prediction gate adds them to H P H^T)


def plot_stats(t: FloatArray, xy: FloatArray, cov: FloatArray, t_ref: float) -> PlotStats:
    """The per-plot sufficient statistics of the CV fit (see module docstring)."""
    n = t.shape[0]
    tau = np.asarray(t, dtype=float) - t_ref
    W = np.asarray(np.linalg.inv(cov), dtype=float)
    H = np.zeros((n, 2, 4))
    H[:, 0, 0] = H[:, 1, 1] = 1.0
    H[:, 0, 2] = H[:, 1, 3] = tau
    HtW = np.swapaxes(H, 1, 2) @ W  # (n, 4, 2)
    AtA = (HtW @ H).reshape(n, 16)
    Atz = np.einsum("nij,nj->ni", HtW, xy)
    z_w_z = np.einsum("ni,nij,nj->n", xy, W, xy)
    return PlotStats(tau, np.asarray(xy, dtype=float), W, AtA, Atz, z_w_z, np.asarray(cov, dtype=float))


@dataclass(frozen=True)
class SetFits:
    """CV fits of ``m`` sets: state at ``t_ref``, covariance, residual chi2, validity."""

    theta: FloatArray  # (m, 4) [x0, y0, vx, vy]
    cov: FloatArray  # (m, 4, 4) A^-1
    chi2: FloatArray  # (m,)
    size: NDArray[np.int64]  # (m,)
    valid: BoolArray  # (m,) False: degenerate (fewer than 2 distinct times)


def fit_sets(stats: PlotStats, members: BoolArray, min_span_s: float) -> SetFits:
    """Weighted LS CV fit of every row of ``members`` (sets x plots) at once."""
    m = members.shape[0]
    mf = members.astype(float)
    A = (mf @ stats.AtA).reshape(m, 4, 4)
    b = mf @ stats.Atz
    c = mf @ stats.z_w_z
    size = members.sum(axis=1).astype(np.int64)
    big = np.where(members, stats.tau[None, :], -np.inf).max(axis=1)
    small = np.where(members, stats.tau[None, :], np.inf).min(axis=1)
    valid = (size >= 2) & (big - small >= min_span_s)
    A = np.where(valid[:, None, None], A, np.eye(4))  # degenerate sets: placeholder, flagged
    cov = np.asarray(np.linalg.inv(A), dtype=float)
    theta = np.einsum("mij,mj->mi", cov, b)
    chi2 = np.where(valid, np.maximum(c - np.einsum("mi,mi->m", b, theta), 0.0), np.inf)
    return SetFits(theta, cov, chi2, size, valid)


def _quad(r0: FloatArray, r1: FloatArray, w00: FloatArray, w01: FloatArray, w11: FloatArray) -> FloatArray:
    """``r^T W r`` for 2-vectors, element-wise (faster than einsum over small axes)."""
    return np.asarray(w00 * r0 * r0 + 2.0 * w01 * r0 * r1 + w11 * r1 * r1)


def residual_d2(stats: PlotStats, fits: SetFits, predicted: bool) -> FloatArray:
    """``(m, n)`` normalised squared distance of every plot to every set's fitted line.

    ``predicted`` False: ``r^T C_p^-1 r`` (members' residual test); True: the prediction gate
    ``r^T (C_p + H_p A^-1 H_p^T)^-1 r`` for plots outside the set.
    """
    th = fits.theta
    tau = stats.tau[None, :]
    r0 = stats.z[None, :, 0] - (th[:, 0, None] + th[:, 2, None] * tau)  # (m, n)
    r1 = stats.z[None, :, 1] - (th[:, 1, None] + th[:, 3, None] * tau)
    W = stats.W
    if not predicted:
        return _quad(r0, r1, W[None, :, 0, 0], W[None, :, 0, 1], W[None, :, 1, 1])
    # S = C_p + H P H^T with H = [I, tau I]: P_xx + tau (P_xv + P_vx) + tau^2 P_vv.
    C = stats.C
    P = fits.cov[:, None]

    def s(i: int, j: int) -> FloatArray:
        return np.asarray(
            C[None, :, i, j]
            + P[..., i, j]
            + tau * (P[..., i, 2 + j] + P[..., 2 + i, j])
            + tau**2 * P[..., 2 + i, 2 + j]
        )

    s00, s01, s11 = s(0, 0), s(0, 1), s(1, 1)
    det = s00 * s11 - s01 * s01
    return _quad(r0, r1, s11 / det, -s01 / det, s00 / det)


@lru_cache(maxsize=32)
def chi2_limits(confidence: float, max_dof: int) -> FloatArray:
    """``chi2.ppf(confidence, k)`` for ``k = 0 .. max_dof`` (rounded up to a power of two so
    that the cache stays small); entry 0 is unused."""
    size = 1 << max(int(max_dof), 1).bit_length()
    return np.asarray(chi2_quantile(confidence, np.maximum(np.arange(size + 1), 1)))


def consistent(
    stats: PlotStats,
    members: BoolArray,
    min_span_s: float,
    plot_gate: float,
    fit_confidence: float,
    speed_mps: tuple[float, float],
) -> tuple[BoolArray, SetFits]:
    """Which sets are one constant-velocity target: a non-degenerate fit (time span at least
    ``min_span_s``), every member within ``plot_gate`` (``r^T C^-1 r``), total chi-square below
    its ``fit_confidence`` quantile with ``2 n - 4`` degrees of freedom (sets of two plots have
    no residual and pass on the per-plot test), speed inside ``speed_mps``."""
    fits = fit_sets(stats, members, min_span_s)
    d2 = residual_d2(stats, fits, predicted=False)
    worst = np.where(members, d2, 0.0).max(axis=1) if members.shape[1] else np.zeros(members.shape[0])
    dof = np.maximum(2 * fits.size - 4, 1)
    speed = np.linalg.norm(fits.theta[:, 2:], axis=1)
    ok = (
        fits.valid
        & (worst <= plot_gate)
        & (fits.chi2 <= chi2_limits(fit_confidence, int(dof.max(initial=1)))[dof])
    )
    ok &= (speed >= speed_mps[0]) & (speed <= speed_mps[1])
    return np.asarray(ok), fits
