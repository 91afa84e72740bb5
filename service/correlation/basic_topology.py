"""The basic topology-sequence method with stepwise rotation (method ``basic-topology``).

The paper's baseline (its reference [9], Wu, Ren, Liu 2009, as summarised in the SVD
paper's abstract and Section 3): the topology sequences (neighbour vectors sorted by
increasing azimuth, Section 1.2) of a candidate pair are compared element by element --
element ``i`` of one sequence with element ``i`` of the other -- after correcting A's sequence
for every hypothesis of a grid of systematic errors: azimuth in steps of
``azimuth_step_deg`` (0.25 deg) over +-``max_azimuth_bias_deg`` and range in steps of
``range_step_m`` (50 m) over +-``max_range_bias_m``.  A range bias ``rho`` moves the vector
to neighbour ``i`` by ``rho (u_i - u_0)`` (``u`` = line-of-sight unit vectors), an azimuth
bias rotates it about the vertical.  The work grows linearly with the azimuth span: the
Python loop over hypotheses below *is* the method (vectorised over candidates only).

Element order is fragile: sequences must have equal length (otherwise no decision) and
neighbours at nearly equal azimuth may swap order; cyclic shifts of up to ``max_shift``
elements are tried.  Test: ``chi2 = sum_i r_i^T S_i^-1 r_i`` with ``S_i`` the sum of the
four position covariances involved (correlations through the reference ignored, as in the
basic method), chi-square with ``3 n`` degrees of freedom at level ``alpha``, minimised over
hypotheses and shifts.  The residual covariance is the joint one: the two references' noise
is common to all elements (``joint_covariance``), so the statistic is chi-square(3 n) at the
true hypothesis -- the same calibrated test as ``svd-topology`` (whose fit removes 3 more
parameters).  For the paper's Section 3 the search spans just the differential bias of the
scenario (:func:`search_span`: +-0.25 deg, +-200 m for 0.1 deg / 100 m per radar).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

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
from service.correlation.topology import TopologyParams, gather_points, neighbourhoods, sort_by_azimuth
from service.correlation.umeyama import yaw_matrix
from service.linalg import inv3, quad3


@dataclass(frozen=True)
class BasicTopologyParams:
    """Search grid and test of the basic method."""

    topology: TopologyParams = field(
        default_factory=lambda: TopologyParams(min_neighbours=0, max_radius_m=10_000.0)
    )
    candidates: CandidateParams = field(default_factory=CandidateParams)
    #: Azimuth step of the rotation search (the paper's 0.25 deg).
    azimuth_step_deg: float = 0.25
    #: Half-width of the azimuth search: the differential azimuth bias it must tolerate.
    max_azimuth_bias_deg: float = 1.0
    #: Range step of the search (the paper's 50 m).
    range_step_m: float = 50.0
    #: Half-width of the range search.
    max_range_bias_m: float = 200.0
    #: Cyclic shifts of the azimuth order tried (a rotation can move the sequence's start).
    max_shift: int = 1
    #: Minimum sequence length for a decision.
    min_neighbours: int = 2
    #: False-rejection probability of the chi-square test (1 %: the same total size as the
    #: svd-topology shape + position tests, so Fig. 1 compares the methods at equal size).
    alpha: float = 0.01
    #: Test with the joint covariance of the sequence: the two references' noise is common to
    #: every element ``z_i = x_i - x_0``.  Ignoring it (False) keeps each element's marginal
    #: covariance right but makes the sum's tail heavier than chi-square(3 n), i.e. a test of
    #: larger size than stated (measured: ~2x on the Fig. 1 scenario).
    joint_covariance: bool = True


def search_span(differential_azimuth_deg: float, differential_range_m: float) -> BasicTopologyParams:
    """Parameters whose search just covers the given differential biases on the paper's grid.

    The paper steps the rotation by 0.25 deg and the range by 50 m (Section 3) over the bias the
    method must tolerate; the span is rounded up to whole steps (at least one step each side).
    """
    d = BasicTopologyParams()
    az = max(np.ceil(differential_azimuth_deg / d.azimuth_step_deg - 1e-9), 1.0) * d.azimuth_step_deg
    rr = max(np.ceil(differential_range_m / d.range_step_m - 1e-9), 1.0) * d.range_step_m
    return BasicTopologyParams(max_azimuth_bias_deg=float(az), max_range_bias_m=float(rr))


@dataclass(frozen=True)
class BasicMatchResult:
    accepted: BoolArray
    reason: NDArray[np.int8]
    chi2: FloatArray
    dof: NDArray[np.int64]
    azimuth_deg: FloatArray
    range_m: FloatArray
    hypotheses: int


def _sequence_chi2(
    r: FloatArray, valid: BoolArray, d_inv: FloatArray, common_inv: FloatArray | None
) -> FloatArray:
    """Chi-square of element residuals ``r (P, K, 3)``.

    With ``common_inv`` (joint covariance): every element carries the two references' noise
    ``C0`` as well as its own ``D_i``, ``Cov = blockdiag(D_i) + 1 1^T (x) C0``; by the
    Woodbury identity ``r^T Cov^-1 r = sum_i r_i^T D_i^-1 r_i - u^T (C0^-1 + sum_i D_i^-1)^-1 u``
    with ``u = sum_i D_i^-1 r_i`` (``common_inv`` is that middle inverse).  Without it, the
    per-element sum with ``d_inv`` already including ``C0`` (correlations ignored).
    """
    rr = np.where(valid[..., None], r, 0.0)
    q = np.where(valid, quad3(rr, d_inv), 0.0).sum(1)
    if common_inv is None:
        return q
    u = (d_inv @ rr[..., None])[..., 0].sum(1)
    return q - quad3(u, common_inv)


def search_grid(params: BasicTopologyParams) -> tuple[FloatArray, FloatArray]:
    """The azimuth (deg) and range (m) hypotheses of the step search."""
    na = int(np.floor(params.max_azimuth_bias_deg / params.azimuth_step_deg + 1e-9))
    nr = int(np.floor(params.max_range_bias_m / params.range_step_m + 1e-9))
    az = np.arange(-na, na + 1, dtype=np.float64) * float(params.azimuth_step_deg)
    rr = np.arange(-nr, nr + 1, dtype=np.float64) * float(params.range_step_m)
    return az.astype(np.float64), rr.astype(np.float64)


def basic_match(
    pa: FloatArray,
    ca: FloatArray,
    ma: BoolArray,
    pb: FloatArray,
    cb: FloatArray,
    mb: BoolArray,
    m0: FloatArray,
    params: BasicTopologyParams | None = None,
) -> BasicMatchResult:
    """Batched basic decisions; same inputs as :func:`service.correlation.svd_topology.svd_match`."""
    prm = params or BasicTopologyParams()
    pa_r = pa @ m0.T
    ca_r = m0 @ ca @ m0.T
    za = (pa_r - pa_r[:, :1])[:, 1:]
    zb = (pb - pb[:, :1])[:, 1:]
    man, mbn = ma[:, 1:], mb[:, 1:]
    oa = sort_by_azimuth(za, man)
    ob = sort_by_azimuth(zb, mbn)
    za = np.take_along_axis(za, oa[..., None], 1)
    zb = np.take_along_axis(zb, ob[..., None], 1)
    can = np.take_along_axis(ca_r[:, 1:], oa[..., None, None], 1)
    cbn = np.take_along_axis(cb[:, 1:], ob[..., None, None], 1)
    los = pa_r / np.maximum(np.linalg.norm(pa_r, axis=-1, keepdims=True), 1.0)
    dlos = np.take_along_axis((los - los[:, :1])[:, 1:], oa[..., None], 1)
    n_a = man.sum(1)
    n_b = mbn.sum(1)
    n = n_b
    p, k = mbn.shape
    valid_b = np.take_along_axis(mbn, ob, 1)  # valid elements come first after sorting
    s0 = ca_r[:, 0] + cb[:, 0]
    shifts = range(-prm.max_shift, prm.max_shift + 1)
    ar = np.arange(k)[None, :]
    partner = {s: np.mod(ar + s, np.maximum(n, 1)[:, None]) for s in shifts}
    inv: dict[int, FloatArray] = {}
    common: dict[int, FloatArray] = {}
    sing = np.zeros(p, dtype=bool)
    s0_inv, s0_ok = inv3(s0)
    sing |= ~s0_ok
    for s in shifts:
        ca_s = np.take_along_axis(can, partner[s][..., None, None], 1)
        if prm.joint_covariance:
            si, ok = inv3(ca_s + cbn)
            si = np.where(valid_b[..., None, None], si, 0.0)
            e_inv, e_ok = inv3(s0_inv + si.sum(axis=1))
            common[s] = e_inv
            sing |= ~e_ok
        else:
            si, ok = inv3(ca_s + cbn + s0[:, None])
        inv[s] = si
        sing |= np.any(valid_b & ~ok, axis=1)
    az_grid, r_grid = search_grid(prm)
    best = np.full(p, np.inf)
    best_az = np.zeros(p)
    best_r = np.zeros(p)
    for az in az_grid:  # the step search: cost linear in the azimuth span
        rot = yaw_matrix(np.array(-np.radians(az)))
        for rr in r_grid:
            zh = (za + rr * dlos) @ rot.T
            for s in shifts:
                zs = np.take_along_axis(zh, partner[s][..., None], 1)
                q = _sequence_chi2(zb - zs, valid_b, inv[s], common.get(s))
                better = q < best
                best = np.where(better, q, best)
                best_az = np.where(better, az, best_az)
                best_r = np.where(better, rr, best_r)
    dof = 3 * n
    few = np.minimum(n_a, n_b) < prm.min_neighbours
    unequal = n_a != n_b
    passed = best <= chi2_upper(prm.alpha, np.maximum(dof, 1))
    reason = np.select(
        [few, unequal, sing, ~passed],
        [Reason.TOO_FEW_NEIGHBOURS, Reason.UNEQUAL_LENGTH, Reason.DEGENERATE_FIT, Reason.SHAPE_TEST],
        default=Reason.ACCEPTED,
    ).astype(np.int8)
    no_dec = few | unequal | sing
    return BasicMatchResult(
        accepted=reason == Reason.ACCEPTED,
        reason=reason,
        chi2=np.where(no_dec, np.nan, best),
        dof=dof.astype(np.int64),
        azimuth_deg=best_az,
        range_m=best_r,
        hypotheses=len(az_grid) * len(r_grid),
    )


class BasicTopologyCorrelator(CorrelationMethod):
    """Method ``basic-topology``: the paper's stepwise-rotation baseline."""

    name = "basic-topology"
    requires_sites = True

    def __init__(self, params: BasicTopologyParams | None = None) -> None:
        self.params = params or BasicTopologyParams()

    def decide(self, a: PredictedTracks, b: PredictedTracks, context: DecisionContext) -> Decisions:
        prm = self.params
        if a.site is None or b.site is None:
            raise ValueError("basic-topology needs two radar sites")
        ia, ib, _ = candidate_pairs(a.position, b.position, prm.candidates.gate_m)
        if len(ia) == 0:
            return Decisions.empty()
        pa, ca, ma = gather_points(a.enu, a.enu_cov(), neighbourhoods(a.enu, prm.topology), ia)
        pb, cb, mb = gather_points(b.enu, b.enu_cov(), neighbourhoods(b.enu, prm.topology), ib)
        res = basic_match(pa, ca, ma, pb, cb, mb, b.site.rotation.T @ a.site.rotation, prm)
        dof = np.maximum(res.dof, 1)
        no_dec = ~np.isfinite(res.chi2)
        return Decisions.build(
            ia,
            ib,
            accepted=res.accepted,
            reason=res.reason,
            cost=np.where(no_dec, np.inf, res.chi2 - dof),
            statistic=res.chi2 / dof,
            rotation_weight=np.ones(len(ia)),
            scale=np.ones(len(ia)),
            neighbors=np.minimum(ma[:, 1:].sum(1), mb[:, 1:].sum(1)),
        )
