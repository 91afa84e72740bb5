"""Classic chi-square nearest-neighbour association on absolute positions (method ``nearest``).

The textbook track-to-track test (He et al. 2007, the paper's reference [1]): for tracks
``i`` of A and ``j`` of B at the same time, ``d = x_i - x_j`` with ``S = P_i + P_j``;
``d^T S^-1 d`` is chi-square with 3 degrees of freedom when both are the same target and
the sensors are unbiased.  Accepted candidates go to the one-to-one assignment.  It fails
under bias -- the third curve of the evaluation -- and is the second stage of
``svd-topology`` once the radars are registered (then the registration's own uncertainty
is added to ``S``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.chi2 import chi2_upper
from service.correlation.base import (
    CorrelationMethod,
    DecisionContext,
    Decisions,
    FloatArray,
    IntArray,
    PredictedTracks,
    Reason,
)
from service.correlation.candidates import CandidateParams, candidate_pairs
from service.linalg import mahalanobis3


@dataclass(frozen=True)
class NearestParams:
    """Chi-square gate of the nearest-neighbour test."""

    candidates: CandidateParams = field(default_factory=CandidateParams)
    #: False-rejection probability of the position test (chi-square, 3 dof).
    alpha: float = 0.01
    #: Also test velocities (chi-square, 3 more dof).  Off for the classic method.
    use_velocity: bool = False


def chi2_pairs(
    a: PredictedTracks,
    b: PredictedTracks,
    ia: IntArray,
    ib: IntArray,
    extra_cov_a: FloatArray | None = None,
    extra_cov_b: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Position and velocity chi-square of candidate pairs; also an ``ok`` flag (non-singular)."""
    d = a.position[ia] - b.position[ib]
    s = a.pos_cov[ia] + b.pos_cov[ib]
    if extra_cov_a is not None:
        s = s + extra_cov_a[ia]
    if extra_cov_b is not None:
        s = s + extra_cov_b[ib]
    q_pos, ok = mahalanobis3(d, s)
    q_vel, _ = mahalanobis3(a.velocity[ia] - b.velocity[ib], a.vel_cov[ia] + b.vel_cov[ib])
    return q_pos, q_vel, ok


def nearest_decide(
    a: PredictedTracks,
    b: PredictedTracks,
    ia: IntArray,
    ib: IntArray,
    params: NearestParams,
    extra_cov_a: FloatArray | None = None,
    extra_cov_b: FloatArray | None = None,
) -> Decisions:
    """Chi-square decisions for given candidates (statistic = chi-square / dof)."""
    q_pos, q_vel, ok = chi2_pairs(a, b, ia, ib, extra_cov_a, extra_cov_b)
    dof = 3 + (3 if params.use_velocity else 0)
    q = q_pos + (q_vel if params.use_velocity else 0.0)
    passed = ok & (q <= chi2_upper(params.alpha, dof))
    reason = np.where(~ok, Reason.DEGENERATE_FIT, np.where(passed, Reason.ACCEPTED, Reason.GATE))
    return Decisions.build(
        ia,
        ib,
        accepted=passed,
        reason=reason.astype(np.int8),
        cost=q - dof,
        statistic=q / dof,
        rotation_weight=np.ones(len(ia)),
        scale=np.ones(len(ia)),
    )


class NearestCorrelator(CorrelationMethod):
    """Method ``nearest``: candidates by the ECEF gate, then the chi-square test above."""

    name = "nearest"
    requires_sites = False

    def __init__(self, params: NearestParams | None = None) -> None:
        self.params = params or NearestParams()

    def decide(self, a: PredictedTracks, b: PredictedTracks, context: DecisionContext) -> Decisions:
        ia, ib, _ = candidate_pairs(a.position, b.position, self.params.candidates.gate_m)
        return nearest_decide(a, b, ia, ib, self.params)
