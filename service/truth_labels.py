"""The simulator's ``truth_id`` of each track: evaluation and display only, outside the tracker.

The contract's ``TrackBatch.truth_id`` is the most common ``truth_id`` among a track's plots
when the plots carry one.  No algorithm may read it, so the tracker never does: it reports
which plots joined which track (:attr:`service.tracking.manager.TrackManager.joined`), and
:class:`TruthLabelledTracker` keeps the tally here and writes the label column of the
tracker's :class:`~service.tracking.base.TrackTable`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from service.geo import Site
from service.tracking.base import PlotColumns, Tracker, TrackTable
from service.tracking.manager import TrackManager


class TruthTally:
    """Plot counts per (track uid, truth name); the most common name is the track's truth."""

    def __init__(self) -> None:
        self._names: list[str] = []
        self._codes: dict[str, int] = {}
        # (track uid, truth code, plots), one row per pair seen
        self._tally = (np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int64))

    def _encode(self, truth: NDArray[np.object_]) -> NDArray[np.int64]:
        """Integer code per plot, -1 where the plot has no truth."""
        codes = np.full(truth.shape[0], -1, dtype=np.int64)
        present = np.array([t is not None for t in truth.tolist()], dtype=bool)
        if present.any():
            names, inv = np.unique(truth[present].astype(str), return_inverse=True)
            lut = np.empty(names.shape[0], dtype=np.int64)
            for q, name in enumerate(names.tolist()):  # loop over distinct names only
                code = self._codes.get(name)
                if code is None:
                    code = len(self._names)
                    self._codes[name] = code
                    self._names.append(name)
                lut[q] = code
            codes[present] = lut[inv]
        return codes

    def add(self, uid: NDArray[np.int64], truth: NDArray[np.object_]) -> None:
        """Count plots with labels ``truth`` for tracks ``uid`` (one entry per plot)."""
        code = self._encode(truth)
        have = code >= 0
        if not have.any():
            return
        u0, c0, k0 = self._tally
        u = np.concatenate([u0, uid[have]])
        c = np.concatenate([c0, code[have]])
        k = np.concatenate([k0, np.ones(int(have.sum()), dtype=np.int64)])
        key = u * (1 << 32) + c
        uk, inv = np.unique(key, return_inverse=True)
        self._tally = (uk >> 32, uk & 0xFFFFFFFF, np.bincount(inv, weights=k).astype(np.int64))

    def keep(self, live: NDArray[np.int64]) -> None:
        """Forget the tracks not in ``live`` (deleted tracks; uids are never reused)."""
        u, c, k = self._tally
        alive = np.isin(u, live)
        self._tally = (u[alive], c[alive], k[alive])

    def of(self, uids: NDArray[np.int64]) -> NDArray[np.object_]:
        """The most common truth name of each track in ``uids`` (sorted), None where none."""
        out = np.full(uids.shape[0], None, dtype=object)
        u, c, k = self._tally
        if u.shape[0] == 0:
            return out
        order = np.lexsort((c, -k, u))  # per uid: most plots first, ties by first-seen code
        u, c = u[order], c[order]
        first = np.ones(u.shape[0], dtype=bool)
        first[1:] = u[1:] != u[:-1]
        u, c = u[first], c[first]
        row = np.searchsorted(uids, u)
        ok = (row < uids.shape[0]) & (uids[np.minimum(row, max(uids.shape[0] - 1, 0))] == u)
        out[row[ok]] = np.array(self._names, dtype=object)[c[ok]]
        return out


class TruthLabelledTracker(Tracker):
    """A :class:`TrackManager` whose tracks carry the truth of their plots (``truth_id``)."""

    def __init__(self, inner: TrackManager) -> None:
        self.inner = inner
        super().__init__(inner.site, inner.window_s)
        self.tally = TruthTally()

    @property
    def site(self) -> Site:
        return self.inner.site

    @site.setter
    def site(self, value: Site) -> None:  # a radar's geometry can be replaced (engine)
        self.inner.site = value

    def update(self, plots: PlotColumns, time_s: float) -> None:
        self.inner.update(plots, time_s)
        for uid, joined in self.inner.joined:
            self.tally.add(uid, joined.truth_id)
        self.tally.keep(self.inner.uids)

    def tracks(self) -> TrackTable:
        table = self.inner.tracks()
        return replace(table, truth_id=self.tally.of(self.inner.uids)) if len(table) else table

    @property
    def window_plots(self) -> int:
        return self.inner.window_plots

    @property
    def window_evicted(self) -> int:
        return self.inner.window_evicted
