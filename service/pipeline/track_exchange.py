"""Track states between partitioned workers: the owner sends what changed, peers rebuild.

A worker that correlates a pair whose radars it does not track needs those radars' track
tables exactly as their owner's correlation would see them: the same rows, bit for bit, in the
same (canonical, :meth:`TrackTable.by_id`) order, at the same data times.  The owner publishes
one ``TrackStates`` per released table on ``{prefix}/radar/{id}/track-states``:

* ``full``: the whole table, at a radar's first table and then at least once per
  ``full_interval_s`` of data time, so that a worker that starts late or lost a message is
  whole again by then;
* otherwise the rows that differ from the previous table (new tracks and updated ones: a
  radar's batch covers a sector of its scan, so about a tenth of its tracks) and the ids that
  left.  ``count`` is the size of the table after the change, a check.

Floats travel as JSON numbers in their shortest round-trip form, so a rebuilt table equals the
owner's.  A receiver applies a change only on top of the table of ``seq - 1``; after a gap
(a lost message, a restarted owner) it waits for the next full table and counts the gap.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.tracking.base import TrackTable
from service.wire.models import TrackStates


@dataclass(frozen=True)
class ExchangeParams:
    """How track states are sent between partitioned workers."""

    #: A radar's whole table is sent at least once per this many data seconds (and with its
    #: first table).  A change costs about a tenth of a whole table; a whole table once a
    #: minute bounds how long a worker that lost a message lacks that radar.
    full_interval_s: float = 60.0


def changed_rows(old: TrackTable, new: TrackTable) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``new`` that are not in ``old`` exactly (a mask), and the ids of ``old`` that
    are not in ``new``.  Both tables in canonical (``track_id``) order."""
    n = len(new)
    if len(old) == 0:
        return np.ones(n, dtype=bool), np.empty(0, dtype=str)
    pos = np.minimum(np.searchsorted(old.track_id, new.track_id), len(old) - 1)
    same = old.track_id[pos] == new.track_id
    same &= old.confirmed[pos] == new.confirmed
    same &= old.time_s[pos] == new.time_s
    same &= old.plots[pos] == new.plots
    same &= np.all(old.position_ecef_m[pos] == new.position_ecef_m, axis=1)
    same &= np.all(old.velocity_ecef_mps[pos] == new.velocity_ecef_mps, axis=1)
    same &= np.all(old.covariance[pos].reshape(n, 36) == new.covariance.reshape(n, 36), axis=1)
    same &= old.truth_id[pos] == new.truth_id
    removed = old.track_id[~np.isin(old.track_id, new.track_id)]
    return ~same, removed


def states_body(
    radar_id: str, seq: int, time_s: float, table: TrackTable, full: bool, removed: np.ndarray
) -> dict[str, Any]:
    """The ``TrackStates`` payload of ``table``'s rows."""
    n = len(table)
    columns: dict[str, Any] = {
        "track_id": table.track_id.tolist(),
        "confirmed": table.confirmed.tolist(),
        "time_s": table.time_s.tolist(),
        "position_ecef_m": table.position_ecef_m.tolist(),
        "velocity_ecef_mps": table.velocity_ecef_mps.tolist(),
        "covariance": table.covariance.reshape(n, 36).tolist(),
        "plots": table.plots.tolist(),
    }
    if any(t is not None for t in table.truth_id.tolist()):
        columns["truth_id"] = table.truth_id.tolist()
    return {
        "radar_id": radar_id,
        "seq": seq,
        "time_s": time_s,
        "full": full,
        "count": None,  # filled by the sender
        "removed": removed.tolist(),
        "tracks": columns,
    }


def table_of(msg: TrackStates) -> TrackTable:
    """The rows a ``TrackStates`` carries, as a table in canonical order."""
    c = msg.tracks
    n = len(c.track_id)
    truth = np.empty(n, dtype=object)
    if c.truth_id is not None:
        truth[:] = c.truth_id
    return TrackTable(
        np.asarray(c.track_id, dtype=str),
        np.asarray(c.confirmed, dtype=bool),
        np.asarray(c.time_s, dtype=float),
        np.asarray(c.position_ecef_m, dtype=float).reshape(n, 3),
        np.asarray(c.velocity_ecef_mps, dtype=float).reshape(n, 3),
        np.asarray(c.covariance, dtype=float).reshape(n, 6, 6),
        np.asarray(c.plots, dtype=np.int64),
        truth,
    ).by_id()


class StatesSender:
    """The owner's side: one ``TrackStates`` body per released table of each radar."""

    def __init__(self, params: ExchangeParams | None = None) -> None:
        self.params = params or ExchangeParams()
        # radar -> (seq of the last message, its table, data time of the last full table)
        self._sent: dict[str, tuple[int, TrackTable, float]] = {}

    def states(self, radar_id: str, table: TrackTable, time_s: float) -> dict[str, Any]:
        """The message for ``table`` (canonical order) at data time ``time_s``."""
        last = self._sent.get(radar_id)
        full = last is None or not (last[2] <= time_s < last[2] + self.params.full_interval_s)
        seq = 1 if last is None else last[0] + 1
        if full or last is None:
            body = states_body(radar_id, seq, time_s, table, True, np.empty(0, dtype=str))
            full_s = time_s
        else:
            changed, removed = changed_rows(last[1], table)
            body = states_body(radar_id, seq, time_s, table.take(changed), False, removed)
            full_s = last[2]
        body["count"] = len(table)
        self._sent[radar_id] = (seq, table, full_s)
        return body

    def forget(self, radar_id: str) -> None:
        self._sent.pop(radar_id, None)


class StatesReceiver:
    """A peer's side: every remote radar's table, rebuilt from the owner's messages."""

    def __init__(self) -> None:
        self._tables: dict[str, tuple[int, TrackTable, float]] = {}
        #: Messages that could not be applied (a gap before them), per radar.
        self.gaps: Counter[str] = Counter()

    def apply(self, msg: TrackStates) -> TrackTable | None:
        """The radar's table after ``msg``; None when it cannot be applied (counted)."""
        rows = table_of(msg)
        held = self._tables.get(msg.radar_id)
        if msg.full:
            table = rows
        elif held is None or held[0] != msg.seq - 1:
            self.gaps[msg.radar_id] += 1
            self._tables.pop(msg.radar_id, None)
            return None
        else:
            base = held[1]
            gone = np.isin(base.track_id, np.asarray(msg.removed, dtype=str)) | np.isin(
                base.track_id, rows.track_id
            )
            table = TrackTable.concat([base.take(~gone), rows]).by_id()
        if msg.count is not None and len(table) != msg.count:
            self.gaps[msg.radar_id] += 1
            self._tables.pop(msg.radar_id, None)
            return None
        self._tables[msg.radar_id] = (msg.seq, table, msg.time_s)
        return table

    def table(self, radar_id: str) -> TrackTable | None:
        held = self._tables.get(radar_id)
        return held[1] if held else None

    def latest(self, radar_id: str) -> tuple[float, TrackTable]:
        """The data time and table of the last message applied (an empty table if none)."""
        held = self._tables.get(radar_id)
        return (held[2], held[1]) if held else (0.0, TrackTable.empty())

    def radars(self) -> list[str]:
        return sorted(self._tables)

    def forget(self, radar_id: str) -> None:
        self._tables.pop(radar_id, None)
