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

from service.correlation.base import Correlator, DecisionContext, Decisions, Reason, TrackSnapshot


class GmmCorrelator(Correlator):
    """Method ``gmm`` (Li, Dong, Ding, Guan): GMM / Coherent-Point-Drift anti-bias association."""

    name = "gmm"
    requires_sites = True

    def __init__(self, params: object | None = None) -> None:
        try:
            from service.correlation import gmm
        except ImportError as exc:  # pragma: no cover - only before the module lands
            raise NotImplementedError(
                "method 'gmm' is not available yet (service/correlation/gmm.py)"
            ) from exc
        self._gmm = gmm
        self.params = params

    def decide(self, a: TrackSnapshot, b: TrackSnapshot, context: DecisionContext) -> Decisions:
        if a.site is None:
            raise ValueError("gmm needs radar A's site")
        pos_a = a.enu[:, :2]
        pos_b = a.site.ecef_to_enu(b.position)[:, :2]
        res = self._gmm.gmm_associate(pos_a, pos_b, self.params)  # type: ignore[arg-type]
        n = int(res.index_a.size)
        post = np.asarray(res.posterior, dtype=float)
        return Decisions.build(
            np.asarray(res.index_a, dtype=np.intp),
            np.asarray(res.index_b, dtype=np.intp),
            accepted=np.ones(n, dtype=bool),
            reason=np.full(n, Reason.ACCEPTED, dtype=np.int8),
            cost=-np.log(np.clip(post, 1e-12, 1.0)),
            statistic=post,
            rotation_weight=np.ones(n),
            scale=np.ones(n),
        )


class CfarCorrelator(Correlator):
    """Method ``cfar`` (Qi, Cui, Xiong, Wang): CA-CFAR confidential pairs, LS bias, 2nd association."""

    name = "cfar"
    requires_sites = False

    def __init__(self, params: object | None = None) -> None:
        try:
            from service.correlation import cfar
        except ImportError as exc:  # pragma: no cover - only before the module lands
            raise NotImplementedError(
                "method 'cfar' is not available yet (service/correlation/cfar.py)"
            ) from exc
        self._cfar = cfar
        self.params = params

    def decide(self, a: TrackSnapshot, b: TrackSnapshot, context: DecisionContext) -> Decisions:
        if a.site is None:
            raise ValueError("cfar needs radar A's site (source B is the reference)")
        ra, aza, _ = a.site.ecef_to_polar(a.position)
        rb, azb, _ = a.site.ecef_to_polar(b.position)
        res = self._cfar.cfar_associate(
            np.column_stack([rb, azb]),
            np.column_stack([ra, aza]),
            self.params,  # type: ignore[arg-type]
        )
        n = int(res.index_ref.size)
        conf = np.asarray(res.confident, dtype=bool)
        return Decisions.build(
            np.asarray(res.index_radar, dtype=np.intp),
            np.asarray(res.index_ref, dtype=np.intp),
            accepted=np.ones(n, dtype=bool),
            reason=np.full(n, Reason.ACCEPTED, dtype=np.int8),
            cost=np.where(conf, -1.0, 0.0),
            statistic=conf.astype(float),
            rotation_weight=np.ones(n),
            scale=np.ones(n),
        )
