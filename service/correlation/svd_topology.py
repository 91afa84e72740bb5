"""SVD topology-sequence correlation (method ``svd-topology``; Wu, Jiang, Ren 2011).

One *single decision* per candidate pair (reference track ``i`` of A, ``j`` of B), batched
over all candidates of an update:

1. Topology sequences in each radar's own ENU frame (Section 2 step 1,
   :mod:`service.correlation.topology`); A's is rotated into B's orientation with the known
   ``M0 = R_B^-1 R_A`` of Eq. (3), so the remaining rotation is the bias part only.
2. Robust neighbour pairing (the paper leaves it open; sequences can differ in length):
   (a) rotation-tolerant mutual nearest neighbour on the vectors ``z_i = x_i - x_0``
   (horizontal radial mismatch, the tangential mismatch beyond
   ``pairing_rotation_tolerance_deg`` and the vertical mismatch);
   (b) similarity fit; (c) mutual nearest neighbour again with the fitted transform under a
   chi-square gate; (d) elements whose residual fails ``element_gate_chi2`` are trimmed and
   the fit repeated.
3. Similarity fit of the paired neighbour vectors, Eq. (7), by :mod:`service.correlation.umeyama`
   (``rotation_model = "yaw"``: rotation about the vertical, 5 parameters; ``"full"``: the
   paper's 3-D rotation, 7 parameters).
4. Validity (Section 1.5): ``weight(M) >= 0.92``.  The paper's ``M`` is the whole A-to-B
   rotation; here ``M0`` is known exactly from the sites, so the check is applied to the
   fitted bias rotation ``M_fit`` (the part that can be wrong).  With ``constrained_fit``
   (default) the pairing fits keep yaw and scale within ``max_bias_rotation_deg`` and
   ``max_scale_deviation``; the test's weighted fit (6) has them as a Gaussian prior.  A hard
   ``|c - 1| <= max_scale_deviation`` rejection applies to the paper's free 3-D fit only.
5. Covariance after the transform (Section 1.6).  The paper prints ``c^2 M^T P M``; for a
   vector mapped by ``y = c M x`` the covariance is ``c^2 M P M^T`` (``Cov(Ax) = A Cov(x)
   A^T``), which is what is used.  The residual of element ``k`` has ``S_k = c^2 M P_A,k M^T
   + P_B,k`` (the reference's own noise is common to all elements and absorbed by ``t``).
6. Matching test (Section 1.4; the paper defers to its reference [9]).  The statistics come
   from the covariance-weighted (GLS) fit of the paired elements with the physical prior on
   yaw and scale (:mod:`service.correlation.gls`; ``rotation_model = "yaw"``): only the
   minimum of the weighted norm is chi-square distributed (the unweighted SVD fit of Section
   1.3 left a statistic that rejected 2.5-3.5 % of true pairs at a nominal 1 %).  Two parts:
   *shape*: ``chi2_shape`` = weighted residual + prior terms over the ``m`` paired
   neighbours, chi-square with the effective ``nu = 3 m - tr(H^-1 H_data)`` degrees of
   freedom (between ``3 m - 5`` and ``3 m - 3``), accepted at level ``alpha_shape``;
   *position*: in topology-vector coordinates both references sit at the origin, so the
   fitted translation ``t`` is the A reference's position predicted from the neighbours
   minus the B reference's: Eq. (4) says it must be small.  ``chi2_ref = t^T S_ref^-1 t``
   with ``S_ref = S_0 + Cov(t)`` (references' noise plus the fit's translation block), 3 dof,
   accepted at ``alpha_position``.  This is what tells two close targets apart.
   ``alpha_shape + alpha_position = 1 %``: the single match's size (Bonferroni).
   With velocities (the stream), ``v_B - c M v_A`` adds a 3-dof velocity term.
   ``statistic`` is the F statistic ``F = (chi2_shape + chi2_ref) / (nu + 3)``, which under
   the hypothesis is ``F(nu + 3, inf)``-distributed: the residual variance of the fit over
   the variance expected from the radars' random errors.  (``rotation_model = "full"``, the
   paper's 3-D fit kept for reference, uses the unweighted statistic with ``nu = 3 m - 7``.)
7. Accepted candidates go to a one-to-one assignment with an ambiguity margin
   (:mod:`service.correlation.assignment`), done by the caller.

Once the stream has registered the radars (snapshots bias-compensated by the Eq. 2 model,
:func:`service.correlation.registration.compensate`) two cheaper decisions use the textbook
absolute chi-square of :mod:`service.correlation.nearest` (He et al. 2007, the paper's
reference [1]) with the registration's own covariance added (:func:`compensated_chi2`):
*stage 2* decides candidates the topology cannot (too few neighbours), and *stage 3*
(:meth:`SvdTopologyCorrelator.reverify`) keeps the currently confirmed pairs that still pass
it, so that the topology match runs only for the tracks that need a decision.  Neither fits a
topology: their ``rotation_weight`` and ``scale`` are NaN (null on the wire), not a claimed
identity.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
from annotated_types import Gt
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.chi2 import chi2_upper
from service.correlation.base import (
    BoolArray,
    CorrelationMethod,
    DecisionContext,
    Decisions,
    FloatArray,
    PredictedTracks,
    Reason,
)
from service.correlation.candidates import CandidateParams, candidate_pairs
from service.correlation.gls import similarity_gls_batch
from service.correlation.nearest import chi2_pairs
from service.correlation.prompt import clear_of_rivals, companions
from service.correlation.topology import (
    BRUTE_FORCE_MAX_DISTANCES,
    TopologyParams,
    gather_points,
    neighbourhoods,
)
from service.correlation.umeyama import (
    SimilarityFit,
    rotation_weight,
    umeyama_batch,
    yaw_matrix,
    yaw_similarity_batch,
)
from service.linalg import (
    congruence,
    inv3,
    mahalanobis2_h,
    mahalanobis3,
    quad3_large,
    yaw_congruence,
)


@dataclass(frozen=True)
class SvdTopologyParams:
    """Every threshold of the SVD topology match."""

    topology: TopologyParams = field(default_factory=TopologyParams)
    candidates: CandidateParams = field(default_factory=CandidateParams)
    #: ``"yaw"`` (rotation about the local vertical: what an azimuth bias produces) or ``"full"``
    #: (the paper's unconstrained 3-D rotation, ill-conditioned for near-horizontal vectors).
    rotation_model: str = "yaw"
    #: Section 1.5: minimum diagonal weight of the A-to-B rotation (0.92 ~ 6.5 deg in total).
    min_rotation_weight: float = 0.92
    #: Largest ``|c - 1|`` physically possible: a range bias ``dr`` scales cross-range
    #: neighbour vectors by about ``dr / r`` (2 km at 100 km: 0.02).  With ``constrained_fit``
    #: the yaw fit's scale is clipped to it; otherwise (and for ``"full"``) a larger fitted
    #: ``|c - 1|`` rejects the candidate.
    max_scale_deviation: float = 0.03
    #: Largest yaw (differential azimuth bias, deg) physically possible between the radars.
    max_bias_rotation_deg: float = 5.0
    #: Yaw model: fit the similarity *within* the physical bounds above (constrained least
    #: squares) instead of fitting freely and rejecting out-of-bound fits.  With 2-5
    #: neighbours at <= 10 km and ~700 m relative noise the free yaw is uncertain by several
    #: degrees, so the paper's reject-after-fit (Section 1.5) loses many true pairs; the
    #: constrained fit keeps the check's intent (only physically possible transforms) and lets
    #: the chi-square test judge the residual.
    constrained_fit: bool = True
    #: Minimum paired neighbours for a decision (2 suffices for the yaw model's 5 parameters,
    #: the full model needs 3 non-collinear).
    min_matched: int = 2
    #: Minimum paired neighbours as a fraction of the shorter sequence.
    min_match_fraction: float = 0.6
    #: Rotation the first pairing tolerates for free (beyond it, tangential mismatch counts).
    pairing_rotation_tolerance_deg: float = 6.0
    #: Gate (m) of the first, rotation-tolerant pairing.
    pairing_gate_m: float = 4_000.0
    #: Chi-square (3 dof: horizontal Mahalanobis + vertical) gate of the re-pairing with the
    #: fitted transform (99.9 %).
    repair_gate_chi2: float = 16.3
    #: Chi-square (3 dof) an element may reach before it is trimmed as mispaired (99.9 %).
    element_gate_chi2: float = 16.3
    #: Yaw model: 1-sigma of the Gaussian prior on the scale ``c`` around 1 in the weighted fit
    #: behind the test (:mod:`.gls`): the physical bound ``max_scale_deviation`` as a soft one.
    prior_scale_sigma: Annotated[float, Gt(0)] = 0.03
    #: ... and on the yaw around 0 (deg): the physical bound ``max_bias_rotation_deg``.
    prior_yaw_sigma_deg: float = 5.0
    #: False-rejection probability of the shape test.  Shape and position tests are two
    #: tests of one hypothesis: their sizes add (Bonferroni), so 0.005 + 0.005 keeps the
    #: single match's false-rejection probability at most 1 %, the size of the basic
    #: method's single test (equal footing in Fig. 1; the velocity term, stream only, adds
    #: at most ``alpha_position`` more).
    alpha_shape: float = 0.005
    #: False-rejection probability of the position (+ velocity) test.
    alpha_position: float = 0.005
    #: Use track velocities (the stream's tracks) in the position test.
    use_velocity: bool = True
    #: When the radars are registered, candidates the topology cannot decide (too few
    #: neighbours) are decided by the bias-compensated chi-square test (stage 2).
    registered_fallback: bool = True
    #: ... and so is a candidate that passes that test while every rival sharing one of its
    #: tracks costs at least this much more (chi-square excess; :mod:`.prompt`'s clear rule):
    #: once registered the absolute test is valid and unambiguous there, and the topology fit
    #: is spent only where it is not (0 disables) ...
    registered_clear_margin: float = 12.0
    #: ... and the candidate's tracks fly alone: no confirmed track of their own radar within
    #: this distance (m, horizontal) flying with them (velocity within
    #: ``registered_clear_velocity_mps``): a formation's tracks keep their topology fit.
    registered_clear_isolation_m: float = 2_000.0
    registered_clear_velocity_mps: float = 40.0
    #: ... and topology-accepted candidates must also pass it at this (loose) level.
    registered_consistency_alpha: float = 1e-4
    #: Once registered, a currently confirmed pair that passes the bias-compensated
    #: chi-square test (position + velocity, at ``alpha_position``) is kept by that test
    #: alone (stage 3, :meth:`SvdTopologyCorrelator.reverify`): no topology fit, and its two
    #: tracks leave the update's candidate references, so a kept pair meets no competitor
    #: (the book already lets a track be in one confirmed pair only; a challenger is decided
    #: once the pair fails the re-check).  A pair that fails is decided in full with the rest.
    maintain_confirmed: bool = True
    #: Before any fit, drop candidates whose velocities cannot belong to one target: speed
    #: difference and the heading difference beyond ``max_bias_rotation_deg`` (an azimuth bias
    #: rotates velocities too), chi-square with 2 dof against this false-rejection level.
    #: 0 disables.  Cheap, and it removes most candidates in dense traffic before the fit.
    velocity_prefilter_alpha: float = 1e-3
    #: Before registration, a candidate the topology cannot decide (too few neighbours) whose
    #: two tracks fly *alone* is accepted (:func:`lone_candidates`): it is the only candidate
    #: of each of its tracks within the candidate gate, no other track of either radar lies
    #: within ``lone_radius_m`` of its own (counting only tracks the velocity gate above lets
    #: be the same aircraft: one flying across is no rival), its velocities passed that gate, and
    #: the topology is no evidence against it (two neighbourhoods of ``min_matched`` or more
    #: with not one neighbour in common are).  Under the gate's own assumption (the biases
    #: displace a target by less than ``candidates.gate_m``) such an aircraft has no other
    #: possible counterpart; without the rule, aircraft further apart than the
    #: neighbourhood's ``max_radius_m`` (thin traffic, the ends of an overlap) are never
    #: paired, and no registration can start from them.
    #: A lone decision is never confirmed at its first look (:mod:`.prompt`): it enters the
    #: book's M of N like any other.  False: such candidates stay undecided.
    lone_pairs: bool = True
    #: ... and no other track of either radar within this (m, 3-D) of that radar's track: the
    #: candidate gate.  Uniqueness within the gate on both sides is what excludes a second
    #: aircraft (its track of either radar would be a rival); twice the gate also left
    #: unpaired the aircraft near the end of an overlap, where neighbours seen by one radar
    #: only are common (docs/correlation.md, "Lone aircraft": 52 % against 90 % of the
    #: common aircraft paired on one such scene, no false pair with either).
    lone_radius_m: float = 10_000.0
    #: ... and not within this many scans (of the slower radar) of the pair's first update,
    #: while the radars' tables fill: a track confirmed before its neighbours looks alone
    #: (the pair correlator's veto, which also leaves out a track with a tentative one of its
    #: radar within the gate).  On the national network, without it, 17 of 1 865 lone decisions
    #: in the pairs' first two updates were wrong, and their tentative pairs kept the radar
    #: pairs from settling for about 20 s (15 % more correlation updates in 120 s).
    lone_after_scans: float = 3.0


#: ``Decisions.extras["stage"]`` of a lone decision (:func:`lone_candidates`): before the
#: topology's 1 (its basis on the wire is the topology: too few neighbours to fit, and the
#: candidate the only one of its two tracks).
LONE_STAGE = 0.5


@dataclass(frozen=True)
class SvdMatchResult:
    """Single decisions of :func:`svd_match`, one entry per candidate."""

    accepted: BoolArray
    reason: NDArray[np.int8]
    chi2_shape: FloatArray
    dof_shape: FloatArray  # effective (non-integer for the regularised yaw fit)
    chi2_ref: FloatArray
    dof_ref: NDArray[np.int64]
    statistic: FloatArray
    cost: FloatArray
    rotation_weight: FloatArray
    scale: FloatArray
    yaw_rad: FloatArray
    matched: NDArray[np.int64]


def _mutual_nearest(cost: FloatArray, gate: float) -> NDArray[np.intp]:
    """For cost (P, Ka, Kb): B index paired with each A element by mutual nearest neighbour, -1 if none."""
    p, ka, kb = cost.shape
    if ka == 0 or kb == 0:
        return np.full((p, ka), -1, dtype=np.intp)
    jb = np.argmin(cost, axis=2)
    ia_of_b = np.argmin(cost, axis=1)
    # Flat indices instead of take_along_axis (same values, no broadcast index arrays).
    flat_b = jb + (np.arange(p) * kb)[:, None]
    back = ia_of_b.ravel()[flat_b]
    best = cost.reshape(p, ka * kb)[np.arange(p)[:, None], jb + (np.arange(ka) * kb)[None, :]]
    ok = (back == np.arange(ka)[None, :]) & (best <= gate)
    return np.where(ok, jb, -1).astype(np.intp)


def _merge_fit(base: SimilarityFit, sub: SimilarityFit, rows: NDArray[np.intp]) -> SimilarityFit:
    """``base`` with the entries ``rows`` replaced by ``sub``."""
    parts = []
    for name in ("rotation", "scale", "translation", "residual", "valid"):
        arr = getattr(base, name).copy()
        arr[rows] = getattr(sub, name)
        parts.append(arr)
    return SimilarityFit(*parts)


def _fit(
    x: FloatArray, y: FloatArray, w: FloatArray, prm: SvdTopologyParams
) -> tuple[SimilarityFit, FloatArray]:
    if prm.rotation_model == "full":
        fit = umeyama_batch(x, y, w, min_points=3)
        yaw = np.arctan2(fit.rotation[:, 1, 0], fit.rotation[:, 0, 0])
        return fit, yaw
    if prm.constrained_fit:
        return yaw_similarity_batch(
            x, y, w, 2, np.radians(prm.max_bias_rotation_deg), prm.max_scale_deviation, residual=False
        )
    return yaw_similarity_batch(x, y, w, min_points=2, residual=False)


def svd_match(
    pa: FloatArray,
    ca: FloatArray,
    ma: BoolArray,
    pb: FloatArray,
    cb: FloatArray,
    mb: BoolArray,
    m0: FloatArray,
    params: SvdTopologyParams | None = None,
    velocity: tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None = None,
    prior_yaw_rad: float = 0.0,
) -> SvdMatchResult:
    """Batched single decisions for P candidates.

    ``pa (P, K+1, 3)``: the A reference (index 0) and its neighbours in A's ENU frame,
    ``ca`` their covariances, ``ma`` the mask; likewise ``pb``, ``cb``, ``mb`` in B's frame.
    ``m0``: Eq. (3) ``R_B^-1 R_A``.  ``velocity``: optional ``(v_a, P_va, v_b, P_vb)`` of the
    references in their own ENU frames.  ``prior_yaw_rad``: a rotation applied to A before
    pairing (e.g. a registration estimate); included in the weight check.
    """
    prm = params or SvdTopologyParams()
    n_par = 7 if prm.rotation_model == "full" else 5
    min_matched = max(prm.min_matched, 3 if prm.rotation_model == "full" else 2)
    rot0 = yaw_matrix(np.array(prior_yaw_rad)) @ m0
    no_rot = bool(np.array_equal(rot0, np.eye(3)))  # e.g. A already turned by the caller (decide)
    if no_rot:
        pa_r, ca_r = pa, ca
    else:
        pa_r = pa @ rot0.T
        ca_r = congruence(rot0, ca)
    za = (pa_r - pa_r[:, :1, :])[:, 1:]
    zb = (pb - pb[:, :1, :])[:, 1:]
    man, mbn = ma[:, 1:], mb[:, 1:]
    can, cbn = ca_r[:, 1:], cb[:, 1:]
    n_a = man.sum(axis=1)
    n_b = mbn.sum(axis=1)
    invalid_pair = ~(man[:, :, None] & mbn[:, None, :])
    n_cand, kb = zb.shape[0], zb.shape[1]

    # 2(a) rotation-tolerant first pairing on the horizontal components.  All (P, Ka, Kb)
    # arrays are formed in place (few temporaries); the cost is the squared distance (the
    # mutual nearest neighbour and its gate are unchanged by the monotone square root).
    ra = np.hypot(za[..., 0], za[..., 1])
    rb = np.hypot(zb[..., 0], zb[..., 1])
    xa, ya = za[:, :, None, 0], za[:, :, None, 1]
    xb, yb = zb[:, None, :, 0], zb[:, None, :, 1]
    dot = xa * xb
    dot += ya * yb
    crs = xa * yb
    crs -= ya * xb
    dth = np.arctan2(crs, dot, out=crs)  # angle between the horizontal vectors
    np.abs(dth, out=dth)
    dth -= np.radians(prm.pairing_rotation_tolerance_deg)
    np.maximum(dth, 0.0, out=dth)
    dth *= 0.5
    tang = dth
    tang *= ra[:, :, None] + rb[:, None, :]
    tang *= tang
    cost0 = np.subtract(ra[:, :, None], rb[:, None, :], out=dot)
    cost0 *= cost0
    cost0 += tang
    dz = np.subtract(za[:, :, None, 2], zb[:, None, :, 2], out=tang)
    dz *= dz
    cost0 += dz
    cost0[invalid_pair] = np.inf
    pair = _mutual_nearest(cost0, prm.pairing_gate_m**2)
    flat_base = (np.arange(n_cand) * kb)[:, None]
    zb_flat = zb.reshape(-1, 3)

    def paired(pr: NDArray[np.intp]) -> tuple[FloatArray, FloatArray]:
        y = zb_flat[np.maximum(pr, 0) + flat_base]
        return y, (pr >= 0).astype(float)

    # 2(b-c) fit (reference included, it anchors the hypothesis) and re-pair with the fit.
    zeros = np.zeros((za.shape[0], 1, 3))
    ones = np.ones((za.shape[0], 1))
    y, w = paired(pair)
    fit, _ = _fit(
        np.concatenate([zeros, za], 1),
        np.concatenate([zeros, y], 1),
        np.concatenate([ones, w], 1),
        prm,
    )
    xt = fit.apply(za)
    xt = np.where(np.isfinite(xt), xt, za)
    cov_a = can.reshape(*can.shape[:2], 9)
    cov_b = cbn.reshape(*cbn.shape[:2], 9)

    def pair_sum(k: int) -> FloatArray:  # (P, Ka, Kb) sum of the A and B covariance entries k
        return np.add(cov_a[:, :, None, k], cov_b[:, None, :, k])

    # Horizontal Mahalanobis plus the vertical term (the small horizontal-vertical correlation
    # ignored): neighbours nearly above or below the reference pair by their heights.
    cost1 = mahalanobis2_h(
        xt[:, :, None, 0] - zb[:, None, :, 0],
        xt[:, :, None, 1] - zb[:, None, :, 1],
        pair_sum(0),
        pair_sum(1),
        pair_sum(4),
    )
    szz = pair_sum(8)
    szz[~(szz > 0)] = np.inf
    dz = np.subtract(xt[:, :, None, 2], zb[:, None, :, 2])
    dz *= dz
    dz /= szz
    cost1 += dz
    cost1[invalid_pair] = np.inf
    pair1 = _mutual_nearest(cost1, prm.repair_gate_chi2)
    pair = np.where(np.isfinite(fit.scale)[:, None], pair1, pair)

    # 3 + 2(d): neighbours-only fit, element chi-square, trim, refit.
    # The element covariances (Section 1.6) use the first fit's transform: trimming changes it
    # by a fraction of the yaw's own uncertainty, far too little to matter for a covariance.
    y, w = paired(pair)
    cy = cbn.reshape(-1, 3, 3)[np.maximum(pair, 0) + flat_base]
    fit, yaw = _fit(za, y, w, prm)
    c = np.where(np.isfinite(fit.scale), fit.scale, 1.0)
    rm = fit.rotation
    if prm.rotation_model == "full":
        rot_can = rm[:, None] @ can @ np.swapaxes(rm, 1, 2)[:, None]
    else:
        rot_can = yaw_congruence(np.where(np.isfinite(yaw), yaw, 0.0), can)
    s_k = (c**2)[:, None, None, None] * rot_can + cy  # Section 1.6
    s_inv, s_ok = inv3(s_k)
    y_safe = np.where(np.isfinite(y), y, 0.0)

    def element_chi2(f: SimilarityFit, rows: NDArray[np.intp] | slice) -> FloatArray:
        r = y_safe[rows] - f.apply(za[rows])
        return np.where(w[rows] > 0, quad3_large(np.where(np.isfinite(r), r, 0.0), s_inv[rows]), 0.0)

    q_k = element_chi2(fit, slice(None))
    for _ in range(2):  # trim and refit only the candidates whose elements changed
        w_new = w * (q_k <= prm.element_gate_chi2)
        ch = np.flatnonzero(np.any(w_new != w, axis=1))
        if ch.size == 0:
            break
        w = w_new
        sub_fit, sub_yaw = _fit(za[ch], y[ch], w[ch], prm)
        fit = _merge_fit(fit, sub_fit, ch)
        yaw = yaw.copy()
        yaw[ch] = sub_yaw
        q_k[ch] = element_chi2(sub_fit, ch)
    c = np.where(np.isfinite(fit.scale), fit.scale, 1.0)
    rm = fit.rotation
    m = (w > 0).sum(axis=1)
    sing = np.any((w > 0) & ~s_ok, axis=1)

    # 6. The test statistics come from the covariance-weighted fit (:mod:`.gls`) of the same
    # paired elements, started from nothing but the physical prior: only the weighted minimum
    # of the weighted norm is chi-square distributed (the unweighted SVD fit above decides the
    # pairing, the trimming and nothing else).
    if prm.rotation_model == "full":
        # The paper's 3-D model, kept for reference: unweighted statistics, leverage approximation.
        chi2_shape = (q_k * (w > 0)).sum(axis=1)
        dof_shape = np.maximum(3.0 * m - n_par, 1.0)
        wsum = np.maximum(w.sum(axis=1), 1.0)
        xbar = np.einsum("pk,pkd->pd", w, za) / wsum[:, None]
        spread = np.einsum("pk,pk->p", w, ((za - xbar[:, None, :])[..., :2] ** 2).sum(-1))
        tiny = np.finfo(float).tiny
        h = 1.0 / wsum + np.where(
            spread > tiny, (xbar[:, :2] ** 2).sum(-1) / np.where(spread > tiny, spread, 1.0), 0.0
        )
        cov_t = h[:, None, None] * np.einsum("pk,pkij->pij", w, s_k) / wsum[:, None, None]
        t_fit = fit.translation
        fit_ok = fit.valid
    else:
        gfit = similarity_gls_batch(
            za,
            np.where(np.isfinite(y), y, 0.0),
            w,
            s_inv,
            prm.prior_scale_sigma,
            np.radians(prm.prior_yaw_sigma_deg),
        )
        fit_ok = gfit.valid
        c = np.where(fit_ok, gfit.scale, 1.0)
        yaw = np.where(fit_ok, gfit.yaw, 0.0)
        rm = yaw_matrix(yaw)
        chi2_shape = np.where(fit_ok, gfit.q_residual + gfit.q_prior, 0.0)
        dof_shape = np.maximum(3.0 * m - np.where(fit_ok, gfit.df_model, 0.0), 0.5)
        cov_t = np.where(fit_ok[:, None, None], gfit.cov[:, 2:, 2:], 0.0)
        t_fit = gfit.translation

    # Position test on the translation t (Eq. 4): both references sit at the origin of their
    # topology vectors, so t is the A reference predicted from the neighbours minus the B
    # reference; its covariance is the references' own noise plus the fit's (GLS block).
    s_0 = (c**2)[:, None, None] * rm @ ca_r[:, 0] @ np.swapaxes(rm, 1, 2) + cb[:, 0]
    t = np.where(np.isfinite(t_fit), t_fit, 0.0)
    chi2_ref, ref_ok = mahalanobis3(t, s_0 + cov_t)
    dof_ref = np.full(len(m), 3, dtype=np.int64)
    chi2_vel = np.zeros(len(m))
    vel_ok = np.ones(len(m), dtype=bool)
    if velocity is not None and prm.use_velocity:
        va, cva, vb, cvb = velocity
        va_r = va if no_rot else va @ rot0.T
        cva_r = cva if no_rot else congruence(rot0, cva)
        rv = vb - c[:, None] * (rm @ va_r[..., None])[..., 0]
        chi2_vel, sv_ok = mahalanobis3(rv, (c**2)[:, None, None] * rm @ cva_r @ np.swapaxes(rm, 1, 2) + cvb)
        vel_ok = chi2_vel <= chi2_upper(prm.alpha_position, 3)
        dof_ref = dof_ref + 3 * sv_ok
    # Section 1.5 on the unknown part of the rotation: M0 of Eq. (3) is known exactly from the
    # sites, so the check asks whether the fitted bias rotation (times any prior) is near I.
    weight = rotation_weight(rm @ yaw_matrix(np.array(prior_yaw_rad)))

    few = (
        (m < min_matched)
        | (np.minimum(n_a, n_b) < min_matched)
        | (m < prm.min_match_fraction * np.minimum(n_a, n_b))
    )
    degenerate = ~fit.valid | ~fit_ok | sing | ~ref_ok | ~np.all(np.isfinite(t_fit), axis=1)
    bad_weight = weight < prm.min_rotation_weight
    # A hard scale bound only for the paper's free 3-D fit: in the yaw model the bound is the
    # prior of the weighted fit, and with 2-10 neighbours at <= 10 km the scale's own
    # uncertainty (1-4 %) exceeds it, so a hard cut would reject true pairs on noise.
    bad_scale = (prm.rotation_model == "full") & (np.abs(c - 1.0) > prm.max_scale_deviation * (1.0 + 1e-9))
    bad_shape = chi2_shape > chi2_upper(prm.alpha_shape, dof_shape)
    bad_pos = chi2_ref > chi2_upper(prm.alpha_position, 3)
    reason = np.select(
        [few, degenerate, bad_weight, bad_scale, bad_shape, bad_pos, ~vel_ok],
        [
            Reason.TOO_FEW_NEIGHBOURS,
            Reason.DEGENERATE_FIT,
            Reason.ROTATION_WEIGHT,
            Reason.SCALE,
            Reason.SHAPE_TEST,
            Reason.POSITION_TEST,
            Reason.VELOCITY_TEST,
        ],
        default=Reason.ACCEPTED,
    ).astype(np.int8)
    no_dec = few | degenerate
    total = chi2_shape + chi2_ref + chi2_vel
    statistic = np.where(no_dec, np.nan, total / (dof_shape + dof_ref))
    cost = np.where(no_dec, np.inf, (chi2_ref + chi2_vel - dof_ref) + (chi2_shape - dof_shape))
    return SvdMatchResult(
        accepted=reason == Reason.ACCEPTED,
        reason=reason,
        chi2_shape=np.where(no_dec, np.nan, chi2_shape),
        dof_shape=dof_shape,
        chi2_ref=np.where(no_dec, np.nan, chi2_ref + chi2_vel),
        dof_ref=dof_ref.astype(np.int64),
        statistic=statistic,
        cost=cost,
        rotation_weight=np.where(degenerate, np.nan, weight),
        scale=np.where(degenerate, np.nan, c),
        yaw_rad=np.where(degenerate, np.nan, yaw + prior_yaw_rad),
        matched=m.astype(np.int64),
    )


def _join_results(parts: list[tuple[NDArray[np.intp], SvdMatchResult]], n: int) -> SvdMatchResult:
    """One :class:`SvdMatchResult` of ``n`` candidates from results of index groups."""
    if len(parts) == 1 and np.array_equal(parts[0][0], np.arange(n)):
        return parts[0][1]
    cols = {}
    for name in SvdMatchResult.__dataclass_fields__:
        first = getattr(parts[0][1], name)
        out = np.empty((n, *first.shape[1:]), dtype=first.dtype)
        for idx, r in parts:
            out[idx] = getattr(r, name)
        cols[name] = out
    return SvdMatchResult(**cols)


def _in_group(snap: PredictedTracks, rows: NDArray[np.intp], prm: SvdTopologyParams) -> BoolArray:
    """Which of ``rows`` have a track of the same snapshot near them flying with them."""
    up = snap.site.rotation[:, 2] if snap.site is not None else None
    none = np.zeros(len(snap), dtype=bool)
    return companions(
        snap.position,
        snap.velocity,
        up,
        rows,
        prm.registered_clear_isolation_m,
        prm.registered_clear_velocity_mps,
        none,
    )


def compensated_chi2(
    a: PredictedTracks,
    b: PredictedTracks,
    ia: NDArray[np.intp],
    ib: NDArray[np.intp],
    context: DecisionContext,
    prm: SvdTopologyParams,
) -> tuple[FloatArray, BoolArray, int]:
    """Absolute chi-square of pairs ``(ia[k], ib[k])`` of bias-compensated snapshots (stages 2, 3).

    :func:`service.correlation.nearest.chi2_pairs` with ``S = P_a + P_b`` plus the covariance
    the registration's own uncertainty adds on each side (``context.registration_cov_*``, as
    :func:`~service.correlation.registration.compensate` returns it), and with ``use_velocity``
    the velocity term (``P_va + P_vb``).  Returns the chi-square, the non-singular flag, the dof.
    """
    q_pos, q_vel, ok = chi2_pairs(a, b, ia, ib, context.registration_cov_a, context.registration_cov_b)
    if prm.use_velocity:
        return q_pos + q_vel, ok, 6
    return q_pos, ok, 3


#: The extras of :meth:`SvdTopologyCorrelator.reverify`: each pair's compensated chi-square
#: and its degrees of freedom (:mod:`.swap`).
CHI2 = "chi2"
DOF = "dof"

#: The topology match of no candidate.
_NO_MATCH = SvdMatchResult(
    accepted=np.zeros(0, dtype=bool),
    reason=np.zeros(0, dtype=np.int8),
    chi2_shape=np.zeros(0),
    dof_shape=np.zeros(0),
    chi2_ref=np.zeros(0),
    dof_ref=np.zeros(0, dtype=np.int64),
    statistic=np.zeros(0),
    cost=np.zeros(0),
    rotation_weight=np.zeros(0),
    scale=np.zeros(0),
    yaw_rad=np.zeros(0),
    matched=np.zeros(0, dtype=np.int64),
)

#: Up to this many candidates are matched in one group (see ``decide``).
_ONE_GROUP = 64


def _used_rows(nbr: NDArray[np.intp], refs: NDArray[np.intp]) -> NDArray[np.intp]:
    """The references ``refs`` and every neighbour of theirs (rows of ``nbr``), ascending."""
    nb = nbr[refs]
    return np.unique(np.concatenate([refs, nb[nb >= 0]]))


def _turned_rows(rot: FloatArray, cov: FloatArray, rows: NDArray[np.intp]) -> FloatArray:
    """``rot P rot^T`` of the stack ``cov`` at ``rows`` (identity elsewhere: never read)."""
    if 2 * len(rows) >= cov.shape[0]:
        return congruence(rot, cov)
    out = np.broadcast_to(np.eye(3), cov.shape).copy()
    out[rows] = congruence(rot, cov[rows])
    return out


def _reference_candidates(
    a: PredictedTracks, b: PredictedTracks, context: DecisionContext, gate_m: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Candidate pairs among the context's reference rows (all rows when it names none), (i, j) order."""
    if context.reference_a is None and context.reference_b is None:
        ia, ib, _ = candidate_pairs(a.position, b.position, gate_m)
        return ia, ib
    ra = np.arange(len(a)) if context.reference_a is None else np.sort(context.reference_a)
    rb = np.arange(len(b)) if context.reference_b is None else np.sort(context.reference_b)
    ia, ib, _ = candidate_pairs(a.position[ra], b.position[rb], gate_m)
    return ra[ia].astype(np.intp), rb[ib].astype(np.intp)  # ascending maps keep the (i, j) order


def count_within(points: FloatArray, queries: FloatArray, radius_m: float) -> NDArray[np.intp]:
    """How many of ``points`` lie within ``radius_m`` of each of ``queries`` (3-D): by all
    distances when there are few of them, else by a k-d tree (the same counts)."""
    if len(queries) == 0 or len(points) == 0:
        return np.zeros(len(queries), dtype=np.intp)
    if len(queries) * len(points) <= BRUTE_FORCE_MAX_DISTANCES:
        d2 = np.zeros((len(queries), len(points)))
        for c in range(3):  # per coordinate: no (q, n, 3) temporary
            d2 += (points[None, :, c] - queries[:, c, None]) ** 2
        return np.asarray((d2 <= radius_m * radius_m).sum(axis=1), dtype=np.intp)
    found = cKDTree(points).query_ball_point(queries, radius_m, return_length=True)
    return np.asarray(found, dtype=np.intp)


def lone_candidates(
    a: PredictedTracks,
    b: PredictedTracks,
    ia: NDArray[np.intp],
    ib: NDArray[np.intp],
    matched: NDArray[np.int64],
    prm: SvdTopologyParams,
) -> BoolArray:
    """Which candidates ``(ia[k], ib[k])`` fly alone (``SvdTopologyParams.lone_pairs``): each
    track the other's only candidate within ``candidates.gate_m`` (among every track of the
    other radar, not only the update's references), no other track of its own radar within
    ``lone_radius_m``, each counting only tracks of a velocity that could be the track's own
    (:func:`_rivals`), and a topology that is no evidence against them: ``matched[k]`` (the
    neighbours its fit paired) at least one, or fewer than ``min_matched`` neighbours on one
    side (nothing to compare).  Two sequences of ``min_matched`` or more with not one
    neighbour in common are two different neighbourhoods: two aircraft, each seen by one
    radar.  Each count includes the track itself (its own radar) or its candidate (the
    other's).  The velocities passed the velocity gate before (``velocity_prefilter_alpha``)."""
    gate, radius = prm.candidates.gate_m, prm.lone_radius_m
    assert a.site is not None and b.site is not None
    m0 = b.site.rotation.T @ a.site.rotation  # Eq. (3): A's orientation into B's
    eye = np.eye(3)
    ok = (_rivals(b, a, ia, gate, m0, prm) == 1) & (_rivals(a, b, ib, gate, m0.T, prm) == 1)
    ok &= (_rivals(a, a, ia, radius, eye, prm) == 1) & (_rivals(b, b, ib, radius, eye, prm) == 1)
    if _by_velocity(prm):  # each count of 1 must be the candidate itself: its tracks agree both ways
        ok &= _velocity_compatible(a, b, ia, ib, m0, prm) & _velocity_compatible(b, a, ib, ia, m0.T, prm)
    rows = np.flatnonzero(ok & (matched == 0))
    if rows.size:  # (few: the neighbourhoods of these tracks only)
        ua, ra = np.unique(ia[rows], return_inverse=True)
        ub, rb = np.unique(ib[rows], return_inverse=True)
        na = (neighbourhoods(a.enu, prm.topology, rows=ua)[ua] >= 0).sum(axis=1)[ra]
        nb = (neighbourhoods(b.enu, prm.topology, rows=ub)[ub] >= 0).sum(axis=1)[rb]
        ok[rows] = np.minimum(na, nb) < prm.min_matched
    return ok


def _rivals(
    points: PredictedTracks,
    query: PredictedTracks,
    rows: NDArray[np.intp],
    radius_m: float,
    m0: FloatArray,
    prm: SvdTopologyParams,
) -> NDArray[np.intp]:
    """Per track ``rows`` of ``query``: the tracks of ``points`` within ``radius_m`` (3-D) of it
    that could be the same aircraft, by the rotation-tolerant velocity gate
    (``velocity_prefilter_alpha``; ``m0`` turns ``query``'s ENU orientation into ``points``').
    A track flying another velocity is no rival: the gate already keeps it out of every
    candidate of the track, so two aircraft crossing, or passing, a few kilometres apart are
    each still alone.  A track whose velocity is uncertain (young) passes the gate easily,
    and so is counted."""
    if not _by_velocity(prm):
        return count_within(points.position, query.position[rows], radius_m)
    qi, pj, _ = candidate_pairs(query.position[rows], points.position, radius_m)
    same = _velocity_compatible(query, points, rows[qi], pj, m0, prm)
    return np.bincount(qi[same], minlength=len(rows)).astype(np.intp)


def _by_velocity(prm: SvdTopologyParams) -> bool:
    """The method's velocity gate is on (the prefilter of :meth:`SvdTopologyCorrelator.decide`)."""
    return prm.use_velocity and prm.velocity_prefilter_alpha > 0


def _velocity_compatible(
    a: PredictedTracks,
    b: PredictedTracks,
    ia: np.ndarray,
    ib: np.ndarray,
    m0: FloatArray,
    prm: SvdTopologyParams,
) -> BoolArray:
    """Rotation-tolerant velocity gate of candidates (see ``velocity_prefilter_alpha``)."""
    va = a.enu_velocity[ia] @ m0.T
    vb = b.enu_velocity[ib]
    sa = np.hypot(va[:, 0], va[:, 1])
    sb = np.hypot(vb[:, 0], vb[:, 1])
    dot = va[:, 0] * vb[:, 0] + va[:, 1] * vb[:, 1]
    crs = va[:, 0] * vb[:, 1] - va[:, 1] * vb[:, 0]
    excess = np.maximum(np.abs(np.arctan2(crs, dot)) - np.radians(prm.max_bias_rotation_deg), 0.0)
    tang = excess * 0.5 * (sa + sb)
    cva = a.vel_cov[ia]
    cvb = b.vel_cov[ib]
    var = (
        0.5 * (cva[:, 0, 0] + cva[:, 1, 1] + cva[:, 2, 2] + cvb[:, 0, 0] + cvb[:, 1, 1] + cvb[:, 2, 2]) / 1.5
    )
    ok = np.isfinite(var) & (var > 0)
    q = ((sa - sb) ** 2 + tang**2) / np.where(ok, var, 1.0)
    return ~ok | (q <= chi2_upper(prm.velocity_prefilter_alpha, 2))


class SvdTopologyCorrelator(CorrelationMethod):
    """Method ``svd-topology``: the topology match above, plus, once registered, stage 2."""

    name = "svd-topology"
    requires_sites = True

    def __init__(self, params: SvdTopologyParams | None = None) -> None:
        self.params = params or SvdTopologyParams()

    def decide(self, a: PredictedTracks, b: PredictedTracks, context: DecisionContext) -> Decisions:
        prm = self.params
        if a.site is None or b.site is None:
            raise ValueError("svd-topology needs two radar sites")
        # Only the reference rows form candidates; every row stays a neighbour (the topology
        # sequence of a reference is its whole neighbourhood, Section 2 step 1).
        ia, ib = _reference_candidates(a, b, context, prm.candidates.gate_m)
        n = len(ia)
        if n == 0:
            return Decisions.empty()
        dof = 3 + (3 if prm.use_velocity else 0)
        q = np.full(n, np.nan)
        ok = np.zeros(n, dtype=bool)
        run = np.ones(n, dtype=bool)
        settled = np.zeros(n, dtype=bool)
        if context.registered:
            # Stage 2 gate first: on compensated positions (+ velocities) a candidate failing the
            # loose consistency test could not be accepted anyway, so it skips the topology fit.
            q, ok, dof = compensated_chi2(a, b, ia, ib, context, prm)
            if prm.registered_consistency_alpha > 0:
                run = ok & (q <= chi2_upper(prm.registered_consistency_alpha, dof))
            if prm.registered_clear_margin > 0:
                # ... and a clear one is settled by it (stage 2, below)
                passes = ok & (q <= chi2_upper(prm.alpha_position, dof))
                cost2 = np.where(ok, q - dof, np.inf)
                settled = clear_of_rivals(ia, ib, cost2, passes, prm.registered_clear_margin)
                # ... unless a track flies in a group (a formation), where the margin can be chance
                settled[settled] &= ~_in_group(a, ia[settled], prm) & ~_in_group(b, ib[settled], prm)
                # a rival of a clear candidate loses to it by the margin: no fit needed either
                settled |= np.isin(ia, ia[settled]) | np.isin(ib, ib[settled])
                run &= ~settled
        m0 = b.site.rotation.T @ a.site.rotation  # Eq. (3)
        if _by_velocity(prm):
            run &= _velocity_compatible(a, b, ia, ib, m0, prm)
        sub = np.flatnonzero(run)
        res = self._topology(a, b, ia[sub], ib[sub], m0) if sub.size else _NO_MATCH

        def full(x: np.ndarray, fill: float) -> np.ndarray:
            out = np.full((n, *x.shape[1:]), fill, dtype=x.dtype)
            out[sub] = x
            return out

        accepted = full(res.accepted, False)
        reason = full(res.reason, Reason.GATE)
        cost = full(res.cost, np.inf)
        statistic = full(res.statistic, np.nan)
        stage = np.where(accepted, 1.0, 0.0)
        if context.registered and prm.registered_fallback:
            undecided = np.isin(reason, [Reason.TOO_FEW_NEIGHBOURS, Reason.DEGENERATE_FIT]) | settled
            passed = undecided & ok & (q <= chi2_upper(prm.alpha_position, dof))
            accepted |= passed
            reason = np.where(
                passed,
                np.int8(Reason.ACCEPTED),
                np.where(undecided & ~passed & ok, np.int8(Reason.GATE), reason),
            )
            cost = np.where(passed, q - dof, cost)
            statistic = np.where(passed, q / dof, statistic)
            stage = np.where(passed, 2.0, stage)
        matched = full(res.matched, 0)
        if prm.lone_pairs and not context.registered:
            open_ = np.flatnonzero(~accepted & (reason == Reason.TOO_FEW_NEIGHBOURS))
            if open_.size:
                hit = open_[lone_candidates(a, b, ia[open_], ib[open_], matched[open_], prm)]
                accepted[hit] = True
                reason[hit] = Reason.ACCEPTED
                # (no test statistic: the decision rests on the candidate's being the only one)
                cost[hit] = 0.0
                stage[hit] = LONE_STAGE
        # A stage 2 decision used no topology fit, a lone one no accepted fit: no rotation
        # weight or scale to report; ``neighbors`` stays what the fit matched (0 in stage 2).
        no_fit = (stage >= 2) | (stage == LONE_STAGE)
        dec = Decisions.build(
            ia,
            ib,
            accepted=accepted,
            reason=reason.astype(np.int8),
            cost=cost,
            statistic=statistic,
            rotation_weight=np.where(no_fit, np.nan, full(res.rotation_weight, np.nan)),
            scale=np.where(no_fit, np.nan, full(res.scale, np.nan)),
            neighbors=np.where(stage >= 2, 0, matched),
        )
        dec.extras["stage"] = stage
        dec.extras["yaw_rad"] = full(res.yaw_rad, np.nan)
        return dec

    def _topology(
        self,
        a: PredictedTracks,
        b: PredictedTracks,
        ra_sub: NDArray[np.intp],
        rb_sub: NDArray[np.intp],
        m0: FloatArray,
    ) -> SvdMatchResult:
        """The topology match (steps 1-6 of the module docstring) of the candidates
        ``(ra_sub[k], rb_sub[k])``."""
        prm = self.params
        assert b.site is not None
        # Neighbourhoods of the candidate references only; A is turned into B's orientation
        # (M0 of Eq. 3) once per track here rather than once per candidate element in
        # svd_match, which is then told that no rotation is left (M0 = I).
        ua, ub = np.unique(ra_sub), np.unique(rb_sub)
        nbr_a = neighbourhoods(a.enu, prm.topology, rows=ua)
        nbr_b = neighbourhoods(b.enu, prm.topology, rows=ub)
        # Covariances in B's ENU orientation, of the rows the references and their neighbours
        # use only (a registered update has few references among many tracks).  For A that is
        # M0 R_A^T P R_A M0^T = R_B^T P R_B (Eq. 3), as for B.
        rot_b = b.site.rotation.T
        enu_a = a.enu @ m0.T
        cov_a = _turned_rows(rot_b, a.pos_cov, _used_rows(nbr_a, ua))
        cov_b = _turned_rows(rot_b, b.pos_cov, _used_rows(nbr_b, ub))
        # Candidates are matched in (at most two) groups by sequence length: most references
        # have ``min_neighbours`` neighbours, a few more, and the per-candidate arrays of a
        # group are only as wide as its longest sequence.  Per-candidate results do not depend
        # on the grouping; a few candidates are one group (one call costs less than two).
        width = np.maximum((nbr_a[ra_sub] >= 0).sum(axis=1), (nbr_b[rb_sub] >= 0).sum(axis=1))
        common = int(np.bincount(width).argmax()) if len(width) else 0
        if len(width) <= _ONE_GROUP:
            common = int(width.max(initial=0))
        groups = [g for g in (np.flatnonzero(width <= common), np.flatnonzero(width > common)) if g.size]
        parts = []
        for g in groups or [np.arange(len(ra_sub))]:
            ga, gb = ra_sub[g], rb_sub[g]
            pa, ca, ma = gather_points(enu_a, cov_a, nbr_a, ga, trim=True)
            pb, cb, mb = gather_points(b.enu, cov_b, nbr_b, gb, trim=True)
            vel = (
                a.enu_velocity[ga] @ m0.T,
                congruence(rot_b, a.vel_cov[ga]),
                b.enu_velocity[gb],
                congruence(rot_b, b.vel_cov[gb]),
            )
            parts.append((g, svd_match(pa, ca, ma, pb, cb, mb, np.eye(3), prm, velocity=vel)))
        return _join_results(parts, len(ra_sub))

    def reverify(
        self,
        a: PredictedTracks,
        b: PredictedTracks,
        ia: NDArray[np.intp],
        ib: NDArray[np.intp],
        context: DecisionContext,
    ) -> Decisions | None:
        """Stage 3: re-check the confirmed pairs ``(ia[k], ib[k])`` by :func:`compensated_chi2` alone.

        Only once registered (the absolute test needs compensated snapshots) and with
        ``maintain_confirmed``; else None.  A pair passing at ``alpha_position`` is accepted
        with ``cost = chi2 - dof`` and ``statistic = chi2 / dof`` (the stage 2 convention);
        ``rotation_weight``, ``scale`` are NaN and ``neighbors`` 0: no topology was matched.
        The extras ``CHI2`` and ``DOF`` hold the chi-square (NaN: singular) and its degrees of
        freedom (:mod:`.swap`).
        """
        prm = self.params
        if not (context.registered and prm.maintain_confirmed):
            return None
        q, ok, dof = compensated_chi2(a, b, ia, ib, context, prm)
        passed = ok & (q <= chi2_upper(prm.alpha_position, dof))
        reason = np.where(passed, Reason.ACCEPTED, np.where(ok, Reason.GATE, Reason.DEGENERATE_FIT)).astype(
            np.int8
        )
        dec = Decisions.build(ia, ib, accepted=passed, reason=reason, cost=q - dof, statistic=q / dof)
        dec.extras["stage"] = np.full(len(ia), 3.0)
        # the chi-square and its degrees of freedom, for the caller's swap test (:mod:`.swap`)
        dec.extras[CHI2] = np.where(ok, q, np.nan)
        dec.extras[DOF] = np.full(len(ia), float(dof))
        return dec
