"""The local offset of a group of tracks: what a formation gives before registration.

In a formation (tens of aircraft a few hundred metres apart, one heading and speed) every
reference's topology sequence looks like its neighbours': with the spacing comparable to the
radars' cross-range error the neighbour pairing of the topology match (SVD paper Section 2
step 2) cannot tell the lattice's elements apart, and nothing is decided.  The group as a
whole still carries the registration: both radars see the same aircraft, displaced by the
same local bias offset ``o`` (Eq. (2): the displacement varies with range and azimuth, by a
few tens of metres over a group a few kilometres wide).

For every candidate pair ``(i, j)`` the absolute difference ``D_ij = x_A,i - x_B,j`` (B's ENU
orientation) is ``o + e_ij`` for the true pairs and ``o + (x_i - x_j) + e_ij`` for the others.
Around each reference ``i`` the differences of the candidates of the *other* A tracks within
``radius_m`` form a cloud whose densest point is ``o``: every true pair sits there, while a
false pairing's difference is shared only by the pairings shifted by the same separation
(fewer: the lattice's edge and its irregularity break the others).  Each candidate's
*support* is the kernel-weighted count of the candidates of the other nearby tracks with
nearly the same difference (kernel ``support_bandwidth`` times the median relative noise);
the offset ``o_i`` is refined from each of the ``starts`` best-supported differences among the
reference's voters by matching: each nearby track's candidate nearest the offset (within a
gate) and the offset their mean, a few times (iterated closest points with the
translation-only model); the start whose matching pairs the most tracks wins (then the least
total chi-square): a lattice shift of the true offset leaves an edge of the group unmatched.
(Started from the mean of the differences, or refined by a kernel average, it settles on a
lattice shift one spacing off as often as not, and registration follows it.)
The residual ``r_ij = D_ij - o_i`` with covariance ``P_A + P_B``
is one look at the pair for the history evidence (:mod:`.evidence`); ``Cov(o_i)``, the
kernel-weighted noise over the effective number of supporting candidates, is common to the
pairs of the neighbourhood.  Leaving row ``i``'s own candidates out keeps a pair from
supporting itself.  The translation-only model is the topology fit of Eq. (7) with the
rotation and scale fixed at their prior (identity), over the whole neighbourhood and without
element pairing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
from annotated_types import Ge
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.correlation.base import FloatArray, IntArray, PredictedTracks
from service.linalg import congruence


@dataclass(frozen=True)
class GroupOffsetParams:
    """The local-offset estimate of :mod:`.group_offset`."""

    #: Use it (before registration, ``svd-topology``).
    enabled: bool = True
    #: Neighbourhood radius (m) around a reference whose other tracks' candidates vote.
    radius_m: float = 5_000.0
    #: Minimum other A tracks in the neighbourhood for an estimate (fewer: a formation is not
    #: what the reference is in, and the topology match alone decides).
    min_tracks: int = 4
    #: Kernel width of the support count, in units of the median relative noise.
    support_bandwidth: float = 1.0
    #: Starts per reference: its this many best-supported voters, each refined (below); the
    #: one matching the most tracks wins.
    starts: int = 4
    #: Refinements after each start: each nearby track's candidate nearest the
    #: offset within ``gate_chi2`` (horizontal, 2 dof; 99 %), the offset their mean.
    iterations: int = 3
    gate_chi2: float = 9.21
    #: At most this many votes, and (candidate, candidate) comparisons for the support counts,
    #: in one update; beyond it the offsets are not estimated (the topology match alone
    #: decides).
    max_comparisons: int = 4_000_000
    #: At most this many candidates vote in one neighbourhood (the nearest tracks' first):
    #: bounds the work of a very dense picture.
    max_votes: Annotated[int, Ge(1)] = 4_000


def group_residuals(
    a: PredictedTracks,
    b: PredictedTracks,
    ia: IntArray,
    ib: IntArray,
    params: GroupOffsetParams,
) -> tuple[NDArray[np.bool_], FloatArray, FloatArray, FloatArray]:
    """Residuals of candidates ``(ia[k], ib[k])`` against their neighbourhood's offset.

    Returns ``(ok, r, s_noise, s_common)``: which candidates got an estimate, and for those
    the residual (B's ENU orientation; A's for a reference source B), its random covariance
    and the offset's covariance (common to the neighbourhood).
    """
    n = len(ia)
    ok = np.zeros(n, dtype=bool)
    empty = (ok, np.empty((0, 3)), np.empty((0, 3, 3)), np.empty((0, 3, 3)))
    if n == 0 or len(a) < params.min_tracks + 1:
        return empty
    site = b.site if b.site is not None else a.site
    rot = np.eye(3) if site is None else site.rotation
    d = (a.position[ia] - b.position[ib]) @ rot
    s = congruence(rot.T, a.pos_cov[ia] + b.pos_cov[ib])
    var_h = 0.5 * (s[:, 0, 0] + s[:, 1, 1])
    # Votes: (reference row i, candidate c) with c's A track within radius of i, not i itself.
    rows = np.unique(ia)
    tree = cKDTree(a.position)
    near = tree.sparse_distance_matrix(cKDTree(a.position[rows]), params.radius_m, output_type="ndarray")
    k_track, i_ref = near["i"].astype(np.intp), rows[near["j"]]
    keep = k_track != i_ref
    k_track, i_ref = k_track[keep], i_ref[keep]
    n_other = np.bincount(i_ref, minlength=len(a))
    # Candidates by A track: c in [start[k], start[k + 1]) (ia is sorted by the gate).
    order = np.argsort(ia, kind="stable")
    counts = np.bincount(ia, minlength=len(a))
    start = np.r_[0, np.cumsum(counts)]
    cnt = counts[k_track]
    if int(cnt.sum()) > params.max_comparisons:
        return empty  # a picture denser than any formation: bounded work, no offsets
    vote_ref = np.repeat(i_ref, cnt)
    offs = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    vote_c = order[np.repeat(start[k_track], cnt) + offs]
    if vote_c.size == 0:
        return empty
    # Bound the work: at most max_votes per reference (votes of nearer tracks are not
    # preferred; the cap only matters for pictures far denser than any formation).
    by_ref = np.argsort(vote_ref, kind="stable")
    vote_ref, vote_c = vote_ref[by_ref], vote_c[by_ref]
    first = np.r_[0, np.flatnonzero(np.diff(vote_ref)) + 1]
    rank = np.arange(vote_ref.size) - np.repeat(first, np.diff(np.r_[first, vote_ref.size]))
    cap = rank < params.max_votes
    vote_ref, vote_c = vote_ref[cap], vote_c[cap]
    m = len(a)
    scale = float(np.sqrt(np.median(var_h[np.unique(vote_c)])))  # the voters' median noise
    support = _support(a, ia, d, counts, start, order, params, scale)
    if support is None:
        return empty
    # Starts: each reference's ``starts`` best-supported voters.  A regular formation has a
    # mode at every lattice shift, nearly as supported as the true one; the matching from each
    # start decides, by the number of tracks it matches (the true offset matches the whole
    # group, a shift loses an edge), then by the total chi-square.
    k_st = max(1, params.starts)
    by = np.lexsort((-support[vote_c], vote_ref))
    first_v = np.r_[True, vote_ref[by][1:] != vote_ref[by][:-1]]
    grp = np.cumsum(first_v) - 1
    rank = np.arange(by.size) - np.flatnonzero(first_v)[grp]
    chosen = by[rank < k_st]
    ref_x = vote_ref[chosen] * k_st + rank[rank < k_st]  # expanded reference: (row, start)
    mx = m * k_st
    off_x: FloatArray = np.zeros((mx, 3))
    off_x[ref_x] = d[vote_c[chosen]]
    has_start = np.zeros(mx, dtype=bool)
    has_start[ref_x] = True
    # Every vote once per start of its reference.
    vr = np.repeat(vote_ref, k_st) * k_st + np.tile(np.arange(k_st), vote_ref.size)
    vc = np.repeat(vote_c, k_st)
    live = has_start[vr]
    vr, vc = vr[live], vc[live]
    inv_h = np.linalg.inv(s[:, :2, :2] + 1e-9 * np.eye(2))  # horizontal, per candidate
    track_of = ia[vc]
    w = np.zeros(vc.size)
    wsum = np.zeros(mx)
    qsum = np.zeros(mx)
    for _ in range(params.iterations):
        # Each nearby track's candidate nearest the current offset (horizontal Mahalanobis),
        # within the gate; the offset is their mean.  (A matching, not a kernel average: the
        # lattice-shifted pairings around the true offset then pull nothing.)
        dd = d[vc, :2] - off_x[vr, :2]
        q = np.einsum("ki,kij,kj->k", dd, inv_h[vc], dd)
        key = vr.astype(np.int64) * (m + 1) + track_of
        order_q = np.lexsort((q, key))
        first = np.r_[True, key[order_q][1:] != key[order_q][:-1]]
        pick = order_q[first]
        pick = pick[q[pick] <= params.gate_chi2]
        w = np.zeros(vc.size)
        w[pick] = 1.0
        wsum = np.bincount(vr, w, minlength=mx).astype(float)
        qsum = np.bincount(vr, w * q, minlength=mx).astype(float)
        new = np.stack([np.bincount(vr, w * d[vc, k], minlength=mx) for k in range(3)], 1)
        good = wsum > 0
        off_x[good] = new[good] / wsum[good, None]
    # The best start of each reference: most matches, then the least total chi-square.
    score = np.where(has_start, wsum * 1e6 - np.minimum(qsum, 1e6 - 1), -np.inf).reshape(m, k_st)
    best_k = np.argmax(score, axis=1)
    sel_x = np.arange(m) * k_st + best_k
    off = off_x[sel_x]
    keep_vote = best_k[vr // k_st] == vr % k_st
    vote_ref, vote_c, w = vr[keep_vote] // k_st, vc[keep_vote], w[keep_vote]
    wsum = wsum[sel_x]
    # Covariance of the offset: the matched candidates' noise over their number.
    n_support = wsum
    s_mean = np.zeros((m, 9))
    for k in range(9):
        s_mean[:, k] = np.bincount(vote_ref, w * s[vote_c].reshape(-1, 9)[:, k], minlength=m)
    s_mean = s_mean.reshape(m, 3, 3) / np.maximum(wsum, 1e-300)[:, None, None]
    cov_off = s_mean / np.maximum(n_support, 1.0)[:, None, None]
    ok = (n_other[ia] >= params.min_tracks) & (n_support[ia] >= params.min_tracks)
    return ok, (d - off[ia])[ok], s[ok], cov_off[ia][ok]


def _support(
    a: PredictedTracks,
    ia: IntArray,
    d: FloatArray,
    counts: NDArray[np.intp],
    start: NDArray[np.intp],
    order: NDArray[np.intp],
    params: GroupOffsetParams,
    scale: float,
) -> FloatArray | None:
    """Each candidate's support: the kernel-weighted number of candidates of the *other* A
    tracks within ``radius_m`` whose difference is nearly its own (None: over the bound)."""
    rows = np.unique(ia)
    tree = cKDTree(a.position[rows])
    near = tree.sparse_distance_matrix(tree, params.radius_m, output_type="ndarray")
    k1, k2 = rows[near["i"]], rows[near["j"]]
    keep = k1 != k2
    k1, k2 = k1[keep], k2[keep]
    size = counts[k1] * counts[k2]
    total = int(size.sum())
    if total > params.max_comparisons:
        return None
    blk = np.repeat(np.arange(k1.size), size)
    r = np.arange(total) - np.repeat(np.cumsum(size) - size, size)
    n2 = counts[k2][blk]
    c1 = order[start[k1][blk] + r // n2]
    c2 = order[start[k2][blk] + r % n2]
    dd = d[c1, :2] - d[c2, :2]
    w = np.exp(-0.5 * (dd * dd).sum(axis=1) / (params.support_bandwidth * scale) ** 2)
    return np.asarray(np.bincount(c1, w, minlength=len(ia)), dtype=float)
