"""The latest identity codes (Mode 3/A, Mode S address) of each track's plots, pure numpy.

A radar with secondary surveillance reports a Mode 3/A code and, for Mode S, the aircraft's
24-bit address with each plot (contract §4.1, ASTERIX I048/070 and I048/220).  A track carries
the code of its most recent plot that had one (``TrackBatch`` ``mode_3a`` / ``mode_s``): codes
change (a squawk is reset, a plot is garbled), and the latest is the one an operator expects.
The tracker does not read them: it reports which plots joined which track, and
:class:`TrackCodes` keeps the record here for the track manager
(:class:`~service.tracking.manager.TrackManager`), which fills the columns of its tables.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.tracking.base import PlotColumns

_NONE = np.array(None, dtype=object)

#: ``(track uids, plot times, codes)`` of the plots that joined tracks.
Chunk = tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.object_]]

#: Codes of deleted tracks are dropped in bulk once this many tracks are held per live one
#: (see ``TruthTally``: a sort per update would cost more than the rest of the work).
_DEAD_PER_LIVE = 2


class LatestCodes:
    """Per track uid, the code of its latest plot (by plot time) that carried one.

    Ties in time go to the plot that came later in the update's order (chunks in order,
    plots in order within a chunk), so the record is a function of the plot stream alone.
    """

    def __init__(self) -> None:
        self._uid = np.empty(0, dtype=np.int64)  # sorted
        self._time = np.empty(0)
        self._code = np.empty(0, dtype=object)

    def __len__(self) -> int:
        return int(self._uid.shape[0])

    def add_chunks(
        self, chunks: list[tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.object_]]]
    ) -> None:
        """Take the codes of plots ``(track uids, plot times, codes)`` chunk by chunk."""
        if not chunks:
            return
        code = np.concatenate([c for _, _, c in chunks])
        present: NDArray[np.bool_] = np.not_equal(code, _NONE, dtype=bool)
        if not present.any():
            return
        uid = np.concatenate([np.asarray(u, dtype=np.int64) for u, _, _ in chunks])[present]
        time = np.concatenate([np.asarray(t, dtype=float) for _, t, _ in chunks])[present]
        code = code[present]
        order = np.lexsort((np.arange(uid.shape[0]), time, uid))  # per uid: latest last
        uid, time, code = uid[order], time[order], code[order]
        last = np.r_[uid[1:] != uid[:-1], True]
        uid, time, code = uid[last], time[last], code[last]
        at = np.searchsorted(self._uid, uid)
        held = at < self._uid.shape[0]
        held[held] = self._uid[at[held]] == uid[held]
        newer = held.copy()
        newer[held] = time[held] >= self._time[at[held]]
        self._time, self._code = self._time.copy(), self._code.copy()
        self._time[at[newer]], self._code[at[newer]] = time[newer], code[newer]
        if not held.all():
            fresh = ~held
            self._uid = np.insert(self._uid, at[fresh], uid[fresh])
            self._time = np.insert(self._time, at[fresh], time[fresh])
            self._code = np.insert(self._code, at[fresh], code[fresh])

    def keep(self, live: NDArray[np.int64]) -> None:
        """Forget tracks not in ``live`` (uids are never reused), in bulk."""
        if self._uid.shape[0] <= _DEAD_PER_LIVE * live.shape[0]:
            return
        alive = np.isin(self._uid, np.asarray(live, dtype=np.int64))
        self._uid, self._time, self._code = self._uid[alive], self._time[alive], self._code[alive]

    def of(self, uids: NDArray[np.int64]) -> NDArray[np.object_]:
        """The latest code of each track in ``uids``, None where none was seen."""
        out = np.full(uids.shape[0], None, dtype=object)
        if self._uid.shape[0] == 0:
            return out
        at = np.minimum(np.searchsorted(self._uid, uids), self._uid.shape[0] - 1)
        ok = self._uid[at] == uids
        out[ok] = self._code[at[ok]]
        return out


class TrackCodes:
    """The identity codes of a tracker's tracks: Mode 3/A and Mode S, each the latest seen
    (:class:`LatestCodes`), taken from the plots that joined each track (the tracker's
    ``joined`` chunks) after every update."""

    NAMES = ("mode_3a", "mode_s")

    def __init__(self) -> None:
        self._codes = {name: LatestCodes() for name in self.NAMES}

    def add(self, joined: list[tuple[NDArray[np.int64], PlotColumns]]) -> None:
        """Take the codes of the plots that joined tracks (``(track uids, plots)`` chunks)."""
        for name, codes in self._codes.items():
            codes.add_chunks([(uid, plots.time_s, getattr(plots, name)) for uid, plots in joined])

    def keep(self, live: NDArray[np.int64]) -> None:
        """Forget the tracks not in ``live`` (in bulk, :meth:`LatestCodes.keep`)."""
        for codes in self._codes.values():
            codes.keep(live)

    def of(self, uids: NDArray[np.int64]) -> dict[str, NDArray[np.object_]]:
        """Each code of each track in ``uids`` (None: none seen), by column name."""
        return {name: codes.of(uids) for name, codes in self._codes.items()}
