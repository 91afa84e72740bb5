"""Fast M/N logic initiator with velocity gates (three plots on three looks), vectorised.

The classic sliding-window logic (Blackman & Popoli 1999, Section 3.5; Bar-Shalom & Li 1995):
1. pairs ``(i, j)``, ``t_j > t_i``, with ``t_j - t_i`` in ``[min_dt, max_dt]`` (scan periods)
   and two-point speed ``|z_j - z_i| / (t_j - t_i)`` inside ``[min_speed, max_speed]`` widened
   by 3 sigma of the position errors (velocity gate);
2. triples ``(i, j, k)`` joining pairs ``(i, j)`` and ``(j, k)``; the third plot must fall in
   the gate of the straight-line prediction ``z_j + (z_j - z_i) tau``,
   ``tau = (t_k - t_j) / (t_j - t_i)``, whose covariance is
   ``R_k + (1 + tau)^2 R_j + tau^2 R_i + (a dt^2 / 2)^2 I`` (acceleration allowance);
3. conflicts (a plot in several triples) are resolved greedily by increasing ``d^2``, all in
   parallel: a triple wins when it is the best triple of each of its plots; winners and the
   triples they block are removed and the round repeats (a handful of rounds).
Plots in the window are candidates only (not used by tracks), so every triple starts a
tentative track whose three plots count as three hits of its M-of-N history.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from service.tracking import kalman
from service.tracking.groups import Groups, IntArray
from service.tracking.measurement import Measurements
from service.tracking.params import LogicParams


def _pairs(meas: Measurements, p: LogicParams, scan_period_s: float) -> tuple[IntArray, IntArray]:
    """Time-ordered pairs passing the time and velocity gates (step 1)."""
    n = len(meas)
    if n < 2:
        e = np.empty(0, dtype=np.intp)
        return e, e
    dt_min, dt_max = p.min_dt_scans * scan_period_s, p.max_dt_scans * scan_period_s
    sig = np.sqrt(np.trace(meas.covariance, axis1=1, axis2=2))  # per-plot 3-D position sigma
    radius = p.max_speed_mps * dt_max + 3.0 * 2.0 * float(sig.max())
    tree = cKDTree(meas.enu_m)
    pr = tree.query_pairs(radius, output_type="ndarray")
    if pr.shape[0] == 0:
        e = np.empty(0, dtype=np.intp)
        return e, e
    a, b = pr[:, 0].astype(np.intp), pr[:, 1].astype(np.intp)
    swap = meas.time_s[a] > meas.time_s[b]
    i = np.where(swap, b, a)
    j = np.where(swap, a, b)
    dt = meas.time_s[j] - meas.time_s[i]
    dist = np.linalg.norm(meas.enu_m[j] - meas.enu_m[i], axis=1)
    slack = 3.0 * np.hypot(sig[i], sig[j])
    ok = (dt >= dt_min) & (dt <= dt_max)
    ok &= dist <= p.max_speed_mps * dt + slack
    ok &= dist >= p.min_speed_mps * dt - slack
    return i[ok], j[ok]


def logic_initiate(meas: Measurements, params: LogicParams, scan_period_s: float) -> Groups:
    """Three-plot candidates from the window's plots (see module docstring)."""
    i, j = _pairs(meas, params, scan_period_s)
    if i.shape[0] < 2:
        return Groups.empty()
    # Step 2: join (i, j) with (j, k): pairs sorted by their first plot.
    order = np.argsort(i, kind="stable")
    first, second = i[order], j[order]
    lo = np.searchsorted(first, j, side="left")
    hi = np.searchsorted(first, j, side="right")
    cnt = hi - lo
    if cnt.sum() == 0:
        return Groups.empty()
    left = np.repeat(np.arange(i.shape[0]), cnt)
    offs = np.arange(left.shape[0]) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    right = lo[left] + offs
    a, b, c = i[left], j[left], second[right]
    t, z, R = meas.time_s, meas.enu_m, meas.covariance
    dt1 = t[b] - t[a]
    dt2 = t[c] - t[b]
    tau = dt2 / dt1
    pred = z[b] + (z[b] - z[a]) * tau[:, None]
    acc = (0.5 * params.max_accel_mps2 * (dt1 + dt2) ** 2) ** 2
    S = R[c] + ((1 + tau) ** 2)[:, None, None] * R[b] + (tau**2)[:, None, None] * R[a]
    S = S + acc[:, None, None] * np.eye(3)
    d2 = kalman.mahalanobis2(z[c] - pred, S)
    ok = d2 <= params.gate_chi2
    trip = np.stack([a[ok], b[ok], c[ok]], axis=1)
    cost = d2[ok]
    if trip.shape[0] == 0:
        return Groups.empty()
    chosen = resolve_conflicts(trip, cost, len(meas))
    trip = trip[chosen]
    g = trip.shape[0]
    return Groups(trip.ravel(), np.repeat(np.arange(g, dtype=np.intp), 3), g)


def resolve_conflicts(members: IntArray, cost: np.ndarray, n_plots: int) -> IntArray:
    """Greedy-by-cost selection of candidates with disjoint plots, in parallel rounds.

    ``members`` is ``(m, k)`` plot indices.  Equivalent to the sequential greedy (take the
    cheapest candidate, drop all that share a plot, repeat): a candidate that is the cheapest
    among all candidates touching its plots would be taken by the sequential form too.
    """
    m, k = members.shape
    rank = np.empty(m, dtype=np.int64)
    rank[np.lexsort((np.arange(m), cost))] = np.arange(m)  # unique ranks break ties by index
    alive = np.ones(m, dtype=bool)
    taken = np.zeros(m, dtype=bool)
    while alive.any():  # each round takes at least the globally cheapest alive candidate
        best = np.full(n_plots, np.iinfo(np.int64).max)
        idx = np.flatnonzero(alive)
        np.minimum.at(best, members[idx].ravel(), np.repeat(rank[idx], k))
        win = np.zeros(m, dtype=bool)
        win[idx] = np.all(best[members[idx]] == rank[idx, None], axis=1)
        taken |= win
        used = np.zeros(n_plots, dtype=bool)
        used[members[win].ravel()] = True
        alive &= ~win & ~used[members].any(axis=1)
    return np.flatnonzero(taken)
