"""Adapters putting the whole-picture methods ``gmm`` and ``cfar`` behind :class:`~.base.Correlator`.

Both are pure functions written elsewhere (:mod:`service.correlation.gmm`,
:mod:`service.correlation.cfar`) that take positions in one plane and return one-to-one
pairs; here they get the same snapshots as the topology methods and answer with
:class:`~.base.Decisions`, so the M-of-N book, assignment and registration are shared.

* ``gmm``: both track sets in radar A's ENU tangent plane (east, north), Eq. numbers in
  :mod:`.gmm`; the decisive pairs and their rivals, cost ``-2 ln(posterior)``, statistic =
  posterior (see :class:`GmmCorrelator`).
* ``cfar``: source B is the *reference* (bias-free: AIS when ``site_b`` is None; with two
  radars B plays the reference and A's bias is estimated relative to B).  Both sets as
  ``[range, azimuth]`` in A's polar frame, the form :func:`.cfar.cfar_associate` takes;
  statistic = 1 for confidential (first-stage) pairs, 0 for second-stage ones.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from service.correlation import cfar, gmm
from service.correlation.base import Correlator, DecisionContext, Decisions, Reason, TrackSnapshot


def _all_accepted(index_a: ArrayLike, index_b: ArrayLike, cost: ArrayLike, statistic: ArrayLike) -> Decisions:
    """Decisions for a method that returns its one-to-one pairs only (every pair accepted)."""
    ia = np.asarray(index_a, dtype=np.intp)
    n = int(ia.size)
    return Decisions.build(
        ia,
        np.asarray(index_b, dtype=np.intp),
        accepted=np.ones(n, dtype=bool),
        reason=np.full(n, Reason.ACCEPTED, dtype=np.int8),
        cost=np.asarray(cost, dtype=float),
        statistic=np.asarray(statistic, dtype=float),
        rotation_weight=np.ones(n),
        scale=np.ones(n),
    )


class GmmCorrelator(Correlator):
    """Method ``gmm`` (Li, Dong, Ding, Guan): GMM / Coherent-Point-Drift anti-bias association.

    Both track sets in radar A's ENU plane, with their position covariances (they bound the
    mixture's sigma from below, ``GmmParams.sigma_floor_factor``).  With
    ``GmmParams.report_rivals`` (the default) the decisions are the candidates of
    :func:`.gmm.candidate_pairs`: cost ``-2 ln P(j | x_i)`` (chi-square units, as the
    assignment's ambiguity margin), accepted where a decisive posterior of Eq. (27) is in the
    candidate's row or column, so that the one-to-one assignment refuses a pair with a rival
    within its margin (the correlator declares ambiguity instead of guessing); the other
    candidates are reported with reason ``AMBIGUOUS`` (the posterior is spread over several
    centroids or the outlier component).  Without it, the pairs of Eq. (27) as the paper
    decides them, all accepted.  ``statistic`` = the posterior.
    """

    name = "gmm"
    requires_sites = True

    def __init__(self, params: gmm.GmmParams | None = None) -> None:
        self.params = params

    @staticmethod
    def _neg2log(post: np.ndarray) -> np.ndarray:
        """``-2 ln P``: a posterior as a cost in chi-square units (a ratio of 20 is 6 apart)."""
        return np.asarray(-2.0 * np.log(np.clip(post, np.finfo(float).tiny, 1.0)))

    def decide(self, a: TrackSnapshot, b: TrackSnapshot, context: DecisionContext) -> Decisions:
        if a.site is None:
            raise ValueError("gmm needs radar A's site")
        p = self.params or gmm.GmmParams()
        rot = a.site.rotation
        pos_a = a.enu[:, :2]
        pos_b = a.site.ecef_to_enu(b.position)[:, :2]
        cov_a = a.enu_cov()[:, :2, :2]
        cov_b = (rot.T @ b.pos_cov @ rot)[:, :2, :2]  # B's ECEF covariance in A's ENU plane
        res = gmm.gmm_associate(pos_a, pos_b, p, cov_a, cov_b)
        if res.posterior_matrix.size == 0:
            return Decisions.empty()
        moved = pos_b + res.displacement  # B's centroids where the fit put them
        if p.report_rivals:
            d = pos_a[:, None, :] - moved[None, :, :]
            chi2 = np.einsum("ijk,ijk->ij", d, d) / max(res.sigma_m**2, np.finfo(float).tiny)
            ia, ib, accepted = gmm.candidate_pairs(
                res.posterior_matrix, chi2, p.posterior_threshold, p.rival_posterior, p.candidate_gate_chi2
            )
        else:
            ia, ib = res.index_a, res.index_b
            accepted = np.ones(ia.size, dtype=bool)
        post = res.posterior_matrix[ia, ib]
        n = int(ia.size)
        return Decisions.build(
            ia,
            ib,
            accepted=accepted,
            reason=np.where(accepted, Reason.ACCEPTED, Reason.AMBIGUOUS).astype(np.int8),
            cost=self._neg2log(post),
            statistic=post,
            rotation_weight=np.ones(n),
            scale=np.ones(n),
        )


class CfarCorrelator(Correlator):
    """Method ``cfar`` (Qi, Cui, Xiong, Wang): CA-CFAR confidential pairs, LS bias, 2nd association."""

    name = "cfar"
    requires_sites = False

    def __init__(self, params: cfar.CfarParams | None = None) -> None:
        self.params = params

    def decide(self, a: TrackSnapshot, b: TrackSnapshot, context: DecisionContext) -> Decisions:
        if a.site is None:
            raise ValueError("cfar needs radar A's site (source B is the reference)")
        ra, aza, _ = a.site.ecef_to_polar(a.position)
        rb, azb, _ = a.site.ecef_to_polar(b.position)
        res = cfar.cfar_associate(np.column_stack([rb, azb]), np.column_stack([ra, aza]), self.params)
        conf = np.asarray(res.confident, dtype=bool)
        return _all_accepted(res.index_radar, res.index_ref, np.where(conf, -1.0, 0.0), conf)
