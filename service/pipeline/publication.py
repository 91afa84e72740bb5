"""What the service has published, kept whole: no output names a track its tables do not hold.

Track tables change with every released batch; pair sets change when their pair is correlated
(a scan later, or later still when the correlation runs in its own process) and system tracks
when they are rebuilt.  A track that goes must leave every pair and system track in the same
release, so :class:`Publication` holds the latest published pair set of every source pair and
the latest system tracks, and

* at every table of a radar (its own batches, or another worker's table), in the order the
  correlation takes them, takes the tracks that went out of every pair set and system track
  that named them, publishing the changed ones *before* the table itself (a subscriber never
  holds a table and a pair set that disagree);
* publishes each answer of the correlation right after the table it answered for (the engine
  keeps them in step), so an answer names only tracks of tables already published; as a guard,
  an answer older than a table that lost tracks loses them too.  System tracks are held to
  every table that lost tracks at their data time as well: a picture is taken at one radar's
  release and a partitioned worker 1 draws it only once the other workers have correlated
  past its time (:mod:`.system_stage`), so the tables of the same data time released after
  that radar's (the merge's order) are published before it, not after.

A track that a pair names was confirmed before the pair was made, so it is in a table already
published: additions need no care.  Cost: a table compares its ids with the previous table's
(both in id order); only a table that lost tracks touches the pair sets, and an answer is
looked at again only if a table lost tracks since its data time.
"""

from __future__ import annotations

import numpy as np

from service.correlation.pairkeys import isin_sorted
from service.pipeline.payload_rows import PairPayloads, TrackPayloads
from service.pipeline.read_model import PairSetView, SystemTrackView, track_batch
from service.tracking.base import TrackTable
from service.wire.keys import Keys
from service.wire.outgoing import Outgoing

Key = tuple[str, str]


class Publication:
    """The latest pair sets and system tracks, held to the latest track tables."""

    def __init__(self, keys: Keys) -> None:
        self.keys = keys
        self.views: dict[Key, PairSetView] = {}
        self.system: SystemTrackView | None = None
        #: Every radar's table as last published (data time, table in id order).
        self.tables: dict[str, tuple[float, TrackTable]] = {}
        #: ... and its track ids (sorted).
        self._ids: dict[str, np.ndarray] = {}
        #: The data time of each radar's latest table that lost tracks.
        self._lost_s: dict[str, float] = {}
        #: ``TrackBatch`` and ``PairSet`` payloads, each row encoded once while it does not change.
        self.track_payloads = TrackPayloads()
        self.pair_payloads = PairPayloads()

    def tracks(self, radar_id: str, time_s: float, table: TrackTable, own: bool) -> list[Outgoing]:
        """A radar's new tracks (rows in id order, :meth:`TrackTable.by_id`): the pair sets and
        system tracks that lose tracks by it, then (``own``: a radar this worker tracks) its
        ``TrackBatch``."""
        out = self._held_to(radar_id, time_s, table)
        if own:
            out.append(
                Outgoing(
                    self.keys.tracks(radar_id),
                    lambda: track_batch(radar_id, time_s, table),
                    lambda: self.track_payloads.batch(radar_id, time_s, table),
                )
            )
        return out

    def _held_to(self, radar_id: str, time_s: float, table: TrackTable) -> list[Outgoing]:
        ids = table.track_id
        old = self._ids.get(radar_id)
        self._ids[radar_id] = ids
        self.tables[radar_id] = (time_s, table)
        if old is None:
            return []
        gone = old[~isin_sorted(old, ids)]  # (sorted, as ``old``; a few)
        if gone.size == 0:
            return []
        self._lost_s[radar_id] = time_s
        # Every view held names only tracks of the radar's previous table (held to it then, or
        # made from tables published before it): taking out the gone ones holds it to this one.
        out = []
        for key, view in list(self.views.items()):
            if radar_id in key:
                held = view.without(key.index(radar_id), gone)
                if held is not view:
                    self.views[key] = held
                    out.append(self._pairs_out(key, held))
        if self.system is not None:
            held_system = self.system.without(radar_id, gone)
            if held_system is not self.system:
                self.system = held_system
                out.append(self._system_out(held_system))
        return out

    def pairs(self, key: Key, view: PairSetView) -> Outgoing:
        """A pair set the correlation answered, held to the tables as they are now."""
        for side, source in enumerate(key):
            if self._lost_s.get(source, -np.inf) > view.time_s:
                view = view.held(side, self._ids[source])
        self.views[key] = view
        return self._pairs_out(key, view)

    def _pairs_out(self, key: Key, view: PairSetView) -> Outgoing:
        return Outgoing(self.keys.pairs(*key), view.body, lambda: self.pair_payloads.pair_set(view))

    def system_tracks(self, view: SystemTrackView) -> Outgoing:
        """System tracks the correlation rebuilt, held to the tables as they are now: to every
        table that lost tracks at or after their data time (one of their own time may have
        been released after the picture was taken, and published before it was drawn)."""
        for source, lost_s in self._lost_s.items():
            if lost_s >= view.time_s:
                view = view.held(source, self._ids[source])
        self.system = view
        return self._system_out(view)

    def _system_out(self, view: SystemTrackView) -> Outgoing:
        return Outgoing(self.keys.system_tracks, lambda: view.body("confirmed"))

    def forget(self, source_id: str) -> list[Outgoing]:
        """A source left: its tables and pair sets go (its pairs are gone from correlation),
        and its tracks leave the system tracks (published if that changed them)."""
        self._ids.pop(source_id, None)
        self.tables.pop(source_id, None)
        self._lost_s.pop(source_id, None)
        self.track_payloads.forget(source_id)
        for key in [k for k in self.views if source_id in k]:
            del self.views[key]
            self.pair_payloads.forget(key)
        if self.system is not None:
            held = self.system.held(source_id, np.empty(0, dtype=str))
            if held is not self.system:
                self.system = held
                return [self._system_out(held)]
        return []

    def pair_views(self) -> list[PairSetView]:
        return [self.views[k] for k in sorted(self.views)]
