"""CA-CFAR confidential association of a bias-free reference (AIS) with a radar (correlator ``cfar``).

Qi Lin, Cui Yaqi, Xiong Wei, Wang Cong, "Anti-bias association algorithm for AIS and radar
based on bias detection", JEIT 37(8), 2015 (``docs/references.md`` §4).

Reference tracks (AIS: true positions) and the radar's tracks, both at common times, are put in
the radar's local plane (Section 2.1-2.2).  Systematic errors shift every radar track by a
similar amount that is, at sea, smaller than the distances between ships, so the smallest
entries of the reference-radar distance matrix are same-source distances and are followed by a
jump to different-source distances.  Steps:

1. distance matrix (Section 2.2); all entries sorted ascending, successive differences
   (Section 2.4);
2. a cell-averaging CFAR detector with a leading reference window, guard cells and a
   weighting coefficient slides along the differences; the first detection is the jump
   (Section 2.4, Fig. 1) and gives the same-source and different-source thresholds.  *Addition
   to the paper*: a detection the pairs' own covariances or the number of isolated pairs make
   implausible is passed over for the next one (:func:`ca_cfar_thresholds`: a chance gap among
   the first few same-source distances, common when the azimuth bias spreads them as
   ``r * dtheta`` over a long range interval);
3. *confidential pairs* (Section 2.3): mutually nearest, closer than the same-source
   threshold, and the second-nearest track of each farther than the different-source
   threshold;
4. least-squares range and azimuth bias from the confidential pairs, bias model of Eqs.
   (17)-(18): ``r_meas = r_true + dr``, ``theta_meas = theta_true + dtheta``.  *Addition*: a
   confidential pair whose residual is inconsistent with the bias of the others (leave-one-out
   chi-square with the pair's covariance, :func:`consistent_pairs`) is dropped; pairs the caller
   vouches for (the stream's re-verified confirmed pairs) join the confidential ones;
5. after compensation, a second association (2-D assignment with a chi-square gate, the
   paper's conclusion (3)) pairs the remaining tracks; the bias is then re-estimated from all
   final pairs (``CfarParams.refine_bias``; an addition to the paper).  The gate of each
   candidate is its own covariance ``S = C_ref + C_radar + C_bias`` in ``[range, azimuth]``
   (the bias model is additive there), so it grows with range as the radar's cross-range error
   does and never depends on the CA-CFAR thresholds; an assigned pair with a rival candidate
   within ``ambiguity_margin`` is left undecided (two targets closer than their errors).

Covariances.  :func:`cfar_associate` takes each track's ``[range_m, azimuth_deg]`` covariance
(the stream's predicted covariances, :func:`polar_covariance`); without them a radar track
gets ``diag(range_sigma_m^2, azimuth_sigma_deg^2)`` and a reference track none.  They are a
floor: when the residuals of the consistent confidential pairs are larger than the covariances
say, the covariances are scaled up (``inflate_to_residuals``), never down.

Equation numbers.  The extraction lost the displayed equations of Sections 2.1-2.4 and their
numbers are not recoverable from the text; only Eqs. (17)-(18) (true position and the radar's
range/azimuth bias decomposition, Section 3.2.2) are cross-referenced.  Formulas of steps 1-3
and 5 are marked *reconstructed*: they follow the digest's standard-method form (the CA-CFAR
of the paper's ref. [14], He You et al., "Radar target detection and CFAR processing").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.special import erf

from service.chi2 import chi2_quantile

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

_TINY = float(np.finfo(float).tiny)
#: Median of the chi-square distribution with 2 degrees of freedom (``2 ln 2``).
_CHI2_2_MEDIAN = 2.0 * math.log(2.0)
#: Entries of one batch of :func:`jump_log_bound` (detections x sorted distances).
_BOUND_BATCH = 1 << 20
#: The plausibility bound uses the pair sigmas of the first ``factor * min(M, N) + min`` sorted
#: distances (a bound over fewer entries is looser, never wrong).
_SIGMA_PREFIX_FACTOR = 4
_SIGMA_PREFIX_MIN = 64


@dataclass(frozen=True)
class CfarParams:
    """Parameters of :func:`cfar_associate`; every threshold of the method is one of these."""

    reference_cells: int = 6
    """Length ``n`` of the leading reference window of the CA-CFAR detector (Fig. 1): the mean
    of the ``n`` differences before the guard cells estimates the local "noise" level."""

    guard_cells: int = 2
    """Guard cells between the test cell and the leading reference window (Fig. 1: two guard
    cells adjacent to the test statistic)."""

    coefficient: float = 5.0
    """Weighting coefficient ``T`` (Fig. 1): the test cell is a detection when its difference
    exceeds ``T`` times the reference-window mean.  With ``n`` exponential-like reference cells
    the per-cell false-alarm probability is ``(1 + T/n)^-n`` (about 2.6 % for 5 and 6).  Over
    the first few dozen same-source distances an early false alarm is therefore common (a
    chance gap; the azimuth bias spreads the same-source distances as ``r * dtheta``).  As the
    paper has it, such a detection gives a small same-source threshold and few confidential
    pairs, a poorer bias estimate, and (with a distance gate of the different-source threshold
    and sigmas estimated from those few, closest pairs) a second stage whose gates shrink with
    it, so that right pairs fail.  Here a detection that the pairs' covariances or the number
    of isolated pairs make implausible is passed over (``jump_probability``,
    ``min_jump_share``), and the second stage gates each candidate by its own covariance,
    whatever the thresholds.  A too-high ``T`` misses the jump when the azimuth bias spreads
    the same-source distances.  5-6 worked best in simulation (30-50 vessels, biases 500 m /
    0.5 deg and 1500 m / 1 deg)."""

    min_reference_cells: int = 3
    """At the start of the sorted list fewer than ``reference_cells`` differences precede the
    test cell; the window is shortened down to this many cells (fewer: cell not tested).  Lets
    scenes with only a few common tracks still find their jump."""

    different_source_factor: float = 2.0
    """Different-source threshold = this factor times the same-source threshold, but at least
    the first distance after the jump (Section 3.1 takes a factor whose value the extraction
    lost; *reconstructed*).  Also the factor of an *isolated* mutual pair (``min_jump_share``)."""

    jump_probability: float = 1e-3
    """Plausibility of a detection (addition to the paper).  A detection at ``k`` claims that
    the ``k + 1`` smallest distances are same-source distances, each at most ``s[k]``.  A
    same-source distance is the length of ``bias + e`` with ``e ~ N(0, S)``, ``S`` the pair's
    covariance in the plane; by Anderson's inequality no bias makes it more likely to be
    short than none, and ``|e| <= x`` needs both principal components within ``x``, so
    ``P(|bias + e| <= x) <= erf(x / (sqrt2 s1)) erf(x / (sqrt2 s2))`` (``s1, s2``: the principal
    standard deviations of ``S``).  The product of these bounds over the ``k + 1`` entries
    bounds the claim's probability (:func:`jump_log_bound`); a detection whose bound is below
    this value has a same-source threshold smaller than the pairs' own random errors allow and
    is passed over.  For the true jump the bound is at least the probability that independent
    same-source distances all fall below their maximum, so it falsely passes over the true jump
    in at most about this share of updates."""

    min_jump_share: float = 0.25
    """Plausibility of a detection, by count (addition to the paper).  Under the paper's premise
    (Section 2: the bias shift is smaller than the distances between targets) a same-source pair
    is mutually nearest and *isolated*: its distance times ``different_source_factor`` is below
    the second-nearest distance of both its tracks.  Their number (:func:`isolated_mutual_pairs`)
    estimates the common targets (a few unrelated pairs add to it; in dense traffic fewer true
    pairs are isolated, which only relaxes the test).  A detection among fewer than this share of
    that number of distances is passed over."""

    gate_probability: float = 0.999
    """Second stage and consistency of the confidential pairs: chi-square gate (2 degrees of
    freedom) on the bias-compensated residual ``[dr, dtheta]`` with its own covariance
    ``S = C_ref + C_radar + C_bias`` (the bias estimate's covariance; with the inflation of
    ``inflate_to_residuals``)."""

    ambiguity_margin: float = 6.0
    """Second stage (addition to the paper): an assigned pair is decided only when every other
    gated candidate of its reference track and of its radar track has a chi-square at least this
    much larger (6: a likelihood ratio of about 20, as ``CorrelationParams.ambiguity_margin``);
    else both tracks stay undecided this update rather than guessed (two targets closer than
    their errors).  0: the paper's plain 2-D assignment."""

    keep_probability: float = 0.999
    """Re-check of the stream's confirmed pairs (:func:`consistent_pairs`, used by
    ``CfarCorrelator.reverify``): a confirmed pair is kept when its residual passes a chi-square
    gate (2 dof) at this probability against the bias of the other confirmed pairs."""

    range_sigma_m: float = 100.0
    """Random range error (m) of a radar track against its reference, for calls without
    covariances (the radar track's covariance is then ``diag(range_sigma_m^2,
    azimuth_sigma_deg^2)``, the reference's zero)."""

    azimuth_sigma_deg: float = 0.3
    """Random azimuth error (deg) of a radar track, as ``range_sigma_m``."""

    inflate_to_residuals: bool = True
    """Scale every covariance by ``max(1, median(q) / median(chi2_2))``, ``q`` the leave-one-out
    chi-square of the consistent confidential (or re-checked) pairs, when there are at least
    ``min_pairs_for_inflation`` of them: the gates widen when the tracks' errors exceed their
    stated covariances and never shrink below them (the median: robust to a few wrong pairs)."""

    min_pairs_for_inflation: int = 5
    """Consistent pairs needed to compare their residuals with their covariances."""

    min_confident_pairs: int = 1
    """Confidential pairs (with the caller's known pairs) needed to estimate the bias; fewer:
    no decision."""

    min_kept_pairs: int = 5
    """Confirmed pairs needed for the re-check (``CfarCorrelator.reverify``): each is tested
    against the bias of the others; fewer: no re-check, every pair is decided afresh."""

    refine_bias: bool = True
    """Re-estimate the bias (same least squares) from all final pairs after the second stage.
    Confidential pairs are selected by distance, which favours pairs whose random error opposes
    the bias and so biases the first estimate toward zero (about -0.02 deg of 0.5 deg in
    simulation); the final pairs are not selected that way.  False: report the paper's
    first-stage estimate."""


@dataclass
class CfarResult:
    """Outcome of :func:`cfar_associate`.  Empty pairs with a ``reason`` is a valid answer."""

    index_ref: IntArray
    """Row of ``ref_polar`` of each final pair (sorted); the caller's known pairs not included."""
    index_radar: IntArray
    """Row of ``radar_polar`` of each final pair."""
    confident: NDArray[np.bool_]
    """True for pairs from the first (confidential) stage, False for second-stage pairs."""
    same_source_threshold_m: float
    """Same-source distance threshold from the CA-CFAR jump (NaN when none was found)."""
    different_source_threshold_m: float
    """Different-source distance threshold (NaN when none was found)."""
    range_bias_m: float
    """Least-squares range bias ``dr`` of the radar (``r_meas = r_true + dr``); NaN if none."""
    azimuth_bias_deg: float
    """Least-squares azimuth bias ``dtheta`` (``theta_meas = theta_true + dtheta``); NaN if none."""
    reason: str
    """What happened ("associated", or why there is no decision)."""
    inflation: float = 1.0
    """Factor the covariances were scaled by (``CfarParams.inflate_to_residuals``; >= 1)."""

    def __bool__(self) -> bool:
        return bool(self.index_ref.size)


@dataclass(frozen=True)
class CfarThresholds:
    """The CA-CFAR detection on the sorted distances (:func:`ca_cfar_thresholds`)."""

    detected: bool
    """True when a (plausible) jump was found."""
    jump_index: int
    """Index ``k`` into the differences ``s[k+1] - s[k]`` of the detection used (-1: none)."""
    same_source_m: float
    """``s[k]``: the largest same-source distance (NaN: none)."""
    different_source_m: float
    """``max(factor * s[k], s[k+1])`` (NaN: none)."""
    passed_over: int = 0
    """Detections before it found implausible (``jump_probability``, ``min_jump_share``)."""


@dataclass(frozen=True)
class CfarBias:
    """Least-squares radar bias from paired tracks (:func:`bias_least_squares`)."""

    range_bias_m: float
    azimuth_bias_deg: float
    range_residual_std_m: float
    """Sample standard deviation of the range residuals after removing the bias (NaN if n < 2)."""
    azimuth_residual_std_deg: float
    """Same for azimuth (deg)."""
    n_pairs: int


@dataclass(frozen=True)
class PairConsistency:
    """Bias of a set of pairs and each pair's consistency with it (:func:`consistent_pairs`)."""

    bias: FloatArray
    """``[dr_m, dtheta_deg]``: least-squares bias (Eqs. 17-18) of the consistent pairs (NaN: none)."""
    bias_cov: FloatArray
    """``(2, 2)`` covariance of ``bias`` (inflated; NaN: none)."""
    chi2: FloatArray
    """Each pair's leave-one-out chi-square (2 dof, inflated covariance)."""
    passed: BoolArray
    """Pairs within the gate."""
    inflation: float
    """Factor the covariances were scaled by (>= 1)."""


def _empty(
    reason: str, thr: CfarThresholds | None = None, bias: CfarBias | None = None, inflation: float = 1.0
) -> CfarResult:
    nan = float("nan")
    return CfarResult(
        index_ref=np.empty(0, dtype=np.intp),
        index_radar=np.empty(0, dtype=np.intp),
        confident=np.empty(0, dtype=bool),
        same_source_threshold_m=thr.same_source_m if thr else nan,
        different_source_threshold_m=thr.different_source_m if thr else nan,
        range_bias_m=bias.range_bias_m if bias else nan,
        azimuth_bias_deg=bias.azimuth_bias_deg if bias else nan,
        reason=reason,
        inflation=inflation,
    )


def wrap_deg(angle_deg: np.ndarray) -> FloatArray:
    """Wrap angles (deg) into ``[-180, 180)``."""
    return np.asarray(np.mod(np.asarray(angle_deg, dtype=float) + 180.0, 360.0) - 180.0)


def polar_to_plane(polar: np.ndarray) -> FloatArray:
    """``[range_m, azimuth_deg]`` rows to (east, north) metres in the radar's local plane.

    Azimuth clockwise from north (docs/references.md §1 correction, as ``service.geo``).
    """
    p = np.asarray(polar, dtype=float)
    az = np.radians(p[:, 1])
    return np.stack([p[:, 0] * np.sin(az), p[:, 0] * np.cos(az)], axis=1)


def polar_covariance(enu: np.ndarray, cov_enu: np.ndarray) -> FloatArray:
    """Covariance ``(N, 2, 2)`` of ``[range_m, azimuth_deg]`` from local ENU positions ``(N, 3)``
    and their covariances ``(N, 3, 3)``, to first order ``J P J^T``.

    ``range = |enu|`` (slant, as :func:`service.geo.enu_to_polar`) and ``azimuth = atan2(e, n)``
    clockwise from north: ``d range / d enu = enu / r``, ``d azimuth / d enu = (n, -e, 0) /
    (e^2 + n^2)`` (rad; times ``180 / pi`` for deg).  A position within 1 m of the site's vertical
    gets the derivatives at 1 m.
    """
    x = np.asarray(enu, dtype=float).reshape(-1, 3)
    c = np.asarray(cov_enu, dtype=float).reshape(-1, 3, 3)
    e, n = x[:, 0], x[:, 1]
    r = np.maximum(np.sqrt(np.einsum("ij,ij->i", x, x)), 1.0)
    h2 = np.maximum(e * e + n * n, 1.0)
    jac = np.zeros((x.shape[0], 2, 3))
    jac[:, 0, :] = x / r[:, None]
    jac[:, 1, 0] = np.degrees(n / h2)
    jac[:, 1, 1] = np.degrees(-e / h2)
    return np.asarray(np.einsum("nij,njk,nlk->nil", jac, c, jac))


def distance_matrix(ref_polar: np.ndarray, radar_polar: np.ndarray) -> FloatArray:
    """Euclidean distances (m) in the radar's plane between every reference and radar track,
    ``(M, N)`` (Section 2.2)."""
    d = polar_to_plane(ref_polar)[:, None, :] - polar_to_plane(radar_polar)[None, :, :]
    return np.asarray(np.sqrt(np.einsum("...i,...i->...", d, d)))


def cfar_statistics(diffs: np.ndarray, params: CfarParams) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Leading-window CA-CFAR over the sorted-distance differences (Fig. 1, reconstructed).

    For test cell ``k`` the reference window is the ``n`` differences ending ``g`` cells before
    it, ``diffs[k-g-n : k-g]`` (shortened at the start down to ``min_reference_cells``).
    Returns the window means ``mu_k`` (NaN where the cell is not tested) and the detections
    ``diffs[k] > T mu_k``.  Vectorised with a cumulative sum.
    """
    x = np.asarray(diffs, dtype=float)
    n_cells = x.size
    k = np.arange(n_cells)
    stop = k - params.guard_cells  # exclusive end of the window
    start = np.maximum(stop - params.reference_cells, 0)
    count = stop - start
    tested = count >= max(1, params.min_reference_cells)
    csum = np.concatenate([[0.0], np.cumsum(x)])
    mu = np.full(n_cells, np.nan)
    mu[tested] = (csum[stop[tested]] - csum[start[tested]]) / count[tested]
    # A window of exact zeros (coincident distances) still detects any positive jump.
    detect = np.zeros(n_cells, dtype=bool)
    detect[tested] = x[tested] > params.coefficient * np.maximum(mu[tested], _TINY)
    return mu, detect


def jump_log_bound(
    sorted_distances: np.ndarray, sigma_minor: np.ndarray, sigma_major: np.ndarray, jumps: np.ndarray
) -> FloatArray:
    """For each candidate jump ``k`` in ``jumps``: the log of the bound of ``jump_probability``,
    ``sum_{q <= k} ln(erf(s[k] / (sqrt2 s1_q)) erf(s[k] / (sqrt2 s2_q)))``.

    ``sigma_minor``/``sigma_major``: principal standard deviations (m) of the covariance of the
    pair behind each sorted distance (a zero one is no constraint: its factor is 1); they may
    cover only the first entries: the product over fewer factors (each at most 1) is still an
    upper bound.  Vectorised over detections and entries, in batches of at most
    ``_BOUND_BATCH`` entries.
    """
    s = np.asarray(sorted_distances, dtype=float)
    ks = np.asarray(jumps, dtype=np.intp)
    out = np.zeros(ks.size)
    if ks.size == 0:
        return out
    root2 = math.sqrt(2.0)
    s1 = np.asarray(sigma_minor, dtype=float) * root2
    s2 = np.asarray(sigma_major, dtype=float) * root2
    start = 0
    while start < ks.size:
        width = min(int(ks[start:].max()) + 1, s1.size)
        stop = min(ks.size, start + max(1, _BOUND_BATCH // max(width, 1)))
        kb = ks[start:stop]
        width = min(int(kb.max()) + 1, s1.size)
        x = s[kb][:, None]
        f1 = np.where(s1[:width] > 0, erf(x / np.where(s1[:width] > 0, s1[:width], 1.0)), 1.0)
        f2 = np.where(s2[:width] > 0, erf(x / np.where(s2[:width] > 0, s2[:width], 1.0)), 1.0)
        with np.errstate(divide="ignore"):
            terms = np.log(f1 * f2)
        terms = np.where(np.arange(width)[None, :] <= kb[:, None], terms, 0.0)
        out[start:stop] = terms.sum(axis=1)
        start = stop
    return out


def ca_cfar_thresholds(
    sorted_distances: np.ndarray,
    params: CfarParams | None = None,
    sigma_minor: np.ndarray | None = None,
    sigma_major: np.ndarray | None = None,
    expected_pairs: float = 0.0,
) -> CfarThresholds:
    """Same- and different-source thresholds from ascending distances (Section 2.4).

    Differences ``delta_k = s[k+1] - s[k]``; a CA-CFAR detection ``k`` marks the jump from
    same-source to different-source distances: same-source threshold ``s[k]``, different-source
    threshold ``max(factor * s[k], s[k+1])`` (reconstructed).  The paper takes the first
    detection.  Additions: a detection among fewer than ``min_jump_share * expected_pairs``
    distances, or (with the sorted entries' principal sigmas ``sigma_minor``/``sigma_major``)
    one whose :func:`jump_log_bound` is below ``ln(jump_probability)``, is passed over for the
    next one.
    """
    p = params if params is not None else CfarParams()
    s = np.asarray(sorted_distances, dtype=float).ravel()
    nan = float("nan")
    if s.size < 2:
        return CfarThresholds(False, -1, nan, nan)
    _, detect = cfar_statistics(np.diff(s), p)
    hits = np.flatnonzero(detect)
    if hits.size == 0:
        return CfarThresholds(False, -1, nan, nan)
    cand = np.flatnonzero(hits + 1 >= p.min_jump_share * expected_pairs)
    first = int(cand[0]) if cand.size else -1
    if sigma_minor is not None and sigma_major is not None:
        # The bound of each remaining detection in order, a few at a time (each costs its index):
        # stop at the first plausible one.
        first, done, size = -1, 0, 8
        log_p = math.log(p.jump_probability)
        while first < 0 and done < cand.size:
            batch = cand[done : done + size]
            good = np.flatnonzero(jump_log_bound(s, sigma_minor, sigma_major, hits[batch]) >= log_p)
            first = int(batch[good[0]]) if good.size else -1
            done += batch.size
            size *= 2
    if first < 0:
        return CfarThresholds(False, -1, nan, nan, int(hits.size))
    k = int(hits[first])
    same = float(s[k])
    return CfarThresholds(True, k, same, float(max(p.different_source_factor * same, s[k + 1])), first)


def isolated_mutual_pairs(dist: np.ndarray, factor: float) -> int:
    """Mutually nearest pairs whose distance times ``factor`` is below the second-nearest
    distance of both tracks (a missing second track counts as infinitely far): an estimate of
    the number of common targets (``CfarParams.min_jump_share``)."""
    d = np.asarray(dist, dtype=float)
    i, j, second_row, second_col = _mutual_nearest(d)
    dij = factor * d[i, j]
    return int(np.count_nonzero((dij < second_row[i]) & (dij < second_col[j])))


def _mutual_nearest(d: FloatArray) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """Mutually nearest pairs ``(i, j)`` of a distance matrix and every row's and column's
    second-smallest distance (inf where there is none)."""
    m, n = d.shape
    nearest_radar = np.argmin(d, axis=1)
    nearest_ref = np.argmin(d, axis=0)
    i = np.flatnonzero(nearest_ref[nearest_radar] == np.arange(m)).astype(np.intp)
    j = nearest_radar[i].astype(np.intp)
    second_row = np.partition(d, 1, axis=1)[:, 1] if n > 1 else np.full(m, np.inf)
    second_col = np.partition(d, 1, axis=0)[1, :] if m > 1 else np.full(n, np.inf)
    return i, j, second_row, second_col


def confident_pairs(
    dist: np.ndarray, same_source_m: float, different_source_m: float
) -> tuple[IntArray, IntArray]:
    """Confidential pairs (Section 2.3): mutually nearest, distance at most ``same_source_m``,
    and both the reference's second-nearest radar track and the radar track's second-nearest
    reference track farther than ``different_source_m`` (a missing second track counts as
    infinitely far)."""
    d = np.asarray(dist, dtype=float)
    i, j, second_row, second_col = _mutual_nearest(d)
    ok = (
        (d[i, j] <= same_source_m)
        & (second_row[i] > different_source_m)
        & (second_col[j] > different_source_m)
    )
    return i[ok].astype(np.intp), j[ok].astype(np.intp)


def bias_least_squares(ref_polar: np.ndarray, radar_polar: np.ndarray) -> CfarBias:
    """Least-squares range and azimuth bias from paired rows of ``ref_polar`` and ``radar_polar``.

    Bias model of Eqs. (17)-(18) in the radar's polar frame: ``r_meas = r_true + dr + e_r``,
    ``theta_meas = theta_true + dtheta + e_theta``.  With white polar errors the design matrix
    is the identity per pair, so the normal equations give the mean residuals:
    ``dr = mean(r_meas - r_true)``, ``dtheta = mean(wrap(theta_meas - theta_true))``.
    """
    ref = np.asarray(ref_polar, dtype=float).reshape(-1, 2)
    rad = np.asarray(radar_polar, dtype=float).reshape(-1, 2)
    n = min(ref.shape[0], rad.shape[0])
    if n == 0:
        nan = float("nan")
        return CfarBias(nan, nan, nan, nan, 0)
    dr = rad[:n, 0] - ref[:n, 0]
    da = wrap_deg(rad[:n, 1] - ref[:n, 1])
    ddof_ok = n > 1
    return CfarBias(
        range_bias_m=float(dr.mean()),
        azimuth_bias_deg=float(da.mean()),
        range_residual_std_m=float(dr.std(ddof=1)) if ddof_ok else float("nan"),
        azimuth_residual_std_deg=float(da.std(ddof=1)) if ddof_ok else float("nan"),
        n_pairs=n,
    )


def polar_residuals(ref_polar: np.ndarray, radar_polar: np.ndarray) -> FloatArray:
    """``[r_radar - r_ref, wrap(theta_radar - theta_ref)]`` of paired rows, ``(n, 2)``: the
    bias plus random error under Eqs. (17)-(18)."""
    ref = np.asarray(ref_polar, dtype=float).reshape(-1, 2)
    rad = np.asarray(radar_polar, dtype=float).reshape(-1, 2)
    return np.column_stack([rad[:, 0] - ref[:, 0], wrap_deg(rad[:, 1] - ref[:, 1])])


def quad2(r: np.ndarray, s: np.ndarray) -> FloatArray:
    """``r^T S^-1 r`` for stacks of 2-vectors ``(..., 2)`` and symmetric 2x2 matrices
    ``(..., 2, 2)`` (closed form); inf where ``S`` is singular (determinant <= 1e-12 of the
    product of its diagonal) or not finite."""
    a, b, d = s[..., 0, 0], s[..., 0, 1], s[..., 1, 1]
    det = a * d - b * b
    x, y = r[..., 0], r[..., 1]
    good = np.isfinite(det) & (det > 1e-12 * np.abs(a * d)) & (det > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = (d * x * x - 2.0 * b * x * y + a * y * y) / np.where(good, det, 1.0)
    return np.asarray(np.where(good, q, np.inf))


def consistent_pairs(
    residuals: np.ndarray, covs: np.ndarray, gate_chi2: float, params: CfarParams
) -> PairConsistency:
    """Bias of paired tracks and which pairs are consistent with it (addition to the paper).

    ``residuals``: ``(n, 2)`` :func:`polar_residuals`; ``covs``: ``(n, 2, 2)`` each pair's
    ``C_ref + C_radar``.  Steps: (1) a robust start, the per-component median; pairs within the
    gate of it (their own covariance) are the *inliers*; (2) the least-squares bias of Eqs.
    (17)-(18) is the inliers' mean; each pair's residual is tested against the mean of the
    *other* inliers (leave-one-out: ``b_k = (sum x - x_k) / (n - 1)`` with covariance
    ``(sum S - S_k) / (n - 1)^2``; a non-inlier against all of them), ``q_k = (x_k - b_k)^T
    (S_k + C_{b,k})^-1 (x_k - b_k)``; a lone inlier gets ``q = 0`` (nothing to test it against);
    (3) with ``inflate_to_residuals`` and at least ``min_pairs_for_inflation`` inliers every
    covariance is scaled by ``f = max(1, median(q_inliers) / median(chi2_2))``; (4) passed:
    ``q_k / f <= gate_chi2``; the bias is the mean of the passed pairs, its covariance
    ``f sum S / n^2``.  Vectorised; :func:`tests.reference_forms.cfar_consistency_reference`
    is the plain form.
    """
    x = np.asarray(residuals, dtype=float).reshape(-1, 2)
    c = np.asarray(covs, dtype=float).reshape(-1, 2, 2)
    n = x.shape[0]
    nan2 = np.full(2, np.nan)
    if n == 0:
        return PairConsistency(nan2, np.full((2, 2), np.nan), np.empty(0), np.zeros(0, dtype=bool), 1.0)
    start = np.median(x, axis=0)
    inlier = quad2(x - start, c) <= gate_chi2
    n_in = int(inlier.sum())
    if n_in == 0:
        return PairConsistency(
            nan2, np.full((2, 2), np.nan), np.full(n, np.inf), np.zeros(n, dtype=bool), 1.0
        )
    sum_x = x[inlier].sum(axis=0)
    sum_c = c[inlier].sum(axis=0)
    others = np.where(inlier, n_in - 1, n_in).astype(float)
    own = inlier[:, None].astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        loo = (sum_x[None, :] - own * x) / others[:, None]
        loo_cov = (sum_c[None, :, :] - own[:, :, None] * c) / (others**2)[:, None, None]
    q = quad2(x - loo, c + loo_cov)
    q = np.where(others > 0, q, 0.0)  # a lone inlier: nothing to test it against
    f = 1.0
    if params.inflate_to_residuals and n_in >= params.min_pairs_for_inflation:
        f = max(1.0, float(np.median(q[inlier])) / _CHI2_2_MEDIAN)
    q = q / f
    passed = q <= gate_chi2
    n_ok = int(passed.sum())
    if n_ok == 0:
        return PairConsistency(nan2, np.full((2, 2), np.nan), q, passed, f)
    bias = x[passed].mean(axis=0)
    bias_cov = f * c[passed].sum(axis=0) / n_ok**2
    return PairConsistency(bias, bias_cov, q, passed, f)


def pair_chi2(
    ref_polar: np.ndarray,
    comp_polar: np.ndarray,
    ref_cov: np.ndarray,
    radar_cov: np.ndarray,
    extra_cov: np.ndarray,
) -> FloatArray:
    """Chi-square ``(M, N)`` of every reference row against every bias-compensated radar row:
    ``r^T S^-1 r`` with ``r = [r_comp - r_ref, wrap(theta_comp - theta_ref)]`` and ``S = C_ref_i
    + C_radar_j + extra`` (the bias estimate's covariance; reconstructed gate of step 5)."""
    ref = np.asarray(ref_polar, dtype=float).reshape(-1, 2)
    comp = np.asarray(comp_polar, dtype=float).reshape(-1, 2)
    r = np.stack([comp[None, :, 0] - ref[:, None, 0], wrap_deg(comp[None, :, 1] - ref[:, None, 1])], axis=-1)
    s = np.asarray(ref_cov)[:, None, :, :] + np.asarray(radar_cov)[None, :, :, :] + np.asarray(extra_cov)
    return quad2(r, s)


def unambiguous(cost: np.ndarray, rows: np.ndarray, cols: np.ndarray, margin: float) -> BoolArray:
    """For each assigned cell ``(rows[k], cols[k])`` of ``cost`` (inf: not a candidate): True when
    every other finite entry of its row and of its column exceeds its cost by at least
    ``margin`` (``CfarParams.ambiguity_margin``).  Vectorised with the two smallest entries of
    each row and column."""
    c = np.asarray(cost, dtype=float)
    r_idx = np.asarray(rows, dtype=np.intp)
    c_idx = np.asarray(cols, dtype=np.intp)
    if r_idx.size == 0 or margin <= 0:
        return np.ones(r_idx.size, dtype=bool)
    m, n = c.shape
    two_r = np.partition(c, 1, axis=1)[:, :2] if n > 1 else np.column_stack([c[:, 0], np.full(m, np.inf)])
    two_c = np.partition(c, 1, axis=0)[:2, :].T if m > 1 else np.column_stack([c[0, :], np.full(n, np.inf)])
    own = c[r_idx, c_idx]
    # The best other entry: the second smallest when the cell is the smallest, else the smallest.
    alt_r = np.where(own <= two_r[r_idx, 0], two_r[r_idx, 1], two_r[r_idx, 0])
    alt_c = np.where(own <= two_c[c_idx, 0], two_c[c_idx, 1], two_c[c_idx, 0])
    with np.errstate(invalid="ignore"):
        return np.asarray((alt_r - own >= margin) & (alt_c - own >= margin))


def _principal_sigmas(
    ref: FloatArray, rad: FloatArray, cref: FloatArray, crad: FloatArray, ii: IntArray, jj: IntArray
) -> tuple[FloatArray, FloatArray]:
    """Principal standard deviations (m) of the plane covariance of pairs ``(ii[k], jj[k])``:
    each side's ``[range, azimuth]`` covariance in metres (``azimuth * r * pi / 180``, its own
    range), summed."""

    def metric(
        polar: FloatArray, cov: FloatArray, rows: IntArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        scale = polar[rows, 0] * (np.pi / 180.0)
        c = cov[rows]
        return c[:, 0, 0], c[:, 0, 1] * scale, c[:, 1, 1] * scale * scale

    a1, b1, d1 = metric(ref, cref, ii)
    a2, b2, d2 = metric(rad, crad, jj)
    a, b, d = a1 + a2, b1 + b2, d1 + d2
    half_tr = 0.5 * (a + d)
    root = np.sqrt(0.25 * (a - d) ** 2 + b * b)
    return np.sqrt(np.maximum(half_tr - root, 0.0)), np.sqrt(np.maximum(half_tr + root, 0.0))


def _covariances(
    ref: FloatArray, rad: FloatArray, ref_cov: np.ndarray | None, radar_cov: np.ndarray | None, p: CfarParams
) -> tuple[FloatArray, FloatArray] | str:
    """The tracks' ``[range, azimuth]`` covariances (the parameters' when not given), or why not."""
    m, n = ref.shape[0], rad.shape[0]
    cref = np.zeros((m, 2, 2)) if ref_cov is None else np.asarray(ref_cov, dtype=float)
    if radar_cov is None:
        crad = np.zeros((n, 2, 2))
        crad[:, 0, 0] = p.range_sigma_m**2
        crad[:, 1, 1] = p.azimuth_sigma_deg**2
    else:
        crad = np.asarray(radar_cov, dtype=float)
    if cref.shape != (m, 2, 2) or crad.shape != (n, 2, 2):
        return f"covariances must be (M, 2, 2) and (N, 2, 2); got {cref.shape}, {crad.shape}"
    if not (np.isfinite(cref).all() and np.isfinite(crad).all()):
        return "non-finite track covariances"
    return cref, crad


def _known_pairs(
    known_ref: np.ndarray | None, known_radar: np.ndarray | None, m: int, n: int
) -> tuple[IntArray, IntArray] | str:
    kr = np.asarray([] if known_ref is None else known_ref, dtype=np.intp).ravel()
    kj = np.asarray([] if known_radar is None else known_radar, dtype=np.intp).ravel()
    if kr.shape != kj.shape:
        return f"known pairs: {kr.size} reference rows, {kj.size} radar rows"
    if kr.size and (kr.min() < 0 or kr.max() >= m or kj.min() < 0 or kj.max() >= n):
        return "known pairs: row out of range"
    if np.unique(kr).size != kr.size or np.unique(kj).size != kj.size:
        return "known pairs: a track in two pairs"
    return kr, kj


def cfar_associate(
    ref_polar: np.ndarray,
    radar_polar: np.ndarray,
    params: CfarParams | None = None,
    ref_cov: np.ndarray | None = None,
    radar_cov: np.ndarray | None = None,
    known_ref: np.ndarray | None = None,
    known_radar: np.ndarray | None = None,
) -> CfarResult:
    """Associate reference tracks (AIS, bias-free) with one radar's tracks under its bias.

    ``ref_polar``: ``(M, 2)`` ``[range_m, azimuth_deg]`` of the reference tracks as seen from the
    radar's site (true positions converted to the radar's polar frame); ``radar_polar``:
    ``(N, 2)`` the radar's tracks, at the same times.  ``ref_cov``/``radar_cov``: ``(M, 2, 2)``,
    ``(N, 2, 2)`` covariances of those ``[range_m, azimuth_deg]`` (None: none for the reference,
    ``range_sigma_m``/``azimuth_sigma_deg`` for the radar).  ``known_ref[k]``/``known_radar[k]``:
    pairs the caller already holds (re-verified): they count as confidential pairs for the bias,
    their rows join no other pair, and they are not in the result.  Degenerate inputs return an
    empty result whose ``reason`` says why; this function does not raise on data.
    """
    p = params if params is not None else CfarParams()
    ref = np.asarray(ref_polar, dtype=float)
    rad = np.asarray(radar_polar, dtype=float)
    if ref.ndim != 2 or rad.ndim != 2 or ref.shape[1] != 2 or rad.shape[1] != 2:
        return _empty(
            f"inputs must be (M, 2) and (N, 2) [range_m, azimuth_deg]; got {ref.shape}, {rad.shape}"
        )
    m, n = ref.shape[0], rad.shape[0]
    if m == 0 or n == 0:
        return _empty(f"no tracks to associate (reference: {m}, radar: {n})")
    if not (np.isfinite(ref).all() and np.isfinite(rad).all()):
        return _empty("non-finite track coordinates")
    if (ref[:, 0] < 0).any() or (rad[:, 0] < 0).any():
        return _empty("negative range")
    covs = _covariances(ref, rad, ref_cov, radar_cov, p)
    if isinstance(covs, str):
        return _empty(covs)
    cref, crad = covs
    known = _known_pairs(known_ref, known_radar, m, n)
    if isinstance(known, str):
        return _empty(known)
    kr, kj = known

    # Steps 1-2: distance matrix, sorted distances, CA-CFAR thresholds (Section 2.4); a
    # detection the pair covariances or the isolated pairs make implausible is passed over.
    dist = distance_matrix(ref, rad)
    flat = dist.ravel()
    # The pair sigmas of the first entries only: the true jump comes after about as many
    # distances as there are common targets (<= min(M, N)); a bound over a prefix is still one.
    width = min(flat.size, _SIGMA_PREFIX_FACTOR * min(m, n) + _SIGMA_PREFIX_MIN)
    first = np.argpartition(flat, width - 1)[:width] if width < flat.size else np.arange(flat.size)
    first = first[np.argsort(flat[first], kind="stable")]
    ii, jj = np.unravel_index(first, dist.shape)
    s1, s2 = _principal_sigmas(ref, rad, cref, crad, ii.astype(np.intp), jj.astype(np.intp))
    expected = isolated_mutual_pairs(dist, p.different_source_factor)
    thr = ca_cfar_thresholds(np.sort(flat), p, s1, s2, expected)

    # Step 3: confidential pairs (Section 2.3), none sharing a track with a known pair.
    ci = cj = np.empty(0, dtype=np.intp)
    if thr.detected:
        ci, cj = confident_pairs(dist, thr.same_source_m, thr.different_source_m)
        clash = np.isin(ci, kr) | np.isin(cj, kj)
        ci, cj = ci[~clash], cj[~clash]
    if kr.size + ci.size < max(1, p.min_confident_pairs):
        if not thr.detected and thr.passed_over:
            return _empty(
                f"no plausible same-source/different-source jump among {dist.size} distances "
                f"({thr.passed_over} detections passed over)",
                thr,
            )
        if not thr.detected:
            return _empty(f"no same-source/different-source jump detected among {dist.size} distances", thr)
        return _empty(f"{ci.size} confidential + {kr.size} known pairs, need {p.min_confident_pairs}", thr)

    # Step 4: least-squares bias, Eqs. (17)-(18), from the known and the consistent
    # confidential pairs; compensation of the radar tracks.
    gate = float(chi2_quantile(p.gate_probability, 2))
    pi = np.concatenate([kr, ci])
    pj = np.concatenate([kj, cj])
    cons = consistent_pairs(polar_residuals(ref[pi], rad[pj]), cref[pi] + crad[pj], gate, p)
    keep_conf = cons.passed[kr.size :]
    ci, cj = ci[keep_conf], cj[keep_conf]
    if not cons.passed.any():
        return _empty(
            "the confidential pairs are inconsistent with any one bias", thr, inflation=cons.inflation
        )
    comp = rad - cons.bias[None, :]

    # Step 5: second association of the rest, 2-D assignment under the chi-square gate with each
    # candidate's own covariance plus the bias estimate's (reconstructed).
    free_ref = np.ones(m, dtype=bool)
    free_rad = np.ones(n, dtype=bool)
    # The known pairs' tracks stay theirs; a confidential pair inconsistent with the bias is free.
    free_ref[kr] = free_ref[ci] = False
    free_rad[kj] = free_rad[cj] = False
    rows = np.flatnonzero(free_ref)
    cols = np.flatnonzero(free_rad)
    si = sj = np.empty(0, dtype=np.intp)
    if rows.size and cols.size:
        q = pair_chi2(ref[rows], comp[cols], cref[rows], crad[cols], cons.bias_cov) / cons.inflation
        sub_ok = q <= gate
        r_any = np.flatnonzero(sub_ok.any(axis=1))
        c_any = np.flatnonzero(sub_ok.any(axis=0))
        if r_any.size and c_any.size:
            ok = sub_ok[np.ix_(r_any, c_any)]
            big = gate + 1.0  # any cost above the gate marks "not allowed"; assigned ones are dropped
            cost = np.where(ok, q[np.ix_(r_any, c_any)], big)
            r, c = linear_sum_assignment(cost)
            keep = ok[r, c] & unambiguous(np.where(ok, cost, np.inf), r, c, p.ambiguity_margin)
            si, sj = rows[r_any[r[keep]]], cols[c_any[c[keep]]]

    index_ref = np.concatenate([ci, si]).astype(np.intp)
    index_radar = np.concatenate([cj, sj]).astype(np.intp)
    known_ok = cons.passed[: kr.size]
    if p.refine_bias:
        bias = bias_least_squares(
            ref[np.concatenate([kr[known_ok], index_ref])], rad[np.concatenate([kj[known_ok], index_radar])]
        )
    else:
        bias = CfarBias(
            float(cons.bias[0]), float(cons.bias[1]), float("nan"), float("nan"), int(cons.passed.sum())
        )
    confident = np.concatenate([np.ones(ci.size, dtype=bool), np.zeros(si.size, dtype=bool)])
    order_out = np.argsort(index_ref, kind="stable")
    return CfarResult(
        index_ref=index_ref[order_out],
        index_radar=index_radar[order_out],
        confident=confident[order_out],
        same_source_threshold_m=thr.same_source_m,
        different_source_threshold_m=thr.different_source_m,
        range_bias_m=bias.range_bias_m,
        azimuth_bias_deg=bias.azimuth_bias_deg,
        reason=(
            f"associated: {ci.size} confidential + {si.size} second-stage pairs"
            f" ({int(known_ok.sum())} known pairs in the bias)"
        ),
        inflation=cons.inflation,
    )
