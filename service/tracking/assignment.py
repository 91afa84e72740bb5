"""One-to-one assignment of plots to tracks within a batch (global nearest neighbour).

Costs are Mahalanobis distances ``d^2`` of gated (track, plot) candidates; a track left
without a plot pays ``miss_cost`` (the gate), so the solution minimises
``sum d^2 + miss_cost * (#unassigned tracks)`` (Blackman & Popoli 1999, Section 6.5).  Solved
with ``scipy.optimize.linear_sum_assignment`` on the ambiguous part only: candidates whose
track and plot both have a single candidate are their own connected component of the gating
graph and are taken directly, which gives the same optimum as one big problem.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from service.geo import FloatArray

IntArray = NDArray[np.intp]

#: Stand-in for "not allowed" in the dense sub-problem (finite: LSA needs a feasible problem).
_FORBIDDEN = 1e12


def _dense_ranks(index: IntArray) -> tuple[IntArray, int]:
    """Rank of each of ``index`` (non-negative ints) among its distinct values, and how many
    there are: ``np.unique(index, return_inverse=True)`` by counting, for small ints (track
    and plot rows)."""
    present = np.bincount(index) > 0
    rank = np.cumsum(present) - 1
    return rank[index], int(rank[-1]) + 1


def _dense_solve(
    rows: IntArray, cols: IntArray, cost: FloatArray, miss_cost: float
) -> tuple[IntArray, IntArray]:
    """LSA on ``[C | diag(miss_cost)]`` over the rows/columns present; returns chosen pair indices."""
    ri, nr = _dense_ranks(rows)
    ci, nc = _dense_ranks(cols)
    mat = np.full((nr, nc + nr), _FORBIDDEN)
    mat[ri, ci] = cost
    mat[np.arange(nr), nc + np.arange(nr)] = miss_cost
    r, c = linear_sum_assignment(mat)
    real = c < nc
    lookup = np.full((nr, nc), -1, dtype=np.intp)
    lookup[ri, ci] = np.arange(rows.shape[0])
    chosen = lookup[r[real], c[real]]
    return chosen, np.asarray(r[real])


def assign(rows: IntArray, cols: IntArray, cost: FloatArray, miss_cost: float) -> IntArray:
    """Indices (into the candidate arrays) of the chosen one-to-one pairs.

    ``rows``/``cols`` are the track/plot of each gated candidate (no duplicates), ``cost`` its
    ``d^2``; a candidate costing more than ``miss_cost`` is never chosen (a cost other than the
    gate's own ``d^2``, as the aid of association gives, :mod:`.aid`).
    """
    over = cost > miss_cost
    if over.any():
        keep = np.flatnonzero(~over)
        return keep[assign(rows[keep], cols[keep], cost[keep], miss_cost)]
    if rows.shape[0] == 0:
        return np.empty(0, dtype=np.intp)
    single = (np.bincount(rows)[rows] == 1) & (np.bincount(cols)[cols] == 1)
    direct = np.flatnonzero(single)
    rest = np.flatnonzero(~single)
    if rest.shape[0] == 0:
        return direct
    chosen, _ = _dense_solve(rows[rest], cols[rest], cost[rest], miss_cost)
    return np.sort(np.concatenate([direct, rest[chosen]]))


def clarity(rows: IntArray, cols: IntArray, d2: FloatArray, chosen: IntArray) -> FloatArray:
    """How clearly each chosen candidate's plot belonged to its track, in (0, 1].

    With the Gaussian likelihood ``L_k = exp(-d2_k / 2)`` of every gated candidate ``k``, the
    clarity of a chosen candidate ``c`` of track ``r`` and plot ``j`` is

        ``L_c / (sum_{k: row r} L_k + sum_{k: col j} L_k - L_c)``,

    the share of the likelihood that the chosen association holds among every association it
    competed with: the other plots in the track's gate and the other tracks whose gate held
    the plot (the association events that involve ``r`` or ``j``, weighed as JPDA weighs them;
    here only a figure of ambiguity: the update stays the one assignment; docs/architecture.md,
    "Track quality").  1 when the track and the plot had no other candidate.  ``L_k`` never
    underflows: the gate keeps ``d2 <= gate_chi2`` (16.3 by default), so ``L_k >= 3e-4``.
    """
    if chosen.shape[0] == 0:
        return np.empty(0)
    like = np.exp(-0.5 * d2)
    by_row = np.bincount(rows, weights=like)
    by_col = np.bincount(cols, weights=like)
    r, c = rows[chosen], cols[chosen]
    own = like[chosen]
    return np.asarray(own / (by_row[r] + by_col[c] - own))


def weighted_covariance(cov: FloatArray, clear: FloatArray, floor: float) -> FloatArray:
    """The covariances ``(n, k, k)`` of plots each weighed by its association's clarity
    ``clear`` (:func:`clarity`): ``cov / max(clear, floor)``.

    A plot that only partly belongs to its track (its likelihood shared with rivals) updates
    it as a plot of that much less information: the Kalman gain shrinks with the share, as the
    probabilistic data association's combined update weighs its one plot by its association
    probability (Bar-Shalom and Fortmann 1988, the probabilistic data association filter; there
    with the spread of the rivals added; here the track moves only towards its own plot, so two
    tracks never draw together, JPDA's coalescence).  ``floor`` in (0, 1]: the least weight; 1
    returns ``cov`` itself."""
    if floor >= 1.0 or clear.shape[0] == 0:
        return cov
    w = np.clip(clear, floor, 1.0)
    return np.asarray(cov / w[:, None, None])
