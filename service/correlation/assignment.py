"""One-to-one assignment of accepted candidates, with an ambiguity margin.

Accepted single decisions can share a track (two close targets both pass).  The candidates
form a sparse bipartite graph; ``scipy.optimize.linear_sum_assignment`` is run once on the
compressed cost matrix of the tracks that have more than one accepted candidate (isolated
candidates are taken as they are).  An assigned pair is then declared *ambiguous* (no
decision) when another accepted candidate of either of its tracks costs less than
``margin`` more -- a likelihood ratio of ``exp(margin / 2)`` for chi-square costs.  This is
what keeps the false-correlation rate low for targets closer than the radars can resolve.

With ``unmatched_cost`` given (the *joint* rule) the margin is measured between the chosen
assignment and the best alternative *assignment* that contains the rival, not the rival pair
alone: taking rival ``(x, y)`` breaks the assigned pairs ``(x, px)`` and ``(py, y)``, whose
tracks ``py`` and ``px`` are then either paired with each other (when that is a candidate)
or left unmatched, each lost match costing ``unmatched_cost``::

    regret(x, y) = c_xy + min(c_{py,px}, unmatched_cost) - c_{x,px} - c_{py,y}

(terms of pairs that do not exist dropped).  Each broken pair's margin is the smallest regret
of the alternatives that break it.  For chi-square costs this is the log-likelihood ratio
(times two) between the two joint hypotheses, so two close targets whose two pairings are
each only somewhat better than the crossed ones are resolved by the sum of both differences
(the single-pair rule saw one).  Alternatives changing more than two pairs are not looked at.
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
    start = np.empty(n, dtype=bool)  # (np.r_ costs ten times this on a few entries)
    start[0] = True
    np.not_equal(k_sorted[1:], k_sorted[:-1], out=start[1:])
    grp = np.cumsum(start) - 1
    first_idx = np.flatnonzero(start)
    g_best = c_sorted[first_idx]
    sizes = np.diff(first_idx, append=n)
    g_second = np.where(sizes > 1, c_sorted[np.minimum(first_idx + 1, n - 1)], np.inf)
    best[order] = g_best[grp]
    second[order] = g_second[grp]
    return best, second


def _joint_regret(
    ia: IntArray, ib: IntArray, c: FloatArray, assigned: BoolArray, unmatched_cost: float
) -> FloatArray:
    """Per candidate: the smallest regret (module docstring) of an alternative breaking it (inf
    for candidates not assigned, or assigned without a rival)."""
    n = ia.shape[0]
    regret = np.full(n, np.inf)
    if n == 0:
        return regret
    na = int(ia.max()) + 1
    nb = int(ib.max()) + 1
    pair_of_a = np.full(na, -1, dtype=np.intp)  # the assigned candidate of each A row
    pair_of_b = np.full(nb, -1, dtype=np.intp)
    sel = np.flatnonzero(assigned)
    pair_of_a[ia[sel]] = sel
    pair_of_b[ib[sel]] = sel
    riv = np.flatnonzero(~assigned)
    if riv.size == 0:
        return regret
    x, y = ia[riv], ib[riv]
    kx = pair_of_a[x]  # assigned pair (x, px), -1 if none
    ky = pair_of_b[y]  # assigned pair (py, y)
    cx = np.where(kx >= 0, c[np.maximum(kx, 0)], 0.0)
    cy = np.where(ky >= 0, c[np.maximum(ky, 0)], 0.0)
    # Re-pairing py with px: the cost of that candidate if it is one (a sparse lookup).
    both = (kx >= 0) & (ky >= 0)
    repair = np.full(riv.size, np.inf)
    if both.any():
        order = np.lexsort((ib, ia))
        keys = ia[order].astype(np.int64) * nb + ib[order]
        want = ia[ky[both]].astype(np.int64) * nb + ib[kx[both]]
        pos = np.minimum(np.searchsorted(keys, want), n - 1)
        found = keys[pos] == want
        repair[np.flatnonzero(both)] = np.where(found, c[order[pos]], np.inf)
    rest = np.where(both, np.minimum(repair, unmatched_cost), 0.0)
    r = c[riv] + rest - cx - cy
    np.minimum.at(regret, kx[kx >= 0], r[kx >= 0])
    np.minimum.at(regret, ky[ky >= 0], r[ky >= 0])
    return regret


def rival_costs(keys: IntArray, cost: FloatArray) -> FloatArray:
    """Per entry: the lowest cost among the *other* entries sharing its key (inf: none)."""
    best, second = _second_best(keys, cost)
    return np.where(cost <= best, second, best)


def assign_unambiguous(
    index_a: IntArray,
    index_b: IntArray,
    cost: FloatArray,
    accepted: BoolArray,
    margin: float,
    unmatched_cost: float | None = None,
) -> tuple[BoolArray, BoolArray]:
    """Return ``(chosen, ambiguous)`` masks over the candidates.

    ``chosen``: the one-to-one assignment among accepted candidates minus the ambiguous ones.
    ``unmatched_cost``: None, the single-pair margin; else the joint rule (module docstring).
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
    if unmatched_cost is not None:
        amb = assigned & (_joint_regret(ia, ib, c, assigned, unmatched_cost) < margin)
    else:
        rival_a = rival_costs(ia, c)
        rival_b = rival_costs(ib, c)
        amb = assigned & ((rival_a - c < margin) | (rival_b - c < margin))
    chosen[acc] = assigned & ~amb
    ambiguous[acc] = amb
    return chosen, ambiguous
