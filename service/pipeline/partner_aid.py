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

A partner is looked up in its radar's table as it was at that same crossing: the latest table
at or before the crossing's place in the release order, this worker's own after each of its
batches, another worker's as its owner sent it.  Its links and its table then agree (a track
the links name is in it unless it was deleted before), and a batch waits only for what was
released through ``t - lag_s``, never for the other workers' tables up to ``t``: partitioned
workers then track ``lag_s`` apart at most, not in step.  The partner is moved from its
table's time to each plot's on its velocity, its position covariance with it (:func:`~service.
tracking.aid.moved`: the velocity's uncertainty and ``AidParams.reference_psd`` of white-noise
acceleration over the ``lag_s`` or more), and into the aided radar's view by the pair's
registration (:func:`~service.correlation.partner_view.view_with_covariance`).  Cost: at each
crossing, a reference to each updated pair's links; at each table released to the correlation
(and each batch that asks), a look whether the reads move on to a newer crossing; nothing more
unless the tracker asks, which it does for the candidates of its tracks in a formation; then,
for each other radar with confirmed pairs with this one, a search of those tracks among its
confirmed pairs and of their partners in its table (each sorted once per links and table), and
one vectorised transform of the candidates with a partner; no loop over tracks or pairs.
Memory:
each pair's links and each radar's tables from the crossing read last on: ``lag_s``, a grid
step, and how far this worker's tracking runs ahead of its merge, of data time; of a radar's
tables one a cell of the grid once the cell's crossing is known (:meth:`PartnerAid.record`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.correlation.pairkeys import find
from service.correlation.partner_view import view_with_covariance
from service.correlation.registration import N_TERMS
from service.geo import FloatArray
from service.pipeline.shared_links import Crossing, Key, LinksHistory, PairRegistration, Position, SharedLinks
from service.pipeline.system_stage import LINKS_GRID_S
from service.pipeline.tracking_stage import TrackingStage
from service.tracking.aid import PartnerReferences, horizontal_spread, moved
from service.tracking.base import TrackTable
from service.tracking.params import AidParams


class PartnerAid:
    """Every pair's links and registration at the links' grid's crossings, and the references
    they give a radar's tracks."""

    def __init__(self, params: AidParams, tracking: TrackingStage, grid_s: float = LINKS_GRID_S) -> None:
        self.params = params
        self.tracking = tracking
        #: The links' grid (data s): the crossings are the first releases of its cells.
        self.grid_s = grid_s
        #: Every pair's links (this worker's at its crossings, the others' as they come) ...
        self.history = LinksHistory()
        #: ... the crossings not reached yet, oldest first ...
        self._crossings: deque[Position] = deque()
        #: ... the crossing the reads are at (None: none yet) ...
        self._crossing: Position | None = None
        #: ... and every pair's links there, once read (for ``_crossing``).
        self._state: tuple[Position, dict[Key, SharedLinks]] | None = None
        #: Every radar's tables, (data time, table), oldest first, from the one at or before the
        #: crossing on: this worker's after each of its batches, the others' as sent.
        self._tables: dict[str, deque[tuple[float, TrackTable]]] = {}
        #: The crossing of each cell of the grid from the one read last on, by cell.
        self._cell_crossings: dict[int, Position] = {}
        #: What each pair's links give each of its radars (:meth:`_partner`), and each table's
        #: ids sorted (:meth:`table`): made once per links and table.
        self._partners: dict[tuple[Key, str], tuple[SharedLinks, _Partner | None]] = {}
        self._sorted: dict[str, tuple[TrackTable, NDArray[np.str_], NDArray[np.intp]]] = {}

    def crossed(self, crossing: Crossing) -> None:
        """A crossing of this worker's correlation (in release order), with its own pairs'
        links as they were then.  Each radar's first table of the crossing's cell goes unless
        it is the crossing's own (:meth:`record`)."""
        for shared in crossing.own:
            self.history.record(shared)
        self._crossings.append(crossing.position)
        cell = self._cell(crossing.position[0])
        self._cell_crossings[cell] = crossing.position
        for radar_id, queue in self._tables.items():
            i = len(queue) - 1
            while i >= 2 and self._cell(queue[i][0]) > cell:  # (tables of later cells already)
                i -= 1
            both = i >= 2 and self._cell(queue[i - 1][0]) == self._cell(queue[i][0]) == cell
            if both and not self._at_crossing(queue[i - 1][0], radar_id, cell):
                del queue[i - 1]

    def mirror(self, shared: SharedLinks) -> None:
        """Another worker's pair's links (in the order its owner updated it)."""
        self.history.record(shared)

    def record(self, radar_id: str, time_s: float, table: TrackTable) -> None:
        """A radar's table after its batch at ``time_s``: this worker's own, or another
        worker's as its owner sent it (each radar's in its order).  Of a radar's tables in one
        cell of the grid only the last is kept, and the first while it may be the cell's
        crossing: a crossing is the first release of its cell, so the latest table at or
        before it is the crossing's own table or the last of an earlier cell.  So at most one
        table a cell once its crossing is known (:meth:`crossed`), two before."""
        queue = self._tables.setdefault(radar_id, deque())
        cell = self._cell(time_s)
        if len(queue) >= 2 and self._cell(queue[-1][0]) == cell:
            first = self._cell(queue[-2][0]) != cell
            if not (first and self._at_crossing(queue[-1][0], radar_id, cell)):
                queue.pop()  # (not, now, its cell's last, and not its crossing: never read)
        queue.append((time_s, table))

    def _cell(self, time_s: float) -> int:
        """The cell of the links' grid that data time ``time_s`` falls in."""
        return math.floor(time_s / self.grid_s)

    def _at_crossing(self, time_s: float, radar_id: str, cell: int) -> bool:
        """Whether radar ``radar_id``'s table at ``time_s`` (the first of its ``cell``) may be
        read at that cell's crossing: it is at or before it, or the crossing is not known yet."""
        crossing = self._cell_crossings.get(cell)
        return crossing is None or (time_s, radar_id) <= crossing

    def forget(self, radar_id: str) -> None:
        """A radar forgotten or dropped: its tables go (its tracks are gone with it)."""
        self._tables.pop(radar_id, None)
        self._sorted.pop(radar_id, None)

    def passed(self, position: Position) -> None:
        """Release order has reached ``position`` (a batch to track, or a table released to the
        correlation; never a place after a batch still to come): the reads move on to the
        latest crossing known at or before its lag, and what no later read needs goes."""
        due = self.due_s(position[0])
        advanced = False
        while self._crossings and self._crossings[0][0] <= due:
            self._crossing = self._crossings.popleft()
            advanced = True
        if advanced and self._crossing is not None:
            self.history.shared_at(self._crossing)  # (each pair's latest links there stay)
            read = self._cell(self._crossing[0])
            for cell in [c for c in self._cell_crossings if c < read]:
                del self._cell_crossings[cell]
            for radar_id, queue in self._tables.items():
                _drop_before(queue, radar_id, self._crossing)

    def due_s(self, time_s: float) -> float:
        """The data time through which a batch at ``time_s`` needs every pair's links."""
        return time_s - self.params.lag_s

    def references(self, radar_id: str, time_s: float) -> PartnerReferences | None:
        """The references of radar ``radar_id``'s tracks for its batch at ``time_s`` (None: no
        crossing that old yet).  Every pair's links and every table through its lag must be in
        (the engine waits for them).  Its pairs are looked at only if the tracker asks (a track
        of it in a formation has candidates)."""
        self.passed((time_s, radar_id))
        crossing = self._crossing
        if crossing is None:
            return None
        if self._state is None or self._state[0] != crossing:
            self._state = (crossing, self.history.shared_at(crossing))
        return _References(self, radar_id, crossing, self._state[1])

    def partners(self, radar_id: str, crossing: Position, state: dict[Key, SharedLinks]) -> list[_Partner]:
        """What the pairs' links of ``state`` (at ``crossing``) give radar ``radar_id``: each
        registered one with confirmed pairs whose other radar is tracked, its table then not
        empty."""
        out = []
        for key, shared in state.items():
            if radar_id not in key or not shared.links.track_a.shape[0] or shared.registration is None:
                continue
            partner = self._partner(key, shared, radar_id)
            if partner is None or partner.other not in self.tracking.tracked:  # (dropped since: none)
                continue
            if len(self.table(partner.other, crossing)[0]):
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
        self, radar_id: str, crossing: Position
    ) -> tuple[TrackTable, NDArray[np.str_], NDArray[np.intp]]:
        """Radar ``radar_id``'s table as it was at ``crossing`` in the release order (the
        latest at or before it; none: empty), its ids sorted and their rows (sorted once per
        table)."""
        queue = self._tables.get(radar_id)
        table = _EMPTY
        if queue:
            _drop_before(queue, radar_id, crossing)
            if (queue[0][0], radar_id) <= crossing:
                table = queue[0][1]
        kept = self._sorted.get(radar_id)
        if kept is None or kept[0] is not table:
            order = np.argsort(table.track_id, kind="stable")
            kept = self._sorted[radar_id] = (table, table.track_id[order], order)
        return kept


def _drop_before(queue: deque[tuple[float, TrackTable]], radar_id: str, crossing: Position) -> None:
    """A radar's tables from the latest at or before ``crossing`` on (the reads only move on)."""
    while len(queue) > 1 and (queue[1][0], radar_id) <= crossing:
        queue.popleft()


#: A radar's table before any was recorded.
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
    """:class:`~service.tracking.aid.PartnerReferences` of one radar for one batch, from every
    pair's links and every table at one crossing."""

    def __init__(
        self, aid: PartnerAid, radar_id: str, crossing: Position, state: dict[Key, SharedLinks]
    ) -> None:
        self.aid = aid
        self.radar_id = radar_id
        self.crossing = crossing
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
        for p in self.aid.partners(self.radar_id, self.crossing, self.state):
            at = find(p.own_ids, track_ids)
            has = np.flatnonzero(at >= 0)
            if not has.shape[0]:
                continue
            table, ids, order = self.aid.table(p.other, self.crossing)
            j = find(ids, p.their_ids[at[has]])
            sel, r = has[j >= 0], order[j[j >= 0]]
            if not sel.shape[0]:
                continue
            vel = table.velocity_ecef_mps[r]
            position, position_cov = moved(
                table.position_ecef_m[r],
                vel,
                table.covariance[r],
                times_s[sel] - table.time_s[r],
                self.aid.params.reference_psd,
            )
            pos, cov, reg = view_with_covariance(
                tracked[p.other].geometry, target, position, vel, position_cov, p.terms, p.terms_cov
            )
            spread = horizontal_spread(cov)
            take = (horizontal_spread(reg) <= limit) & (spread < best[sel])
            won = sel[take]
            ref[won], ref_cov[won], best[won] = pos[take], cov[take], spread[take]
        return ref, ref_cov
