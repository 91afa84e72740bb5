"""Adapters putting the whole-picture methods ``gmm`` and ``cfar`` behind :class:`~.base.Correlator`.

Both are pure functions written elsewhere (:mod:`service.correlation.gmm`,
:mod:`service.correlation.cfar`) that take positions in one plane and return one-to-one
pairs; here they get the same snapshots as the topology methods and answer with
:class:`~.base.Decisions` (every returned pair accepted), so the M-of-N book,
assignment and registration are shared.

* ``gmm``: both track sets in radar A's ENU tangent plane (east, north), Eq. numbers in
  :mod:`.gmm`; cost ``-ln(posterior)``, statistic = posterior.
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
    """Method ``gmm`` (Li, Dong, Ding, Guan): GMM / Coherent-Point-Drift anti-bias association."""

    name = "gmm"
    requires_sites = True

    def __init__(self, params: gmm.GmmParams | None = None) -> None:
        self.params = params

    def decide(self, a: TrackSnapshot, b: TrackSnapshot, context: DecisionContext) -> Decisions:
        if a.site is None:
            raise ValueError("gmm needs radar A's site")
        pos_a = a.enu[:, :2]
        pos_b = a.site.ecef_to_enu(b.position)[:, :2]
        res = gmm.gmm_associate(pos_a, pos_b, self.params)
        post = np.asarray(res.posterior, dtype=float)
        return _all_accepted(res.index_a, res.index_b, -np.log(np.clip(post, 1e-12, 1.0)), post)


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
