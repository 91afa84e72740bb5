"""Fast M/N logic initiator with velocity gates (three plots on three looks), vectorised.

The classic sliding-window logic (Blackman & Popoli 1999, Section 3.5; Bar-Shalom & Li 1995):
1. pairs ``(i, j)``, ``t_j > t_i``, with ``t_j - t_i`` in ``[min_dt, max_dt]`` (scan periods)
   and two-point speed ``|z_j - z_i| / (t_j - t_i)`` inside ``[min_speed, max_speed]`` widened
   by 3 sigma of the position errors (velocity gate);
2. triples ``(i, j, k)`` joining pairs ``(i, j)`` and ``(j, k)``; the third plot must fall in
   the gate of the straight-line prediction ``z_j + (z_j - z_i) tau``,
   ``tau = (t_k - t_j) / (t_j - t_i)``, whose covariance is
   ``R_k + (1 + tau)^2 R_j + tau^2 R_i + (a dt^2 / 2)^2 I`` (acceleration allowance);
3. conflicts (a plot in several triples) are resolved greedily by increasing cost, all in
   parallel: a triple wins when it is the best triple of each of its plots; winners and the
   triples they block are removed and the round repeats (a handful of rounds).  The cost is
   ``d^2 - support_weight * ln(support)`` (:func:`velocity_support`: how many triples nearby
   share this one's velocity), so that in a formation each aircraft's own plots win over a
   line across the formation that is just as straight (:class:`LogicParams`).
Plots in the window are candidates only (not used by tracks), so every triple starts a
tentative track whose three plots count as three hits of its M-of-N history.

Memory and work per call are bounded (:class:`~service.tracking.params.BoundParams`): the
pairs come from a blockwise search of later plots in the time gate
(:mod:`service.tracking.pairs`, at most ``max_pairs`` candidates), and the triples are formed
and gated in blocks, at most ``max_triples`` of them (pairs with the fewest continuations
first).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.tracking import kalman
from service.tracking.groups import Groups, IntArray
from service.tracking.measurement import Measurements
from service.tracking.pairs import time_gated_pairs
from service.tracking.params import BoundParams, LogicParams


def _pairs(
    meas: Measurements, p: LogicParams, scan_period_s: float, bounds: BoundParams
) -> tuple[IntArray, IntArray]:
    """Time-ordered pairs passing the time and velocity gates (step 1), searched with bounded
    memory and work (:func:`service.tracking.pairs.time_gated_pairs`)."""
    n = len(meas)
    if n < 2:
        e = np.empty(0, dtype=np.intp)
        return e, e
    dt_min, dt_max = p.min_dt_scans * scan_period_s, p.max_dt_scans * scan_period_s
    sig = np.sqrt(np.trace(meas.covariance, axis1=1, axis2=2))  # per-plot 3-D position sigma
    # Search reach: the speed gate below never accepts a pair farther apart than this.
    radius = p.max_speed_mps * dt_max + 3.0 * 2.0 * float(sig.max())
    t, z = meas.time_s, meas.enu_m

    def gates(i: IntArray, j: IntArray) -> np.ndarray:
        dt = t[j] - t[i]
        dist = np.linalg.norm(z[j] - z[i], axis=1)
        slack = 3.0 * np.hypot(sig[i], sig[j])
        ok = (dt >= dt_min) & (dt <= dt_max)
        ok &= dist <= p.max_speed_mps * dt + slack
        ok &= dist >= p.min_speed_mps * dt - slack
        return ok

    return time_gated_pairs(t, z, radius, dt_min, dt_max, gates, bounds.max_pairs, bounds.block)


def _triple_counts(cnt: IntArray, max_triples: int) -> IntArray:
    """Triples per pair, zero for the pairs beyond the ``max_triples`` work bound: pairs are
    taken with the fewest continuations first (the least ambiguous; ties in pair order) and
    the first pair whose triples would pass the bound, and every later one, gives none."""
    if int(cnt.sum()) <= max_triples:
        return cnt
    by_count = np.argsort(cnt, kind="stable")
    fits = np.cumsum(cnt[by_count]) <= max_triples
    out = np.zeros_like(cnt)
    out[by_count[fits]] = cnt[by_count[fits]]
    return out


def _gate_triples(
    meas: Measurements, params: LogicParams, a: IntArray, b: IntArray, c: IntArray
) -> tuple[np.ndarray, np.ndarray]:
    """Step 2's third-plot gate: ``(ok, d^2)`` of triples ``(a, b, c)``."""
    t, z, R = meas.time_s, meas.enu_m, meas.covariance
    dt1 = t[b] - t[a]
    dt2 = t[c] - t[b]
    tau = dt2 / dt1
    pred = z[b] + (z[b] - z[a]) * tau[:, None]
    acc = (0.5 * params.max_accel_mps2 * (dt1 + dt2) ** 2) ** 2
    S = R[c] + ((1 + tau) ** 2)[:, None, None] * R[b] + (tau**2)[:, None, None] * R[a]
    S = S + acc[:, None, None] * np.eye(3)
    d2 = kalman.mahalanobis2(z[c] - pred, S)
    return d2 <= params.gate_chi2, d2


def logic_initiate(
    meas: Measurements, params: LogicParams, scan_period_s: float, bounds: BoundParams | None = None
) -> Groups:
    """Three-plot candidates from the window's plots (see module docstring); memory and work
    within ``bounds`` (default :class:`BoundParams`)."""
    bounds = bounds if bounds is not None else BoundParams()
    i, j = _pairs(meas, params, scan_period_s, bounds)
    if i.shape[0] < 2:
        return Groups.empty()
    # Step 2: join (i, j) with (j, k): pairs sorted by their first plot.
    order = np.argsort(i, kind="stable")
    first, second = i[order], j[order]
    lo = np.searchsorted(first, j, side="left")
    hi = np.searchsorted(first, j, side="right")
    cnt = _triple_counts(hi - lo, bounds.max_triples)
    if cnt.sum() == 0:
        return Groups.empty()
    # Triples in blocks of consecutive pairs (``block`` triples, plus one pair's own), in the
    # order of one pass over all pairs; the gate is per triple, so blocks change nothing.
    if int(cnt.sum()) <= bounds.block:
        cuts = np.array([0, cnt.shape[0]])
    else:
        start = np.cumsum(cnt) - cnt
        edges = np.flatnonzero(np.diff(start // max(bounds.block, 1))) + 1
        cuts = np.concatenate([[0], edges, [cnt.shape[0]]])
    trips: list[np.ndarray] = []
    costs: list[np.ndarray] = []
    for p0, p1 in zip(cuts[:-1].tolist(), cuts[1:].tolist(), strict=True):  # a few blocks
        bc = cnt[p0:p1]
        if bc.sum() == 0:
            continue
        left = np.repeat(np.arange(p0, p1), bc)
        offs = np.arange(left.shape[0]) - np.repeat(np.cumsum(bc) - bc, bc)
        right = lo[left] + offs
        a, b, c = i[left], j[left], second[right]
        ok, d2 = _gate_triples(meas, params, a, b, c)
        trips.append(np.stack([a[ok], b[ok], c[ok]], axis=1))
        costs.append(d2[ok])
    trip = np.concatenate(trips) if trips else np.empty((0, 3), dtype=np.intp)
    cost = np.concatenate(costs) if costs else np.empty(0)
    if trip.shape[0] == 0:
        return Groups.empty()
    if params.support_weight > 0.0:
        support = velocity_support(
            meas, trip, params.support_radius_m, params.support_sigma, params.support_max_pairs
        )
        cost = cost - params.support_weight * np.log(support)
    chosen = resolve_conflicts(trip, cost, len(meas))
    trip = trip[chosen]
    g = trip.shape[0]
    return Groups(trip.ravel(), np.repeat(np.arange(g, dtype=np.intp), 3), g)


def velocity_support(
    meas: Measurements,
    trip: IntArray,
    radius_m: float,
    k_sigma: float,
    max_pairs: int = LogicParams.support_max_pairs,
) -> np.ndarray:
    """Per triple ``(a, b, c)`` of ``trip``: how many triples (itself included) have their first
    plot within ``radius_m`` of its first plot and their two-point velocity
    ``(z_c - z_a) / (t_c - t_a)`` within ``k_sigma`` velocity errors of its own, on each
    horizontal axis (the error: the median over the triples of
    ``sqrt(trace(R_a + R_c)) / (t_c - t_a)`` in the plane): one k-d tree count in the four
    scaled coordinates (Chebyshev distance 1).

    Its work is the number of (triple, neighbour) pairs, which grows with the square of a dense
    window's triples (a formation's first scans, a flood of plots).  The triples are first
    counted in the cells of side 2 (a ball's width) of the scaled coordinates; when the sum of
    the squared cell counts, the pairs a ball count would visit about, exceeds ``max_pairs``,
    each triple's support is the count of its own cell instead: ``O(T log T)`` for ``T``
    triples either way."""
    t, z, R = meas.time_s, meas.enu_m, meas.covariance
    a, c = trip[:, 0], trip[:, 2]
    dt = t[c] - t[a]
    velocity = (z[c, :2] - z[a, :2]) / dt[:, None]
    sigma = np.sqrt(np.trace(R[a, :2, :2] + R[c, :2, :2], axis1=1, axis2=2)) / dt
    scale = max(k_sigma * float(np.median(sigma)), 1e-9)
    points = np.column_stack([z[a, :2] / radius_m, velocity / scale])
    in_cell = cell_counts(points)
    if float(np.sum(in_cell.astype(float))) <= max_pairs:  # (each triple's own count: sum n_c^2)
        counts = cKDTree(points).query_ball_point(points, 1.0, p=np.inf, return_length=True)
        return np.asarray(counts, dtype=float)
    return in_cell.astype(float)


def cell_counts(points: np.ndarray) -> NDArray[np.int64]:
    """Per row of ``points``: how many rows share its cell of side 2 (``floor(x / 2)`` on every
    axis)."""
    cells = np.floor(points / 2.0).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    return np.asarray(counts[inverse.reshape(-1)], dtype=np.int64)


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
