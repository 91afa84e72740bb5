"""One-to-one assignment of accepted candidates, with an ambiguity margin.

Accepted single decisions can share a track (two close targets both pass).  The candidates
form a sparse bipartite graph; ``scipy.optimize.linear_sum_assignment`` is run once on the
compressed cost matrix of the tracks that have more than one accepted candidate (isolated
candidates are taken as they are).  An assigned pair is then declared *ambiguous* (no
decision) when another accepted candidate of either of its tracks costs less than
``margin`` more -- a likelihood ratio of ``exp(margin / 2)`` for chi-square costs.  This is
what keeps the false-correlation rate low for targets closer than the radars can resolve.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from service.correlation.base import BoolArray, FloatArray, IntArray

#: Cost given to non-candidates inside the compressed assignment matrix.
_FORBIDDEN = 1e12


def _second_best(keys: IntArray, cost: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per entry: best and second-best cost among entries sharing its key."""
    n = keys.shape[0]
    best = np.full(n, np.inf)
    second = np.full(n, np.inf)
    if n == 0:
        return best, second
    order = np.lexsort((cost, keys))
    k_sorted = keys[order]
    c_sorted = cost[order]
    start = np.r_[True, k_sorted[1:] != k_sorted[:-1]]
    grp = np.cumsum(start) - 1
    first_idx = np.flatnonzero(start)
    g_best = c_sorted[first_idx]
    sizes = np.diff(np.r_[first_idx, n])
    g_second = np.where(sizes > 1, c_sorted[np.minimum(first_idx + 1, n - 1)], np.inf)
    best[order] = g_best[grp]
    second[order] = g_second[grp]
    return best, second


def assign_unambiguous(
    index_a: IntArray, index_b: IntArray, cost: FloatArray, accepted: BoolArray, margin: float
) -> tuple[BoolArray, BoolArray]:
    """Return ``(chosen, ambiguous)`` masks over the candidates.

    ``chosen``: the one-to-one assignment among accepted candidates minus the ambiguous ones.
    """
    n = index_a.shape[0]
    chosen = np.zeros(n, dtype=bool)
    ambiguous = np.zeros(n, dtype=bool)
    acc = np.flatnonzero(accepted & np.isfinite(cost))
    if acc.size == 0:
        return chosen, ambiguous
    ia, ib, c = index_a[acc], index_b[acc], cost[acc]
    _, inv_a, cnt_a = np.unique(ia, return_inverse=True, return_counts=True)
    _, inv_b, cnt_b = np.unique(ib, return_inverse=True, return_counts=True)
    simple = (cnt_a[inv_a] == 1) & (cnt_b[inv_b] == 1)
    assigned = simple.copy()
    multi = np.flatnonzero(~simple)
    if multi.size:
        ra, rows = np.unique(ia[multi], return_inverse=True)
        rb, cols = np.unique(ib[multi], return_inverse=True)
        mat = np.full((ra.size, rb.size), _FORBIDDEN)
        mat[rows, cols] = c[multi]
        r_idx, c_idx = linear_sum_assignment(mat)
        hit = mat[r_idx, c_idx] < _FORBIDDEN
        sel = np.zeros((ra.size, rb.size), dtype=bool)
        sel[r_idx[hit], c_idx[hit]] = True
        assigned[multi] = sel[rows, cols]
    best_a, second_a = _second_best(ia, c)
    best_b, second_b = _second_best(ib, c)
    rival_a = np.where(c <= best_a, second_a, best_a)
    rival_b = np.where(c <= best_b, second_b, best_b)
    amb = assigned & ((rival_a - c < margin) | (rival_b - c < margin))
    chosen[acc] = assigned & ~amb
    ambiguous[acc] = amb
    return chosen, ambiguous
