"""The aid of association (:mod:`service.tracking.aid`): every pair's confirmed partners and
registration, by data time, the same for one worker and for N partitioned ones.

At every release that crosses a multiple of the links' grid (:mod:`.system_stage`) each pair's
owner takes its links (its confirmed pairs) and its registration as they are then: this worker's
correlation hands its own pairs' to this class with the crossing (:meth:`PartnerAid.crossed`),
the other workers send theirs (``{prefix}/links/{a}/{b}``, :meth:`PartnerAid.mirror`).  A
radar's batch at ``t`` is aided by every pair's links and registration at the latest crossing
at or before ``t - lag_s`` (``AidParams.lag_s``): every worker releases the same tables in the
same order (:mod:`.merger`), so that crossing and what it holds are the same everywhere.  The
engine holds the batch until they are in (:meth:`Engine._answers_through
<service.engine.Engine>`): this worker's correlation through ``t - lag_s`` and, partitioned,
every other live worker's (their ``correlated_s``, sent after the links it covers).  So the aid
is the same whether the correlation runs in this process, in its own, or in other workers, and
however the batches arrive and group.

A partner is looked up in its radar's table as the tracking stage holds it at the batch (the
merge's data-time order decides that, not arrival), moved to each plot's time on its velocity
and into the aided radar's view by the pair's registration
(:func:`~service.correlation.partner_view.view_with_covariance`).  Cost: at each crossing, a
reference to each updated pair's links; nothing more unless the tracker asks, which it does for
the candidates of its tracks in a formation; then, for each other radar with confirmed pairs
with this one, a search of those tracks among its confirmed pairs and of their partners in its
table (each sorted once per links and table), and one vectorised transform of the candidates
with a partner; no loop over tracks or pairs.  Memory: each pair's links from the crossing read
last on (about ``lag_s`` plus a grid step of data time).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.correlation.pairkeys import find
from service.correlation.partner_view import view_with_covariance
from service.correlation.registration import N_TERMS
from service.geo import FloatArray
from service.pipeline.shared_links import Crossing, Key, LinksHistory, PairRegistration, Position, SharedLinks
from service.pipeline.tracking_stage import TrackingStage
from service.tracking.aid import PartnerReferences, horizontal_spread
from service.tracking.base import TrackTable
from service.tracking.params import AidParams


class PartnerAid:
    """Every pair's links and registration at the links' grid's crossings, and the references
    they give a radar's tracks."""

    def __init__(self, params: AidParams, tracking: TrackingStage) -> None:
        self.params = params
        self.tracking = tracking
        #: Every pair's links (this worker's at its crossings, the others' as they come) ...
        self.history = LinksHistory()
        #: ... the crossings not read yet, oldest first ...
        self._crossings: deque[Position] = deque()
        #: ... and every pair's links at the crossing read last (None: none yet).
        self._state: dict[Key, SharedLinks] | None = None
        #: What each pair's links give each of its radars (:meth:`_partner`), and each radar's
        #: table with its ids sorted (:meth:`table`): made once per links and table.
        self._partners: dict[tuple[Key, str], tuple[SharedLinks, _Partner | None]] = {}
        self._tables: dict[str, tuple[TrackTable, NDArray[np.str_], NDArray[np.intp]]] = {}
        #: The tables of the radars other workers track, as their owners sent them (data time,
        #: table), oldest first: from the one before the batch read last on.
        self._foreign: dict[str, deque[tuple[float, TrackTable]]] = {}

    def crossed(self, crossing: Crossing) -> None:
        """A crossing of this worker's correlation (in release order), with its own pairs'
        links as they were then."""
        for shared in crossing.own:
            self.history.record(shared)
        self._crossings.append(crossing.position)

    def mirror(self, shared: SharedLinks) -> None:
        """Another worker's pair's links (in the order its owner updated it)."""
        self.history.record(shared)

    def foreign(self, radar_id: str, time_s: float, table: TrackTable) -> None:
        """A table of a radar another worker tracks, as its owner sent it (in its order)."""
        self._foreign.setdefault(radar_id, deque()).append((time_s, table))

    def passed(self, position: Position) -> None:
        """The batch at ``position`` is tracked (batches come in release order): the other
        workers' tables that no later batch reads go, the latest before it stays."""
        for other, queue in self._foreign.items():
            while len(queue) > 1 and (queue[1][0], other) < position:
                queue.popleft()

    def due_s(self, time_s: float) -> float:
        """The data time through which a batch at ``time_s`` needs every pair's links."""
        return time_s - self.params.lag_s

    def _take(self, time_s: float) -> dict[Key, SharedLinks] | None:
        """Every pair's links at the latest crossing at or before ``due_s(time_s)`` (batches
        come in data-time order, so the reads only move on)."""
        due = self.due_s(time_s)
        taken = None
        while self._crossings and self._crossings[0][0] <= due:
            taken = self._crossings.popleft()
        if taken is not None:
            self._state = self.history.shared_at(taken)
        return self._state

    def references(self, radar_id: str, time_s: float) -> PartnerReferences | None:
        """The references of radar ``radar_id``'s tracks for its batch at ``time_s`` (None: no
        crossing that old yet).  Its pairs are looked at only if the tracker asks (a track of
        it in a formation has candidates)."""
        position = (time_s, radar_id)
        self.passed(position)
        state = self._take(time_s)
        return _References(self, position, state) if state is not None else None

    def partners(self, position: Position, state: dict[Key, SharedLinks]) -> list[_Partner]:
        """What the pairs' links of ``state`` give the radar of the batch at ``position``: each
        registered one with confirmed pairs whose other radar is tracked, its table then not
        empty."""
        radar_id = position[1]
        out = []
        for key, shared in state.items():
            if radar_id not in key or not shared.links.track_a.shape[0] or shared.registration is None:
                continue
            partner = self._partner(key, shared, radar_id)
            if partner is not None and len(self.table(partner.other, position)[0]):  # (dropped: none)
                out.append(partner)
        return out

    def _partner(self, key: Key, shared: SharedLinks, radar_id: str) -> _Partner | None:
        """What a pair's links give radar ``radar_id`` (made once per links; None: nothing)."""
        held = self._partners.get((key, radar_id))
        if held is not None and held[0] is shared:
            return held[1]
        links = shared.links
        mine = 0 if links.source_a == radar_id else 1
        other = (links.source_a, links.source_b)[1 - mine]
        reg = shared.registration
        terms = None if reg is None else _pair_terms(reg, radar_id, other)
        partner = None
        if terms is not None and other != radar_id and other in self.tracking.tracked:
            own = links.track_a if mine == 0 else links.track_b
            order = np.argsort(own, kind="stable")
            theirs = (links.track_b if mine == 0 else links.track_a)[order]
            partner = _Partner(other, own[order], theirs, *terms)
        self._partners[(key, radar_id)] = (shared, partner)
        return partner

    def table(
        self, radar_id: str, position: Position
    ) -> tuple[TrackTable, NDArray[np.str_], NDArray[np.intp]]:
        """Radar ``radar_id``'s table as it was before the batch at ``position`` in the release
        order (the tracking stage's, when this worker tracks it; else the latest its owner sent
        from before), its ids sorted and their rows (sorted once per table)."""
        queue = self._foreign.get(radar_id)
        if queue is None:
            radar = self.tracking.tracked.get(radar_id)
            table = radar.table if radar is not None else _EMPTY  # (a radar dropped: none)
        elif queue and (queue[0][0], radar_id) < position:
            table = queue[0][1]
        else:
            table = _EMPTY
        kept = self._tables.get(radar_id)
        if kept is None or kept[0] is not table:
            order = np.argsort(table.track_id, kind="stable")
            kept = self._tables[radar_id] = (table, table.track_id[order], order)
        return kept


#: A radar's table before its owner sent any.
_EMPTY = TrackTable.empty()


@dataclass(frozen=True)
class _Partner:
    """Another radar's confirmed partners of one radar's tracks, by one pair's links."""

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

    def __init__(self, aid: PartnerAid, position: Position, state: dict[Key, SharedLinks]) -> None:
        self.aid = aid
        self.position = position
        self.radar_id = position[1]
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
        for p in self.aid.partners(self.position, self.state):
            at = find(p.own_ids, track_ids)
            has = np.flatnonzero(at >= 0)
            if not has.shape[0]:
                continue
            table, ids, order = self.aid.table(p.other, self.position)
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
