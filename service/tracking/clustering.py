"""Velocity fuzzy clustering of a preliminary track (Hough paper Section 2, Eq. 7-10).

This module holds Eq. (7)-(10) and Steps 1-8 *as published* (the ablation baseline); the form
used by the initiators, with Steps 7-8 fixed, is :mod:`service.tracking.velocity_tracks`.

Given the plots of one preliminary track (position, time stamp ``t``, location error
``delta``), sorted by time (Step 2):

* Eq. (7): ``v_ij = (x_j - x_i) / (t_j - t_i)`` for ``i < j`` (``|t_j - t_i| >= min_dt``);
* Eq. (8): closeness of two velocities from plot ``i``:
  ``d_ijk = exp(-|v_ij - v_ik|^2 (delta_i delta_j delta_k)^eta / (|x_i-x_j|^eta |x_i-x_k|^eta))``
  for ``j != k`` and the threshold term
  ``d_ikk = exp(-lambda |dv|^2 (delta_i delta_k^2)^eta / |x_i - x_k|^(2 eta))``;
* Eq. (9): ``u_ijk = d_ijk^(1/(c-1)) / sum_s d_isk^(1/(c-1))`` (computed in the log domain:
  in SI units the exponents of Eq. 8 are large and ``d`` underflows);
* Eq. (10): ``U_i = [u_ijk]``, rows ``j``, columns ``k``, both ``> i``;
* Step 5: for column ``k`` of ``U_i``, ``A_ik = {i, k} U {j : u_ijk > u_ikk}``, empty when the
  column's maximum is on the diagonal; Step 6 repeats for every ``i``;
* Step 7: sets sharing ``merge_overlap`` (2) or more plots are merged, until none do;
* Step 8: every remaining set (of at least ``min_plots``) starts one track.

Notes. Eq. (9) divides a whole column by one sum, so ``u_ijk > u_ikk`` iff ``d_ijk > d_ikk``
and the decision does not depend on ``c``; the paper calls ``U_i`` symmetric, which holds for
``d`` (Eq. 8 is symmetric in ``j, k``) but not for the column-normalised ``u``.  Pairs with
equal time stamps give no velocity (``d = 0``); as the paper says, they can still end in one
set through the merging of Step 7.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from service.geo import FloatArray
from service.tracking.groups import IntArray
from service.tracking.params import ClusterParams


def log_closeness(t: FloatArray, x: FloatArray, delta: FloatArray, p: ClusterParams) -> FloatArray:
    """``log d_ijk`` of Eq. (8) as an ``(S, S, S)`` array (``-inf`` where undefined).

    Plots must be sorted by time.  Entry ``[i, j, k]`` is defined for ``j > i`` and ``k > i``.
    """
    s = t.shape[0]
    dt = t[None, :] - t[:, None]  # dt[i, j] = t_j - t_i
    dx = x[None, :, :] - x[:, None, :]  # (S, S, d)
    upper = np.triu(np.ones((s, s), dtype=bool), 1)
    valid = upper & (np.abs(dt) >= p.min_dt_s)
    v = dx / np.where(valid, dt, 1.0)[..., None]  # Eq. (7)
    dist = np.linalg.norm(dx, axis=-1)
    dist = np.maximum(dist, 1e-6)  # floor (m): coincident plots, avoids 0 / 0
    eta = p.eta
    # j != k term: |v_ij - v_ik|^2 (d_i d_j d_k)^eta / (|x_ij|^eta |x_ik|^eta), written as
    # (|v_ij|^2 + |v_ik|^2 - 2 v_ij . v_ik) d_i^eta w_ij w_ik with w_ij = d_j^eta / |x_ij|^eta
    # (a batched Gram product: no (S, S, S, 2) temporary).
    vv = np.sum(v * v, axis=-1)  # (S, S)
    logd = v @ np.swapaxes(v, 1, 2)  # [i, j, k] = v_ij . v_ik
    logd *= -2.0
    logd += vv[:, :, None]
    logd += vv[:, None, :]
    np.maximum(logd, 0.0, out=logd)  # rounding
    w = delta[None, :] ** eta / dist**eta
    logd *= -(delta[:, None, None] ** eta) * w[:, :, None]
    logd *= w[:, None, :]
    # j == k term: lambda |dv|^2 (d_i d_k^2)^eta / |x_ik|^(2 eta)
    diag = -p.lam * p.delta_v_mps**2 * (delta[:, None] * delta[None, :] ** 2) ** eta / dist ** (2 * eta)
    jj = np.arange(s)
    logd[:, jj, jj] = diag
    ok = valid[:, :, None] & valid[:, None, :]
    return np.where(ok, logd, -np.inf)


def similarity(logd: FloatArray, p: ClusterParams) -> FloatArray:
    """Eq. (9)-(10): ``u_ijk``, normalised over rows ``s > i`` of each column ``k``."""
    e = logd / (p.c - 1.0)
    m = np.max(e, axis=1, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    w = np.exp(e - m)
    tot = w.sum(axis=1, keepdims=True)
    return np.asarray(np.where(tot > 0, w / np.where(tot > 0, tot, 1.0), 0.0))


def candidate_sets(logd: FloatArray) -> np.ndarray:
    """Steps 5-6: the non-empty sets ``A_ik`` as a boolean ``(n_sets, S)`` matrix."""
    s = logd.shape[0]
    jj = np.arange(s)
    diag = logd[:, jj, jj]  # [i, k] = log d_ikk
    beats = logd > diag[:, None, :]  # [i, j, k]: u_ijk > u_ikk (same order as d, see notes)
    beats[:, jj, jj] = False
    beats &= np.isfinite(diag)[:, None, :]
    has = beats.any(axis=1)  # [i, k]: column k's maximum is off the diagonal
    ii, kk = np.nonzero(has)
    sets = np.swapaxes(beats, 1, 2)[ii, kk].copy()  # (n_sets, S): the j's
    sets[np.arange(ii.shape[0]), ii] = True
    sets[np.arange(ii.shape[0]), kk] = True
    return sets


def merge_sets(sets: np.ndarray, overlap: int) -> np.ndarray:
    """Step 7: merge sets sharing ``overlap`` or more plots, repeatedly, until none do."""
    while sets.shape[0] > 1:
        m = sets.astype(np.int32)
        share = (m @ m.T) >= overlap
        n_comp, label = connected_components(csr_matrix(share), directed=False)
        if n_comp == sets.shape[0]:
            break
        merged = np.zeros((n_comp, sets.shape[1]), dtype=bool)
        np.logical_or.at(merged, label, sets)
        sets = merged
    return sets


def velocity_cluster_published(
    t: FloatArray, x: FloatArray, delta: FloatArray, p: ClusterParams
) -> list[IntArray]:
    """Steps 1-8 exactly as published (Step 7: merge on overlap alone); index arrays into the
    given plots.  Kept as the ablation baseline of the fixed form :func:`velocity_cluster`."""
    s = t.shape[0]
    if s < 3:
        return []
    order = np.argsort(t, kind="stable")  # Step 2
    logd = log_closeness(t[order], x[order], delta[order], p)  # Step 3, Eq. (7)-(8)
    sets = candidate_sets(logd)  # Steps 4-6 (Eq. 9-10 via the order-preserving d)
    if sets.shape[0] == 0:
        return []
    sets = merge_sets(sets, p.merge_overlap)  # Step 7
    sizes = sets.sum(axis=1)
    sets = sets[sizes >= p.min_plots]  # Step 8
    return [np.sort(order[row]) for row in sets]
