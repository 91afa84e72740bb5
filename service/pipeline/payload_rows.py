"""``TrackBatch`` and ``PairSet`` payloads encoded row by row, each row that did not change
since its source's last encoded payload taken as it was encoded then.

A radar's batch covers a sector of its scan, so about a tenth of its tracks change from one
``TrackBatch`` to the next, yet the whole batch is published each time (the contract's
``TrackBatch`` holds every track of the radar); a pair set changed by a prompt decision gains a
few pairs.  Building a JSON-ready row per track or pair is most of the publisher's work on them
(1.5 ms for a national radar's 750 tracks).  :class:`PayloadRows` compares each row's published
values with those it encoded last for the same row (floats by their bits, so a reused row is
the row the full encoding would write) and encodes only the rows that differ: the payload is
the same bytes as encoding the whole body (``tests/test_payload_rows.py``).

Bounds: per source (a radar, a radar pair), the last encoded payload's values and row bytes
(about the size of one payload); a forgotten source's go with it (:meth:`PayloadRows.forget`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.columns import row_bits
from service.correlation.pairkeys import find, pair_keys
from service.pipeline.read_model import PairSetView, track_columns
from service.tracking.base import TrackTable
from service.wire.outputs import encode, pair_rows, track_rows

Columns = dict[str, np.ndarray]


@dataclass(frozen=True)
class _Encoded:
    """A source's last encoded payload: its row ids, each row's numbers as bits and other
    values, and each row's bytes."""

    ids: np.ndarray
    bits: np.ndarray
    values: dict[str, np.ndarray]
    rows: np.ndarray  # (bytes objects)


class PayloadRows:
    """Payloads of one kind whose list of rows is encoded row by row (thread-safe: the
    publisher reads payloads on its own thread).

    ``numbers``: the published float fields and their values per row, compared by their bits;
    ``values``: the other published fields, compared as values; ``rows_of``: the JSON-ready
    rows of some columns."""

    def __init__(
        self,
        numbers: tuple[tuple[str, int], ...],
        values: tuple[str, ...],
        rows_of: Callable[[Columns], list[dict[str, Any]]],
    ) -> None:
        self.numbers, self.values, self.rows_of = numbers, values, rows_of
        self._last: dict[Hashable, _Encoded] = {}
        self._lock = threading.Lock()

    def encode(self, source: Hashable, head: dict[str, Any], ids: np.ndarray, cols: Columns) -> bytes:
        """``encode(head)`` with its last field, an empty list, holding the rows of ``cols``
        (``ids``: each row's identity, unique): the bytes of encoding it whole."""
        bits = row_bits([(cols[k], width) for k, width in self.numbers])
        values = {k: np.asarray(cols[k]) for k in self.values}
        rows = np.empty(len(ids), dtype=object)  # each row's bytes
        with self._lock:
            last = self._last.get(source)
            fresh = np.ones(len(ids), dtype=bool)
            if last is not None and len(last.ids) and len(ids):
                at = find(last.ids, ids)
                known = np.flatnonzero(at >= 0)
                was = at[known]
                same = np.all(last.bits[was] == bits[known], axis=1)
                for k, v in values.items():
                    same &= last.values[k][was] == v[known]
                rows[known[same]] = last.rows[was[same]]
                fresh[known[same]] = False
            changed = np.flatnonzero(fresh)
            encoded = np.empty(len(changed), dtype=object)
            encoded[:] = [encode(row) for row in self.rows_of({k: v[changed] for k, v in cols.items()})]
            rows[changed] = encoded
            self._last[source] = _Encoded(ids, bits, values, rows)
        # one copy of the rows: the head and the tail joined to the first and the last row
        start = encode(head)[: -len(b"]}")]
        parts = rows.tolist()
        if len(parts) < 2:
            return start + b"".join(parts) + b"]}"
        parts[0], parts[-1] = start + parts[0], parts[-1] + b"]}"
        return b",".join(parts)

    def forget(self, source: Hashable) -> None:
        """A source that left: its last payload is no base any more."""
        with self._lock:
            self._last.pop(source, None)


class TrackPayloads(PayloadRows):
    """``TrackBatch`` payloads, one base per radar."""

    def __init__(self) -> None:
        numbers = (
            *(("time_s", 1), ("latitude_deg", 1), ("longitude_deg", 1), ("altitude_m", 1)),
            *(("position_ecef_m", 3), ("velocity_ecef_mps", 3), ("quality", 1)),
        )
        super().__init__(numbers, ("confirmed", "plots", "truth_id", "mode_3a", "mode_s"), track_rows)

    def batch(self, radar_id: str, time_s: float, table: TrackTable) -> bytes:
        """``encode(track_batch(radar_id, time_s, table))``, byte for byte."""
        cols = track_columns(table)
        head = {"radar_id": radar_id, "time_s": time_s, "tracks": []}
        return self.encode(radar_id, head, np.asarray(cols["track_id"]), cols)


class PairPayloads(PayloadRows):
    """``PairSet`` payloads (every pair), one base per radar pair."""

    def __init__(self) -> None:
        numbers = tuple(
            (k, 1) for k in ("score", "statistic", "rotation_weight", "scale", "first_time_s", "last_time_s")
        )
        super().__init__(numbers, ("confirmed", "neighbors", "hits", "basis", "held"), pair_rows)

    def pair_set(self, view: PairSetView) -> bytes:
        """``encode(view.body())``, byte for byte."""
        c = view.columns
        head = {
            "radar_a": view.radar_a,
            "radar_b": view.radar_b,
            "time_s": view.time_s,
            "method": view.method,
            "pairs": [],
        }
        return self.encode((view.radar_a, view.radar_b), head, pair_keys(c["track_a"], c["track_b"]), c)
