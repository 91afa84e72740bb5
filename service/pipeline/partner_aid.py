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
(:func:`~service.correlation.partner_view.view_with_covariance`).  Cost: nothing unless the
tracker asks, which it does for the candidates of its tracks in a formation; then, for each
other radar with confirmed pairs with this one, a search of those tracks among its confirmed
pairs and of their partners in its table (each sorted once per pair set and table), and one
vectorised transform of the candidates with a partner; no loop over tracks or pairs.
Memory: the pair sets of the last ``lag_s`` of answers (a dictionary of references to the
views per answered table that changed pairs, which keeps those views alive: on the national
network 26 MB more at the peak).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.correlation.pairkeys import find
from service.correlation.partner_view import view_with_covariance
from service.correlation.registration import N_TERMS
from service.geo import FloatArray
from service.pipeline.read_model import PairRegistration, PairSetView
from service.pipeline.tracking_stage import TrackingStage
from service.tracking.aid import PartnerReferences, horizontal_spread
from service.tracking.base import TrackTable
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
        #: What each pair set gives each of its radars (:meth:`_partner`), and each radar's
        #: table with its ids sorted (:meth:`table`): made once per pair set and table.
        self._partners: dict[tuple[Key, str], tuple[PairSetView, _Partner | None]] = {}
        self._tables: dict[str, tuple[TrackTable, NDArray[np.str_], NDArray[np.intp]]] = {}

    def answered(self, time_s: float, updated: Iterable[tuple[Key, PairSetView]]) -> None:
        """The correlation's answer to a radar table of data time ``time_s`` (answers come in
        data-time order)."""
        changed = dict(updated)
        if changed:
            self._views = {**self._views, **changed}
            self._history.append((time_s, self._views))

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
        """The references of radar ``radar_id``'s tracks for its batch at ``time_s`` (None: no
        answer that old yet).  Its pairs are looked at only if the tracker asks (a track of it
        in a formation has candidates)."""
        state = self._state(time_s)
        return _References(self, radar_id, state) if state else None

    def partners(self, radar_id: str, state: dict[Key, PairSetView]) -> list[_Partner]:
        """What the pair sets of ``state`` give radar ``radar_id``: each registered one with
        confirmed pairs whose other radar is still tracked, its table not empty."""
        out = []
        for key, view in state.items():
            if radar_id not in key or not view.confirmed or view.registration is None:
                continue
            partner = self._partner(key, view, radar_id)
            held = None if partner is None else self.tracking.tracked.get(partner.other)
            if partner is not None and held is not None and len(held.table):  # (a radar dropped: none)
                out.append(partner)
        return out

    def _partner(self, key: Key, view: PairSetView, radar_id: str) -> _Partner | None:
        """What a pair set gives radar ``radar_id`` (made once per pair set; None: nothing)."""
        held = self._partners.get((key, radar_id))
        if held is not None and held[0] is view:
            return held[1]
        mine = 0 if view.radar_a == radar_id else 1
        other = (view.radar_a, view.radar_b)[1 - mine]
        terms = None if view.registration is None else _pair_terms(view.registration, radar_id, other)
        partner = None
        if terms is not None and other != radar_id and other in self.tracking.tracked:
            on = np.asarray(view.columns["confirmed"], bool)
            own = view.columns["track_a" if mine == 0 else "track_b"][on]
            order = np.argsort(own, kind="stable")
            theirs = view.columns["track_b" if mine == 0 else "track_a"][on][order]
            partner = _Partner(other, own[order], theirs, *terms)
        self._partners[(key, radar_id)] = (view, partner)
        return partner

    def table(self, radar_id: str) -> tuple[TrackTable, NDArray[np.str_], NDArray[np.intp]]:
        """Radar ``radar_id``'s table as the tracking stage holds it, its ids sorted and their
        rows (sorted once per table)."""
        table = self.tracking.tracked[radar_id].table
        held = self._tables.get(radar_id)
        if held is None or held[0] is not table:
            order = np.argsort(table.track_id, kind="stable")
            held = self._tables[radar_id] = (table, table.track_id[order], order)
        return held


@dataclass(frozen=True)
class _Partner:
    """Another radar's confirmed partners of one radar's tracks, by one pair set."""

    other: str
    own_ids: NDArray[np.str_]  # this radar's tracks of the confirmed pairs, sorted
    their_ids: NDArray[np.str_]  # ... and their partners, in the same order
    terms: FloatArray  # (10,): this radar's five terms, then the other's
    terms_cov: FloatArray  # (10, 10)


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

    def __init__(self, aid: PartnerAid, radar_id: str, state: dict[Key, PairSetView]) -> None:
        self.aid = aid
        self.radar_id = radar_id
        self.state = state

    def __call__(
        self, track_ids: NDArray[np.str_], times_s: FloatArray, own_spread_m2: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        n = track_ids.shape[0]
        ref, ref_cov = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
        best = np.asarray(own_spread_m2, dtype=float).copy()  # (a reference must beat the track)
        tracked = self.aid.tracking.tracked
        target = tracked[self.radar_id].geometry
        limit = self.aid.params.registration_sigma_m**2
        for p in self.aid.partners(self.radar_id, self.state):
            at = find(p.own_ids, track_ids)
            has = np.flatnonzero(at >= 0)
            if not has.shape[0]:
                continue
            table, ids, order = self.aid.table(p.other)
            j = find(ids, p.their_ids[at[has]])
            sel, r = has[j >= 0], order[j[j >= 0]]
            if not sel.shape[0]:
                continue
            vel = table.velocity_ecef_mps[r]
            pos, cov, reg = view_with_covariance(
                tracked[p.other].geometry,
                target,
                table.position_ecef_m[r] + vel * (times_s[sel] - table.time_s[r])[:, None],
                vel,
                table.covariance[r, :3, :3],
                p.terms,
                p.terms_cov,
            )
            spread = horizontal_spread(cov)
            take = (horizontal_spread(reg) <= limit) & (spread < best[sel])
            won = sel[take]
            ref[won], ref_cov[won], best[won] = pos[take], cov[take], spread[take]
        return ref, ref_cov
