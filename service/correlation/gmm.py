"""GMM anti-bias track association (correlator ``gmm``), pure numpy/scipy.

Li Baozhu, Dong Yunlong, Ding Hao, Guan Jian, "GMM-based anti-bias track association"
(``docs/references.md`` §3).

Radar A reports the track set ``X_A`` (``M`` tracks, the GMM *samples*), radar B the set
``X_B`` (``N`` tracks, the moving GMM *centroids*), both in one local plane.  Systematic
errors move and deform ``X_B`` against ``X_A`` (paper Eqs. (6)-(7): rigid for small range
bias, non-rigid for large), and not every target is seen by both radars.  The method:

1. neighbourhood similarity of A-track ``i`` and B-track ``j`` from their ``K`` nearest
   neighbours, by the OSPA distance (Schuhmacher, Vo, Vo 2008) between ``l``-element
   subsets of the two neighbourhoods (Eqs. (8)-(10));
2. a Gaussian mixture with the ``X_B`` as centroids plus a uniform outlier component of
   weight ``omega`` (Eqs. (11)-(13)); component priors from the similarities (Eq. (14));
3. a non-rigid displacement ``X_A ~ X_B + G W`` with Gaussian kernel ``G`` (width ``beta``)
   and regulariser ``lambda`` (Eqs. (16)-(20)), fitted by EM (Eqs. (21)-(25));
4. ``omega`` smoothed across iterations, ``omega = omega_old + (omega_new - omega_old) / k``
   (Eq. (26));
5. association matrix ``C(i, j) = 1`` where the posterior is the maximum of its row and of its
   column and above a threshold (Eq. (27)).

Equation numbers.  The extraction lost every displayed equation of this paper.  The numbers
used here are those the text cross-references ((4)-(7), (16), (18), (20), (25), (26)) and,
between them, the order of the displayed equations in the text; formulas marked
*reconstructed* follow the standard method the paper cites: OSPA (its ref. [21]) and Coherent
Point Drift, Myronenko & Song, PAMI 32(12) 2010 (its ref. [22]), whose E-step, M-step and
sigma^2 update the paper adopts with non-uniform component priors.

Design choices the text leaves open (each is a parameter of :class:`GmmParams`):

* the neighbourhood of a track is the set of vectors from it to its ``K`` nearest neighbours
  in its own radar (the paper describes neighbourhoods "by Euclidean distance"; the Euclidean
  norm is used as OSPA's base metric), so it is translation invariant, and the small
  relative rotation between the radars (``theta_0`` of Eq. (6), about 2 deg at most) moves a
  neighbour vector by far less than the OSPA cut-off;
* EM runs on coordinates centred on each set's mean and scaled by their common RMS spread,
  as Coherent Point Drift does (``beta = lambda = 2`` of the paper are CPD's defaults for
  normalised data); centring removes the bulk translation the biases cause;
* the uniform density of the outlier component is ``1/M`` (CPD's convention);
* ``omega`` is kept at or above ``1 - N/M`` (``omega_floor_from_counts``): with fewer centroids
  than samples that many samples cannot have a counterpart.  On the paper's dense starting box
  (20 targets in 3 x 3 km) the free update of Eq. (25) otherwise collapses ``omega`` to ~0.005
  while 25-35 % of A's tracks are unmatched; the floor raises the correct rate there from 0.64
  to 0.70 (30 scenes) and the false share of pairs from 0.30 to 0.24.  The rest is the density
  itself: with the true bias offset removed, an optimal one-to-one assignment reaches only 0.80
  at the first period; by period 10 (20 s, the box spreading) the method gets 0.90 and from
  period 25 on 0.97-1.0, about 0.93 averaged over the run, the paper's "about 0.9".
* the kernel is at least ``min_kernel_width_m`` wide in metres: the part of the biases that
  is not a rigid motion varies over the scale of the range (Eq. (6) against Eq. (7)), and a
  kernel of ``beta = 2`` spreads on a formation a few km across lets the field chase the
  random errors;
* given the tracks' covariances, ``sigma`` is kept at or above the relative error of two tracks
  of one target (``sigma_floor_factor``): in scenes as dense as the errors the update of
  Eq. (25) shrinks it to the nearest-centroid spread and the posteriors become over-confident.

For a stream (:class:`~service.correlation.external.GmmCorrelator`), :func:`candidate_pairs`
extends Eq. (27): the decisive pairs are handed on with their rivals, so that a one-to-one
assignment with an ambiguity margin refuses a close call instead of guessing, together with
every pair the fit does not rule out (what an accumulation over updates must see).  Where one
snapshot cannot separate aircraft spaced like the random errors, no choice of these
parameters can: ``docs/evaluation/gmm_dense.md`` measures how far one snapshot, and an
accumulation of them, get.

Everything is vectorised over tracks and track pairs; only the EM iterations loop.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

_TINY = float(np.finfo(float).tiny)
_EPS = float(np.finfo(float).eps)


@dataclass(frozen=True)
class GmmParams:
    """Parameters of :func:`gmm_associate`; every threshold of the method is one of these."""

    k_neighbours: int = 5
    """``K``: nearest neighbours (in the track's own radar) forming its neighbourhood set
    (Eq. (8)).  Clipped to ``min(M, N) - 1`` for small scenes.  Cost grows as ``K!``."""

    subset_size: int = 4
    """``l``: neighbours of each set that are paired in the OSPA subset distance (Eq. (9));
    ``K - l`` neighbours per set may lack a counterpart (not seen by the other radar).
    Clipped to the effective ``K``."""

    ospa_cutoff_m: float = 1500.0
    """OSPA cut-off ``c`` (m): a neighbour-vector mismatch counts at most ``c``.  Should exceed
    the same-target mismatch (random error of both radars plus the bias-induced rotation
    times the neighbour distance) and be below typical distances between unrelated tracks."""

    ospa_order: float = 2.0
    """OSPA order ``p`` (Eq. (9))."""

    prior_floor: float = 0.05
    """``epsilon`` added to every similarity before normalising to component priors (Eq. (14),
    reconstructed), so that a low neighbourhood similarity down-weights a component but never
    rules it out."""

    beta: float = 2.0
    """Gaussian kernel width ``beta`` of ``G`` (Eq. (19)), in normalised units (coordinates
    divided by the common RMS spread).  Paper: 2; good range 1.5-4 (its Fig. 9)."""

    min_kernel_width_m: float = 20_000.0
    """Lower bound (m) of the kernel width in metres, ``beta`` times the RMS spread the
    coordinates are normalised by: the kernel of Eq. (19) is ``max(beta, min_kernel_width_m /
    spread)`` wide in normalised units.  What the biases add to a rigid motion (Eq. (6) against
    Eq. (7)) is the range bias along each target's line of sight, whose direction turns by
    ``L / R`` over a distance ``L`` at range ``R``: under 100 m across 20 km for range biases up
    to 1 km at 200 km.  A kernel narrower than that in metres (``beta = 2`` on a formation a
    few km across) only lets the displacement field chase the random errors, pulling a B
    centroid onto an A track without a counterpart (dense formation at 3 cross-range sigmas
    spacing, decisive single-update pairs: 10 % of 241 false without the bound, 1 % of 128
    with it; ``docs/evaluation/gmm_dense.md``).
    On the paper's own scene it raises the correct rate at period 10 from 0.91 to 0.94 and
    halves the false share (0.115 to 0.061); 10-50 km give the same."""

    lam: float = 2.0
    """Regulariser weight ``lambda`` of the displacement field (Eq. (17)-(20)).  Paper: 2; good
    range 0.1-5 (its Fig. 9)."""

    omega0: float = 0.2
    """Initial weight ``omega`` of the uniform outlier component (Eq. (13))."""

    omega_min: float = 1e-3
    """Lower clip of ``omega``: keeps the uniform term positive, so posteriors stay finite."""

    omega_max: float = 0.95
    """Upper clip of ``omega``."""

    omega_floor_from_counts: bool = True
    """Keep ``omega >= 1 - N / M`` (at least ``M - N`` of the ``M`` samples have no counterpart
    among the ``N`` centroids).  Without it, in dense scenes (the paper's 20 targets in a
    3 x 3 km box at the start, nearest-neighbour spacing ~300 m against ~200 m relative track
    error) every unmatched A track lies close enough to some B centroid that the EM update of
    Eq. (25) drives ``omega`` to ~0, and unmatched tracks are forced onto centroids."""

    max_iter: int = 150
    """Maximum number of EM iterations (Eqs. (21)-(26))."""

    tol: float = 1e-6
    """Convergence: relative change of the negative log-likelihood of Eq. (20) between two
    iterations below ``tol``."""

    posterior_threshold: float = 0.5
    """Minimum posterior ``P(j | x_i)`` for ``C(i, j) = 1`` (Eq. (27))."""

    sigma_floor_factor: float = 1.0
    """Lower bound of the mixture variance from the tracks' own covariances, when the caller
    gives them (``cov_a``, ``cov_b`` of :func:`gmm_associate`): ``sigma^2 >= factor * (mean
    per-axis variance of A's tracks + that of B's)``, the spread the random errors alone give
    the two tracks of one target.  The sigma^2 update of Eq. (25) is the mean squared distance
    of each sample to the centroids it is given to; in a scene denser than the track errors
    those are its *nearest* centroids, not its true ones, so the update shrinks sigma below
    the real residual of a true pair (dense formation at 1.5 cross-range sigmas spacing, true
    pairs' residual 290 m per axis after the fit: sigma 160 m with ``beta = 2`` alone, 250 m
    with ``min_kernel_width_m``), and the posteriors of Eq. (21) become over-confident: of the
    pairs of Eq. (27) with posterior >= 0.9 there only 40 % are right.  0 disables the floor."""

    report_rivals: bool = True
    """What the stream adapter (:class:`~service.correlation.external.GmmCorrelator`) hands the
    one-to-one assignment.  True: every candidate of :func:`candidate_pairs` (the decisive
    pairs of Eq. (27) and their rivals), each with cost ``-2 ln P``, so the assignment's
    ambiguity margin (chi-square units) refuses a pair whose row or column holds a rival
    within that likelihood ratio.  False: only the pairs of Eq. (27) as the paper decides them
    (mutual maxima, always one-to-one: the margin never sees a rival)."""

    candidate_gate_chi2: float = 13.8
    """Squared distance to a fitted centroid over ``sigma^2`` up to which an A-B pair is a
    candidate of the stream adapter even when its posterior is small (2 dof, 13.8 = 0.1 %
    tail): a true pair stays in view of the caller on every update, whatever its rivals.  Such
    a candidate is accepted only as described in :func:`candidate_pairs`."""

    rival_posterior: float = 0.01
    """Smallest posterior ``P(j | x_i)`` of a candidate handed on as a rival
    (``report_rivals``).  A rival matters when its cost is within the margin ``m`` of the
    chosen pair's, i.e. when its posterior is at least ``exp(-m / 2)`` (1/20 for ``m = 6``)
    of a posterior above ``posterior_threshold``; 0.01 keeps every such rival for thresholds
    down to 0.2."""

    min_spread_m: float = 1e-3
    """A track set whose points all lie within this distance (m) of each other per axis is
    degenerate (identical points): no decision."""

    ospa_chunk_elements: int = 4_000_000
    """Memory bound of the vectorised OSPA matrix: elements per block of A-tracks."""


@dataclass
class GmmResult:
    """Outcome of :func:`gmm_associate`.  Empty pairs with a ``reason`` is a valid answer."""

    index_a: IntArray
    """Row of ``pos_a`` of each associated pair."""
    index_b: IntArray
    """Row of ``pos_b`` of each associated pair."""
    posterior: FloatArray
    """Posterior ``P(j | x_i)`` of each pair (Eq. (21))."""
    displacement: FloatArray
    """Fitted displacement of B in metres, shape of ``pos_b``: ``pos_b + displacement`` is where
    the mixture put each B centroid among the A tracks (``G W`` of Eq. (19) scaled back, plus
    the centring translation).  Zeros when no fit was made."""
    iterations: int
    """EM iterations run."""
    converged: bool
    """True when the likelihood change fell below ``tol`` (or sigma collapsed to zero)."""
    reason: str
    """Why the result looks as it does ("converged", "max_iter reached", or why no decision)."""
    outlier_weight: float = float("nan")
    """Final ``omega``: estimated share of A tracks with no counterpart in B (Eqs. (25)-(26))."""
    sigma_m: float = float("nan")
    """Final mixture standard deviation ``sigma`` in metres."""
    similarity: FloatArray = field(default_factory=lambda: np.empty((0, 0)))
    """Neighbourhood similarity matrix ``s_ij`` (M, N) of Eq. (10), for diagnostics."""
    posterior_matrix: FloatArray = field(default_factory=lambda: np.empty((0, 0)))
    """Final posteriors ``P(j | x_i)`` (M, N) of Eq. (21), row ``i`` = A-track; each row sums
    to one minus the posterior of the outlier component."""
    sigma_floor_m: float = 0.0
    """The lower bound ``sigma`` was held to (``sigma_floor_factor``; 0: none)."""

    def __bool__(self) -> bool:
        return bool(self.index_a.size)


def _empty(pos_b: FloatArray, reason: str) -> GmmResult:
    shape = pos_b.shape if pos_b.ndim == 2 else (0, 2)
    return GmmResult(
        index_a=np.empty(0, dtype=np.intp),
        index_b=np.empty(0, dtype=np.intp),
        posterior=np.empty(0),
        displacement=np.zeros(shape),
        iterations=0,
        converged=False,
        reason=reason,
    )


# -- neighbourhoods and OSPA -------------------------------------------------------------------


def neighbour_vectors(pos: FloatArray, k: int) -> FloatArray:
    """Vectors from each point to its ``k`` nearest other points, nearest first, ``(n, k, d)``.

    The neighbourhood set ``I_i`` of Eq. (8).  Exact duplicates of a point count as neighbours
    (at distance 0); the point itself never does.
    """
    n = pos.shape[0]
    _, idx = cKDTree(pos).query(pos, k=k + 1)
    idx = np.asarray(idx, dtype=np.intp).reshape(n, k + 1)
    is_self = idx == np.arange(n)[:, None]
    # Stable sort moves the self index (True) behind the others; rows where duplicates hid the
    # self index simply drop their farthest candidate.
    order = np.argsort(is_self, axis=1, kind="stable")[:, :k]
    neighbours = np.take_along_axis(idx, order, axis=1)
    out: FloatArray = pos[neighbours] - pos[:, None, :]
    return out


def ospa_subset_matrix(
    feat_a: FloatArray,
    feat_b: FloatArray,
    subset_size: int,
    cutoff: float,
    order: float = 2.0,
    chunk_elements: int = 4_000_000,
) -> FloatArray:
    """OSPA distance between best-matching ``l``-subsets of every pair of neighbourhoods.

    Eq. (9) (OSPA, Schuhmacher et al. 2008, reconstructed) applied to subsets of ``l`` elements
    of two ``K``-element sets ``U = feat_a[i]`` and ``V = feat_b[j]`` (Eq. (8)):

        D(i, j) = min over l-subsets S of U, T of V of
                  ( (1/l) min over bijections pi: S -> T of sum_{u in S} min(c, |u - pi(u)|)^p )^(1/p)

    Equal cardinalities, so OSPA's cardinality term vanishes.  The double minimum is the
    cheapest partial matching of exactly ``l`` pairs, which equals the minimum over all ``K!``
    full permutations of the sum of the ``l`` smallest matched costs (any partial matching
    extends to a permutation; the ``l`` cheapest pairs of a permutation are a partial matching),
    so it is computed by enumerating the permutations, vectorised over all ``(i, j)``.

    ``feat_a``: ``(M, K, d)``, ``feat_b``: ``(N, K, d)``; returns ``(M, N)`` in ``[0, c]``.
    """
    m, k, _ = feat_a.shape
    n = feat_b.shape[0]
    perms = np.array(list(itertools.permutations(range(k))), dtype=np.intp)  # (P, K)
    cols = np.arange(k)[None, :]
    out = np.empty((m, n))
    rows_per_chunk = max(1, int(chunk_elements // max(1, n * perms.shape[0] * k)))
    for start in range(0, m, rows_per_chunk):  # blocks of A-tracks bound the memory only
        fa = feat_a[start : start + rows_per_chunk]
        diff = fa[:, None, :, None, :] - feat_b[None, :, None, :, :]  # (m, N, K, K, d)
        cost = np.minimum(np.sqrt(np.einsum("...i,...i->...", diff, diff)), cutoff) ** order
        matched = cost[:, :, cols, perms]  # (m, N, P, K): cost of u_q matched to v_perm[q]
        if subset_size < k:
            matched = np.partition(matched, subset_size - 1, axis=-1)[..., :subset_size]
        out[start : start + rows_per_chunk] = matched.sum(axis=-1).min(axis=-1)
    return np.asarray((out / subset_size) ** (1.0 / order))


def neighbourhood_similarity(pos_a: FloatArray, pos_b: FloatArray, params: GmmParams) -> FloatArray:
    """Similarity ``s_ij`` in ``[0, 1]`` of the neighbourhoods of A-track i and B-track j.

    Eq. (10) (reconstructed): ``s_ij = 1 - D(i, j) / c`` with ``D`` the OSPA subset distance of
    Eq. (9) and ``c`` its cut-off, so identical neighbourhoods give 1 and neighbourhoods with
    nothing in common give 0.  Returns ones (no information) when a set has under 2 tracks.
    """
    m, n = pos_a.shape[0], pos_b.shape[0]
    k = min(params.k_neighbours, m - 1, n - 1)
    if k < 1:
        return np.ones((m, n))
    subset = max(1, min(params.subset_size, k))
    dist = ospa_subset_matrix(
        neighbour_vectors(pos_a, k),
        neighbour_vectors(pos_b, k),
        subset,
        params.ospa_cutoff_m,
        params.ospa_order,
        params.ospa_chunk_elements,
    )
    return np.asarray(1.0 - dist / params.ospa_cutoff_m)


# -- EM / coherent point drift -----------------------------------------------------------------


def _sq_dist(x: FloatArray, t: FloatArray) -> FloatArray:
    """``||x_i - t_j||^2`` as an ``(N, M)`` matrix (row = centroid j, column = sample i)."""
    d = t[:, None, :] - x[None, :, :]
    return np.asarray(np.einsum("...i,...i->...", d, d))


def _e_step(
    x: FloatArray, t: FloatArray, prior: FloatArray, sigma2: float, omega: float
) -> tuple[FloatArray, float]:
    """Posteriors ``P[j, i] = P(centroid j | sample x_i)`` and the negative log-likelihood.

    Eq. (21) (reconstructed, CPD Eq. (7) with priors ``pi_ji`` in place of ``1/N``):

        P_ji = pi_ji exp(-|x_i - t_j|^2 / 2 sigma^2)
               / ( sum_k pi_ki exp(-|x_i - t_k|^2 / 2 sigma^2) + (2 pi sigma^2)^(D/2) w/(1-w) / M )

    from the mixture of Eq. (13): ``p(x) = w / M + (1 - w) sum_j pi_ji N(x; t_j, sigma^2 I)``
    (uniform density ``1/M`` as in CPD).
    """
    m, dim = x.shape
    num = prior * np.exp(-_sq_dist(x, t) / (2.0 * sigma2))  # (N, M)
    c = (2.0 * np.pi * sigma2) ** (dim / 2.0) * omega / ((1.0 - omega) * m)
    den = num.sum(axis=0) + c
    # -log p(x_i) = -log((1 - w) (2 pi sigma^2)^(-D/2) den_i)
    nll = -float(np.sum(np.log(den))) - m * (np.log1p(-omega) - dim / 2.0 * np.log(2.0 * np.pi * sigma2))
    return num / den, nll


def _omega_floor(m: int, n: int, p: GmmParams) -> float:
    """Lower bound of ``omega``: with ``M`` samples and ``N < M`` centroids at least ``M - N``
    samples have no counterpart, so the outlier share is at least ``1 - N / M``
    (``omega_floor_from_counts``); never below ``omega_min``."""
    if p.omega_floor_from_counts and m > n:
        return float(min(max(p.omega_min, 1.0 - n / m), p.omega_max))
    return p.omega_min


def sigma_floor_m(cov_a: np.ndarray | None, cov_b: np.ndarray | None, params: GmmParams) -> float:
    """The lower bound of the mixture's ``sigma`` (m) from the tracks' position covariances.

    ``cov_a`` (M, d, d), ``cov_b`` (N, d, d) in the plane of the positions.  The relative
    position of two tracks of one target has covariance ``P_a + P_b``; its mean variance per
    axis over the tracks, ``(mean tr P_a + mean tr P_b) / d``, times ``sigma_floor_factor``, is
    the variance the isotropic mixture of Eq. (13) may not go below.  0 when either is missing
    or not finite (no floor).
    """
    if cov_a is None or cov_b is None or params.sigma_floor_factor <= 0.0:
        return 0.0
    ca, cb = np.asarray(cov_a, dtype=float), np.asarray(cov_b, dtype=float)
    if ca.ndim != 3 or cb.ndim != 3 or ca.shape[0] == 0 or cb.shape[0] == 0:
        return 0.0
    dim = ca.shape[-1]
    var = (np.trace(ca, axis1=1, axis2=2).mean() + np.trace(cb, axis1=1, axis2=2).mean()) / dim
    if not np.isfinite(var) or var <= 0.0:
        return 0.0
    return float(np.sqrt(params.sigma_floor_factor * var))


def candidate_pairs(
    post: FloatArray, chi2: FloatArray, threshold: float, rival_floor: float, gate_chi2: float
) -> tuple[IntArray, IntArray, BoolArray]:
    """The candidates ``(i, j)`` handed to a one-to-one assignment, and which of them it may take.

    ``post`` (M, N): posteriors ``P(j | x_i)`` of Eq. (21); ``chi2`` (M, N): squared distance
    of A-track ``i`` to the fitted B centroid ``j`` over ``sigma^2``.

    * Candidates: every ``(i, j)`` with ``P(j | x_i) > threshold`` (decisive, Eq. (27)), or
      ``P(j | x_i) >= rival_floor``, or ``chi2 <= gate_chi2`` (a pair the fit does not rule
      out, whatever its rivals: what an accumulation over updates needs to see).
    * Accepted: the candidates in the row or the column of a decisive one -- the decisive
      ones and their *rivals*.  Given costs ``-2 ln P``, an assignment with an ambiguity
      margin then keeps a pair only when it beats every rival of its row and of its column by
      that margin.  A rival itself is never kept (a decisive candidate of its row or column
      costs less), nor is a candidate whose row and column hold no decisive one (the threshold
      of Eq. (27)).

    Row-major order.  Returns ``(index_a, index_b, accepted)``.
    """
    p = np.asarray(post, dtype=float)
    if p.size == 0:
        e = np.empty(0, dtype=np.intp)
        return e, e.copy(), np.empty(0, dtype=bool)
    strong = p > threshold
    row, col = np.asarray(strong.any(axis=1)), np.asarray(strong.any(axis=0))
    near: BoolArray = row[:, None] | col[None, :]
    ia, ib = np.nonzero(strong | (p >= rival_floor) | (np.asarray(chi2) <= gate_chi2))
    return ia.astype(np.intp), ib.astype(np.intp), near[ia, ib]


def gmm_associate(
    pos_a: np.ndarray,
    pos_b: np.ndarray,
    params: GmmParams | None = None,
    cov_a: np.ndarray | None = None,
    cov_b: np.ndarray | None = None,
) -> GmmResult:
    """Associate radar A's tracks ``pos_a`` (M, d) with radar B's ``pos_b`` (N, d), d = 2 or 3.

    Both sets in metres in one local plane (or tangent frame) at one common time, each with its
    own radar's systematic errors.  ``cov_a`` (M, d, d) and ``cov_b`` (N, d, d): the tracks'
    position covariances in the same plane, optional; given, they bound the mixture's sigma
    from below (:func:`sigma_floor_m`).  Degenerate inputs (fewer than 2 tracks on a side,
    non-finite values, mismatched or unsupported dimensions, identical points) return an empty
    result whose ``reason`` says why; this function does not raise on data.
    """
    p = params if params is not None else GmmParams()
    a = np.asarray(pos_a, dtype=float)
    b = np.asarray(pos_b, dtype=float)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1] or a.shape[1] not in (2, 3):
        return _empty(b, f"positions must be (M, d) and (N, d) with d in (2, 3); got {a.shape}, {b.shape}")
    m, n = a.shape[0], b.shape[0]
    if m < 2 or n < 2:
        return _empty(b, f"too few tracks to associate (A: {m}, B: {n}; need 2 each)")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        return _empty(b, "non-finite track positions")
    if np.ptp(a, axis=0).max() <= p.min_spread_m or np.ptp(b, axis=0).max() <= p.min_spread_m:
        return _empty(b, "degenerate track set: all positions identical")

    # (a) neighbourhood similarity, Eqs. (8)-(10); priors, Eq. (14) (reconstructed):
    #     pi_ji = (s_ij + eps) / sum_k (s_ik + eps), one distribution over centroids per sample.
    sim = neighbourhood_similarity(a, b, p)
    weight = sim.T + p.prior_floor  # (N, M)
    prior = weight / weight.sum(axis=0, keepdims=True)

    # Normalise as CPD does: centre each set, one common scale (keeps the geometry's scale).
    mean_a, mean_b = a.mean(axis=0), b.mean(axis=0)
    xa, yb = a - mean_a, b - mean_b
    scale = float(np.sqrt((np.sum(xa**2) + np.sum(yb**2)) / (m + n)))
    x, y = xa / scale, yb / scale
    dim = x.shape[1]

    # Gaussian kernel G_jk = exp(-|y_j - y_k|^2 / 2 beta^2), Eq. (19).
    beta = max(p.beta, p.min_kernel_width_m / scale)
    g = np.exp(-_sq_dist(y, y) / (2.0 * beta**2))
    w = np.zeros_like(y)
    sigma2 = float(np.sum(_sq_dist(x, y))) / (dim * m * n)  # CPD's initial sigma^2
    floor_m = sigma_floor_m(cov_a, cov_b, p)
    sigma2_lo = (floor_m / scale) ** 2
    sigma2 = max(sigma2, sigma2_lo)
    omega_lo = _omega_floor(m, n, p)
    omega = float(np.clip(p.omega0, omega_lo, p.omega_max))
    sigma2_floor = 10.0 * _EPS

    nll_old = np.inf
    converged = False
    reason = "max_iter reached"
    iterations = 0
    for k in range(1, p.max_iter + 1):
        iterations = k
        t = y + g @ w
        post, nll = _e_step(x, t, prior, sigma2, omega)  # E-step, Eq. (21)
        nll += 0.5 * p.lam * float(np.sum(w * (g @ w)))  # regulariser of Eq. (20)
        if abs(nll_old - nll) <= p.tol * max(abs(nll), 1.0):
            converged, reason = True, "converged"
            break
        nll_old = nll
        # M-step, Eqs. (22)-(24) (reconstructed, CPD Fig. 4):
        #   (diag(P1) G + lambda sigma^2 I) W = P X - diag(P1) Y
        # (the digest's (G + lambda sigma^2 diag(P1)^-1) W = diag(P1)^-1 P X - Y multiplied by
        # diag(P1), which stays well posed when a centroid has no posterior mass).
        p1 = post.sum(axis=1)
        pt1 = post.sum(axis=0)
        n_p = float(p1.sum())
        px = post @ x
        w = np.linalg.solve(p1[:, None] * g + p.lam * sigma2 * np.eye(n), px - p1[:, None] * y)
        t = y + g @ w
        # sigma^2 update, Eq. (25): (tr(X' d(Pt1) X) - 2 tr((PX)' T) + tr(T' d(P1) T)) / (Np D)
        if n_p <= _TINY:
            reason = "no sample is explained by any centroid (all outliers)"
            break
        sigma2 = float(
            np.sum(pt1 * np.sum(x**2, axis=1)) - 2.0 * np.sum(px * t) + np.sum(p1 * np.sum(t**2, axis=1))
        ) / (n_p * dim)
        # omega update, Eq. (25): omega_new = 1 - Np / M, smoothed by Eq. (26), alpha = 1/k.
        omega_new = 1.0 - n_p / m
        omega = float(np.clip(omega + (omega_new - omega) / k, omega_lo, p.omega_max))
        sigma2 = max(sigma2, sigma2_lo)  # no tighter than the tracks' errors (sigma_floor_factor)
        if sigma2 <= sigma2_floor:
            sigma2 = sigma2_floor
            converged, reason = True, "converged (sigma collapsed: exact fit)"
            break

    t = y + g @ w
    post, _ = _e_step(x, t, prior, sigma2, omega)
    # Decision, Eq. (27): C(i, j) = 1 iff P_ji is the maximum of row i and of column j and
    # exceeds the threshold.
    pm = post.T  # (M, N), [i, j]
    best_b = np.argmax(pm, axis=1)
    best_a = np.argmax(pm, axis=0)
    ia = np.flatnonzero(best_a[best_b] == np.arange(m))
    ib = best_b[ia]
    keep = pm[ia, ib] > p.posterior_threshold
    ia, ib = ia[keep], ib[keep]

    displacement = (t - y) * scale + (mean_a - mean_b)
    return GmmResult(
        index_a=ia.astype(np.intp),
        index_b=ib.astype(np.intp),
        posterior=pm[ia, ib],
        displacement=displacement,
        iterations=iterations,
        converged=converged,
        reason=reason if ia.size else f"{reason}; no posterior above {p.posterior_threshold}",
        outlier_weight=omega,
        sigma_m=float(np.sqrt(sigma2)) * scale,
        similarity=sim,
        posterior_matrix=pm,
        sigma_floor_m=floor_m,
    )
