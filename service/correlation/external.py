"""Adapters putting the whole-picture methods ``gmm`` and ``cfar`` behind :class:`~.base.CorrelationMethod`.

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

from service.chi2 import chi2_quantile
from service.correlation import cfar, gmm
from service.correlation.base import (
    CorrelationMethod,
    DecisionContext,
    Decisions,
    IntArray,
    PredictedTracks,
    Reason,
)
from service.geo import Site, enu_to_polar


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


class GmmCorrelator(CorrelationMethod):
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

    def decide(self, a: PredictedTracks, b: PredictedTracks, context: DecisionContext) -> Decisions:
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


class CfarCorrelator(CorrelationMethod):
    """Method ``cfar`` (Qi, Cui, Xiong, Wang): CA-CFAR confidential pairs, LS bias, 2nd association.

    Both sets as ``[range, azimuth]`` in radar A's polar frame with their covariances there
    (:func:`.cfar.polar_covariance` of the predicted ENU covariances; B's ECEF covariance turned
    into A's ENU frame).  :meth:`reverify` re-checks the stream's confirmed pairs by a
    bias-compensated chi-square (:func:`.cfar.consistent_pairs`), so a right pair is not lost
    when one update's CA-CFAR detection is poor; :meth:`decide` then associates the other tracks,
    with the kept pairs as known pairs for the bias.  ``statistic`` = 1 for confidential and kept
    pairs, 0 for second-stage ones; a kept pair's cost is its chi-square less its 2 dof.
    """

    name = "cfar"
    requires_sites = False

    def __init__(self, params: cfar.CfarParams | None = None) -> None:
        self.params = params

    @staticmethod
    def _polar(
        s: PredictedTracks, site: Site, rows: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``[range_m, azimuth_deg]`` of ``s``'s tracks (``rows``; None: all) in ``site``'s polar
        frame, and their ``(n, 2, 2)`` covariances."""
        pos = s.position if rows is None else s.position[rows]
        cov = s.pos_cov if rows is None else s.pos_cov[rows]
        enu = site.ecef_to_enu(pos)
        r, az, _ = enu_to_polar(enu)
        rot = site.rotation
        return np.column_stack([r, az]), cfar.polar_covariance(enu, rot.T @ cov @ rot)

    def decide(self, a: PredictedTracks, b: PredictedTracks, context: DecisionContext) -> Decisions:
        if a.site is None:
            raise ValueError("cfar needs radar A's site (source B is the reference)")
        rad, crad = self._polar(a, a.site)
        ref, cref = self._polar(b, a.site)
        # Rows that may form candidate pairs (the context's reference rows); the confirmed pairs
        # with both tracks outside them are the pairs the re-check kept: known pairs for the bias.
        free_a = np.ones(len(a), dtype=bool)
        free_b = np.ones(len(b), dtype=bool)
        if context.reference_a is not None:
            free_a[:] = False
            free_a[context.reference_a] = True
        if context.reference_b is not None:
            free_b[:] = False
            free_b[context.reference_b] = True
        known = ~free_a[context.confirmed_a] & ~free_b[context.confirmed_b]
        res = cfar.cfar_associate(
            ref,
            rad,
            self.params,
            cref,
            crad,
            known_ref=context.confirmed_b[known],
            known_radar=context.confirmed_a[known],
        )
        ok = free_a[res.index_radar] & free_b[res.index_ref]
        conf = np.asarray(res.confident, dtype=bool)[ok]
        return _all_accepted(res.index_radar[ok], res.index_ref[ok], np.where(conf, -1.0, 0.0), conf)

    def reverify(
        self, a: PredictedTracks, b: PredictedTracks, ia: IntArray, ib: IntArray, context: DecisionContext
    ) -> Decisions | None:
        """Re-check the confirmed pairs ``(ia[k], ib[k])``: each pair's ``[range, azimuth]``
        residual against the bias of the other confirmed pairs (Eqs. (17)-(18) of the paper,
        leave-one-out, robust start; :func:`.cfar.consistent_pairs`), chi-square with 2 dof and
        the covariance ``C_a + C_b + C_bias``, kept at ``keep_probability``.  None (every pair
        decided afresh) without A's site or with fewer than ``min_kept_pairs`` pairs.  A kept
        pair: ``cost = chi2 - 2``, ``statistic`` 1 (as a confidential pair)."""
        p = self.params or cfar.CfarParams()
        if a.site is None or len(ia) < max(2, p.min_kept_pairs):
            return None
        rad, crad = self._polar(a, a.site, ia)
        ref, cref = self._polar(b, a.site, ib)
        gate = float(chi2_quantile(p.keep_probability, 2))
        cons = cfar.consistent_pairs(cfar.polar_residuals(ref, rad), cref + crad, gate, p)
        n = len(ia)
        return Decisions.build(
            np.asarray(ia, dtype=np.intp),
            np.asarray(ib, dtype=np.intp),
            accepted=cons.passed,
            reason=np.where(cons.passed, Reason.ACCEPTED, Reason.GATE).astype(np.int8),
            cost=cons.chi2 - 2.0,
            statistic=np.ones(n),
            rotation_weight=np.ones(n),
            scale=np.ones(n),
        )
