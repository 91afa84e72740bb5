"""The aid of association (:mod:`service.tracking.aid`): the correlation's answers, by data time.

The correlation answers each radar table it is given with the pair sets that table updated
(:class:`~.read_model.PairSetView`, with the pair correlator's registration).  This keeps them
as they stood after every table up to each data time, and gives a radar's tracker, for a batch
at ``t``, the references of its tracks from the state after every table up to ``t - lag_s``
(``AidParams.lag_s``).  The engine waits for those answers before the batch
(:meth:`Engine._answers_through <service.engine.Engine>`), so the aid is the same whether the
correlation runs in this process or in its own, however the batches arrive and group.

A partner is looked up in its radar's table as the tracking stage holds it at the batch (the
merge's data-time order decides that, not arrival), moved to each plot's time on its velocity
and into the aided radar's view by the pair's registration
(:func:`~service.correlation.partner_view.view_with_covariance`).  Cost per batch: for each
other radar with confirmed pairs with this one, a search of the candidates' tracks among its
confirmed pairs (one sort) and of their partners in its table, then the transform of the
candidates that have a partner (eleven vectorised transforms); no loop over tracks or pairs.
Memory: the pair sets of the last ``lag_s`` of answers (references to the views the engine
holds anyway, a dictionary per answered table that changed pairs).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from service.correlation.pairkeys import find
from service.correlation.partner_view import view_with_covariance
from service.correlation.registration import N_TERMS
from service.geo import FloatArray
from service.pipeline.read_model import PairRegistration, PairSetView
from service.pipeline.tracking_stage import TrackingStage
from service.tracking.aid import PartnerReferences, horizontal_spread
from service.tracking.params import AidParams

Key = tuple[str, str]


class PartnerAid:
    """The correlation's pair sets as answered, by data time, and the references they give."""

    def __init__(self, params: AidParams, tracking: TrackingStage) -> None:
        self.params = params
        self.tracking = tracking
        #: Every pair set as last answered ...
        self._views: dict[Key, PairSetView] = {}
        #: ... and as it stood after each answered table that changed one (data time, views).
        self._history: deque[tuple[float, dict[Key, PairSetView]]] = deque()

    def answered(self, time_s: float, updated: Iterable[tuple[Key, PairSetView]]) -> None:
        """The correlation's answer to a radar table of data time ``time_s`` (answers come in
        data-time order)."""
        changed = dict(updated)
        if changed:
            self._views = {**self._views, **changed}
            self._history.append((time_s, self._views))

    def clear(self) -> None:
        """Forget every answer (a restart: the answers come again from the restored state)."""
        self._views = {}
        self._history.clear()

    def due_s(self, time_s: float) -> float:
        """The data time through which a batch at ``time_s`` needs the correlation's answers."""
        return time_s - self.params.lag_s

    def _state(self, time_s: float) -> dict[Key, PairSetView]:
        """The pair sets after every table up to ``due_s(time_s)`` (batches come in data-time
        order, so older states are dropped)."""
        due = self.due_s(time_s)
        while len(self._history) > 1 and self._history[1][0] <= due:
            self._history.popleft()
        if not self._history or self._history[0][0] > due:
            return {}
        return self._history[0][1]

    def references(self, radar_id: str, time_s: float) -> PartnerReferences | None:
        """The references of radar ``radar_id``'s tracks for its batch at ``time_s`` (None:
        none of its pairs is registered with a confirmed pair)."""
        partners = []
        for view in self._state(time_s).values():
            if radar_id not in (view.radar_a, view.radar_b) or not view.confirmed:
                continue
            if view.registration is None or view.radar_a == view.radar_b:
                continue
            mine = 0 if view.radar_a == radar_id else 1
            other = (view.radar_a, view.radar_b)[1 - mine]
            held = self.tracking.tracked.get(other)
            if held is None or not len(held.table):
                continue
            on = np.asarray(view.columns["confirmed"], bool)
            own_ids = view.columns["track_a" if mine == 0 else "track_b"][on]
            their_ids = view.columns["track_b" if mine == 0 else "track_a"][on]
            terms = _pair_terms(view.registration, radar_id, other)
            if terms is not None:
                partners.append((other, own_ids, their_ids, *terms))
        if not partners:
            return None
        return _References(self, radar_id, partners)


def _pair_terms(reg: PairRegistration, own: str, other: str) -> tuple[FloatArray, FloatArray] | None:
    """The ten terms (``own``'s five, then ``other``'s) of a pair's registration and their joint
    covariance ``(10, 10)``; None when the registration does not hold both radars."""
    if own not in reg.radar_ids or other not in reg.radar_ids:
        return None
    at = [reg.radar_ids.index(r) for r in (own, other)]
    cols = np.concatenate([np.arange(N_TERMS * j, N_TERMS * j + N_TERMS) for j in at])
    return np.concatenate([reg.terms[at[0]], reg.terms[at[1]]]), reg.covariance[np.ix_(cols, cols)]


class _References:
    """:class:`~service.tracking.aid.PartnerReferences` of one radar for one batch."""

    def __init__(
        self,
        aid: PartnerAid,
        radar_id: str,
        partners: list[tuple[str, NDArray[np.str_], NDArray[np.str_], FloatArray, FloatArray]],
    ) -> None:
        self.aid = aid
        self.radar_id = radar_id
        self.partners = partners

    def __call__(
        self, track_ids: NDArray[np.str_], times_s: FloatArray, own_spread_m2: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        n = track_ids.shape[0]
        ref, ref_cov = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
        best = np.asarray(own_spread_m2, dtype=float).copy()  # (a reference must beat the track)
        tracked = self.aid.tracking.tracked
        target = tracked[self.radar_id].geometry
        limit = self.aid.params.registration_sigma_m**2
        ids = np.asarray(track_ids)
        for other, own_ids, their_ids, terms, terms_cov in self.partners:
            at = find(own_ids, ids)
            has = np.flatnonzero(at >= 0)
            if not has.shape[0]:
                continue
            table = tracked[other].table
            rows = find(table.track_id, their_ids[at[has]])
            sel, r = has[rows >= 0], rows[rows >= 0]
            if not sel.shape[0]:
                continue
            dt = times_s[sel] - table.time_s[r]
            vel = table.velocity_ecef_mps[r]
            pos, cov, reg = view_with_covariance(
                tracked[other].geometry,
                target,
                table.position_ecef_m[r] + vel * dt[:, None],
                vel,
                table.covariance[r, :3, :3],
                terms,
                terms_cov,
            )
            spread = horizontal_spread(cov)
            take = (horizontal_spread(reg) <= limit) & (spread < best[sel])
            won = sel[take]
            ref[won], ref_cov[won], best[won] = pos[take], cov[take], spread[take]
        return ref, ref_cov
