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
   (Section 2.4, Fig. 1) and gives the same-source and different-source thresholds;
3. *confidential pairs* (Section 2.3): mutually nearest, closer than the same-source
   threshold, and the second-nearest track of each farther than the different-source
   threshold;
4. least-squares range and azimuth bias from the confidential pairs, bias model of Eqs.
   (17)-(18): ``r_meas = r_true + dr``, ``theta_meas = theta_true + dtheta``;
5. after compensation, a second association (2-D assignment with a chi-square and distance
   gate, the paper's conclusion (3)) pairs the remaining tracks; the bias is then re-estimated
   from all final pairs (``CfarParams.refine_bias``; an addition to the paper).

Equation numbers.  The extraction lost the displayed equations of Sections 2.1-2.4 and their
numbers are not recoverable from the text; only Eqs. (17)-(18) (true position and the radar's
range/azimuth bias decomposition, Section 3.2.2) are cross-referenced.  Formulas of steps 1-3
and 5 are marked *reconstructed*: they follow the digest's standard-method form (the CA-CFAR
of the paper's ref. [14], He You et al., "Radar target detection and CFAR processing").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

_TINY = float(np.finfo(float).tiny)


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
    the per-cell false-alarm probability is ``(1 + T/n)^-n`` (about 2.6 % for 5 and 6).  An
    early false alarm only shrinks the thresholds (fewer, still safe, confidential pairs); a
    too-high ``T`` misses the jump when the azimuth bias spreads the same-source distances
    (they grow with range as ``r * dtheta``).  5-6 worked best in simulation (30-50 vessels,
    biases 500 m / 0.5 deg and 1500 m / 1 deg)."""

    min_reference_cells: int = 3
    """At the start of the sorted list fewer than ``reference_cells`` differences precede the
    test cell; the window is shortened down to this many cells (fewer: cell not tested).  Lets
    scenes with only a few common tracks still find their jump."""

    different_source_factor: float = 2.0
    """Different-source threshold = this factor times the same-source threshold, but at least
    the first distance after the jump (Section 3.1 takes a factor whose value the extraction
    lost; *reconstructed*)."""

    gate_probability: float = 0.999
    """Second stage: chi-square gate (2 degrees of freedom) on the bias-compensated polar residual
    ``(dr / s_r)^2 + (dtheta / s_theta)^2``.  The compensated pair must also be closer than the
    different-source threshold (the distance gate)."""

    range_sigma_m: float | None = None
    """Random range error (m) of a radar track against its reference after compensation.  None:
    estimated from the confidential pairs' residuals (needs ``min_pairs_for_sigma`` pairs), else
    ``fallback_range_sigma_m``."""

    azimuth_sigma_deg: float | None = None
    """Random azimuth error (deg), as ``range_sigma_m``."""

    fallback_range_sigma_m: float = 100.0
    """Range sigma (m) used when it is neither given nor estimable."""

    fallback_azimuth_sigma_deg: float = 0.3
    """Azimuth sigma (deg) used when it is neither given nor estimable."""

    min_range_sigma_m: float = 5.0
    """Floor of an estimated range sigma (m): a few pairs can agree by chance."""

    min_azimuth_sigma_deg: float = 0.01
    """Floor of an estimated azimuth sigma (deg)."""

    min_pairs_for_sigma: int = 5
    """Confidential pairs needed to estimate the sigmas from their residuals."""

    min_confident_pairs: int = 1
    """Confidential pairs needed to estimate the bias; fewer: no decision."""

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
    """Row of ``ref_polar`` of each final pair (sorted)."""
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

    def __bool__(self) -> bool:
        return bool(self.index_ref.size)


@dataclass(frozen=True)
class CfarThresholds:
    """The CA-CFAR detection on the sorted distances (:func:`ca_cfar_thresholds`)."""

    detected: bool
    """True when a jump was found."""
    jump_index: int
    """Index ``k`` into the differences ``s[k+1] - s[k]`` of the first detection (-1: none)."""
    same_source_m: float
    """``s[k]``: the largest same-source distance (NaN: none)."""
    different_source_m: float
    """``max(factor * s[k], s[k+1])`` (NaN: none)."""


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


def _empty(reason: str, thr: CfarThresholds | None = None, bias: CfarBias | None = None) -> CfarResult:
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


def ca_cfar_thresholds(sorted_distances: np.ndarray, params: CfarParams | None = None) -> CfarThresholds:
    """Same- and different-source thresholds from ascending distances (Section 2.4).

    Differences ``delta_k = s[k+1] - s[k]``; the first CA-CFAR detection ``k`` marks the jump
    from same-source to different-source distances: same-source threshold ``s[k]``,
    different-source threshold ``max(factor * s[k], s[k+1])`` (reconstructed).
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
    k = int(hits[0])
    same = float(s[k])
    return CfarThresholds(True, k, same, float(max(p.different_source_factor * same, s[k + 1])))


def confident_pairs(
    dist: np.ndarray, same_source_m: float, different_source_m: float
) -> tuple[IntArray, IntArray]:
    """Confidential pairs (Section 2.3): mutually nearest, distance at most ``same_source_m``,
    and both the reference's second-nearest radar track and the radar track's second-nearest
    reference track farther than ``different_source_m`` (a missing second track counts as
    infinitely far)."""
    d = np.asarray(dist, dtype=float)
    m, n = d.shape
    nearest_radar = np.argmin(d, axis=1)
    nearest_ref = np.argmin(d, axis=0)
    i = np.flatnonzero(nearest_ref[nearest_radar] == np.arange(m))
    j = nearest_radar[i]
    second_row = np.partition(d, 1, axis=1)[:, 1] if n > 1 else np.full(m, np.inf)
    second_col = np.partition(d, 1, axis=0)[1, :] if m > 1 else np.full(n, np.inf)
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


def _sigmas(bias: CfarBias, p: CfarParams) -> tuple[float, float]:
    """Range and azimuth sigmas for the second-stage gate (given, estimated, or fallback)."""
    estimable = bias.n_pairs >= p.min_pairs_for_sigma
    if p.range_sigma_m is not None:
        s_r = p.range_sigma_m
    elif estimable:
        s_r = max(bias.range_residual_std_m, p.min_range_sigma_m)
    else:
        s_r = p.fallback_range_sigma_m
    if p.azimuth_sigma_deg is not None:
        s_a = p.azimuth_sigma_deg
    elif estimable:
        s_a = max(bias.azimuth_residual_std_deg, p.min_azimuth_sigma_deg)
    else:
        s_a = p.fallback_azimuth_sigma_deg
    return float(s_r), float(s_a)


def cfar_associate(
    ref_polar: np.ndarray, radar_polar: np.ndarray, params: CfarParams | None = None
) -> CfarResult:
    """Associate reference tracks (AIS, bias-free) with one radar's tracks under its bias.

    ``ref_polar``: ``(M, 2)`` ``[range_m, azimuth_deg]`` of the reference tracks as seen from the
    radar's site (true positions converted to the radar's polar frame); ``radar_polar``:
    ``(N, 2)`` the radar's tracks, at the same times.  Degenerate inputs return an empty result
    whose ``reason`` says why; this function does not raise on data.
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

    # Steps 1-2: distance matrix, sorted distances, CA-CFAR thresholds (Section 2.4).
    dist = distance_matrix(ref, rad)
    thr = ca_cfar_thresholds(np.sort(dist, axis=None), p)
    if not thr.detected:
        return _empty(f"no same-source/different-source jump detected among {dist.size} distances", thr)

    # Step 3: confidential pairs (Section 2.3).
    ci, cj = confident_pairs(dist, thr.same_source_m, thr.different_source_m)
    if ci.size < max(1, p.min_confident_pairs):
        return _empty(f"{ci.size} confidential pairs, need {p.min_confident_pairs}", thr)

    # Step 4: least-squares bias, Eqs. (17)-(18), and compensation of the radar tracks.
    bias = bias_least_squares(ref[ci], rad[cj])
    comp = np.column_stack([rad[:, 0] - bias.range_bias_m, rad[:, 1] - bias.azimuth_bias_deg])

    # Step 5: second association of the rest, 2-D assignment with chi-square and distance gates
    # (reconstructed).  Gate variance includes the bias estimate's own variance (s^2 / n).
    s_r, s_a = _sigmas(bias, p)
    inflate = 1.0 + 1.0 / ci.size
    chi = (comp[None, :, 0] - ref[:, None, 0]) ** 2 / (s_r**2 * inflate) + wrap_deg(
        comp[None, :, 1] - ref[:, None, 1]
    ) ** 2 / (s_a**2 * inflate)
    gate = float(chi2.ppf(p.gate_probability, df=2))
    ok = (chi <= gate) & (distance_matrix(ref, comp) <= thr.different_source_m)
    free_ref = np.ones(m, dtype=bool)
    free_rad = np.ones(n, dtype=bool)
    free_ref[ci] = False
    free_rad[cj] = False
    ok &= free_ref[:, None] & free_rad[None, :]
    rows = np.flatnonzero(ok.any(axis=1))
    cols = np.flatnonzero(ok.any(axis=0))
    si = sj = np.empty(0, dtype=np.intp)
    if rows.size and cols.size:
        sub_ok = ok[np.ix_(rows, cols)]
        big = gate + 1.0  # any cost above the gate marks "not allowed"; assigned ones are dropped
        cost = np.where(sub_ok, chi[np.ix_(rows, cols)], big)
        r, c = linear_sum_assignment(cost)
        keep = sub_ok[r, c]
        si, sj = rows[r[keep]], cols[c[keep]]

    index_ref = np.concatenate([ci, si]).astype(np.intp)
    index_radar = np.concatenate([cj, sj]).astype(np.intp)
    if p.refine_bias:
        bias = bias_least_squares(ref[index_ref], rad[index_radar])
    confident = np.concatenate([np.ones(ci.size, dtype=bool), np.zeros(si.size, dtype=bool)])
    order = np.argsort(index_ref, kind="stable")
    return CfarResult(
        index_ref=index_ref[order],
        index_radar=index_radar[order],
        confident=confident[order],
        same_source_threshold_m=thr.same_source_m,
        different_source_threshold_m=thr.different_source_m,
        range_bias_m=bias.range_bias_m,
        azimuth_bias_deg=bias.azimuth_bias_deg,
        reason=f"associated: {ci.size} confidential + {si.size} second-stage pairs",
    )
