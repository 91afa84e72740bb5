"""The simulator's ``truth_id`` of each track: evaluation and display only, outside the tracker.

The contract's ``TrackBatch.truth_id`` is the most common ``truth_id`` among a track's plots
when the plots carry one.  No algorithm may read it, so the tracker never does: it reports
which plots joined which track (:attr:`service.tracking.manager.TrackManager.joined`), and
:class:`TruthLabelledTracker` keeps the tally here and writes the label column of the
tracker's :class:`~service.tracking.base.TrackTable`.  Input without ``truth_id`` (real radar
data) costs one test of each batch's column: the tally stays empty and is never consulted.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.geo import Site
from service.tracking.aid import PartnerReferences
from service.tracking.base import PlotColumns, Tracker, TrackTable
from service.tracking.manager import TrackManager

_NONE = np.array(None, dtype=object)

#: The tally forgets deleted tracks only once it holds this many tracks per live one: a
#: sort and two searches at every update cost more than the rest of the tally's work, and
#: the memory stays within a few times that of the live tracks.
_DEAD_PER_LIVE = 2
#: A track counts as on an aircraft for :attr:`TruthTally.joined_led` once that aircraft leads
#: its plots with at least this many (a track's first plots name its aircraft by chance).
LED_PLOTS = 3


def _find(sorted_values: NDArray[Any], values: NDArray[Any]) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """Insertion point of each of ``values`` in ``sorted_values``, and whether it is there."""
    at = np.searchsorted(sorted_values, values)
    found = at < sorted_values.shape[0]
    found[found] = sorted_values[at[found]] == values[found]
    return at, found


class TruthTally:
    """Plot counts per (track uid, truth name); the most common name is the track's truth.

    Names get integer codes in the order they are first seen (a batch's new names in the order
    of its chunks, sorted by name within a chunk), and ties between equally common names go to
    the lowest code.  Counts only grow while a track lives, so each track's leader is kept up
    to date from the pairs a batch adds: :meth:`of` is a lookup, not a sort of the tally.

    It also counts how the plots it is given fall (evaluation: the study of formations): of the
    plots that joined a track already on an aircraft (its leader with ``LED_PLOTS`` plots or
    more), :attr:`joined_led`, those of another aircraft, :attr:`joined_other`, and of these,
    those whose track's own aircraft had a plot in the same batch, :attr:`joined_other_seen`
    (the batch's labels given to :meth:`add_chunks`).
    """

    def __init__(self) -> None:
        self._names = np.empty(0, dtype=object)  # code -> name
        self._sorted_names = np.empty(0, dtype=str)  # the names, sorted, for lookups
        self._sorted_codes = np.empty(0, dtype=np.int64)
        # (track uid << 32 | truth code) -> plots, sorted by key
        self._key = np.empty(0, dtype=np.int64)
        self._count = np.empty(0, dtype=np.int64)
        # per track, sorted by uid: its most common code and that code's plots
        self._lead_uid = np.empty(0, dtype=np.int64)
        self._lead_code = np.empty(0, dtype=np.int64)
        self._lead_count = np.empty(0, dtype=np.int64)
        #: Plots with a truth that joined a track on an aircraft, and those of another aircraft.
        self.joined_led = 0
        self.joined_other = 0
        self.joined_other_seen = 0

    def __len__(self) -> int:
        """Tracks with a truth (0: no plot carried one yet)."""
        return int(self._lead_uid.shape[0])

    def _encode(self, truth: NDArray[np.object_], chunk: NDArray[np.int64]) -> NDArray[np.int64]:
        """Integer code per plot, -1 where the plot has no truth; ``chunk``: each plot's chunk
        (new names are coded in the order of the chunk that first holds them, then by name)."""
        codes = np.full(truth.shape[0], -1, dtype=np.int64)
        present: NDArray[np.bool_] = np.not_equal(truth, _NONE, dtype=bool)  # per-element ``!= None``
        if not present.any():
            return codes
        names, inv = np.unique(truth[present].astype(str), return_inverse=True)
        where, known = _find(self._sorted_names, names)
        lut = np.full(names.shape[0], -1, dtype=np.int64)
        lut[known] = self._sorted_codes[where[known]]
        if not known.all():
            first = np.full(names.shape[0], np.iinfo(np.int64).max, dtype=np.int64)
            np.minimum.at(first, inv, chunk[present])
            new = np.flatnonzero(~known)
            new = new[np.lexsort((new, first[new]))]  # by first chunk, then by name
            lut[new] = self._names.shape[0] + np.arange(new.shape[0])
            self._names = np.concatenate([self._names, names[new].astype(object)])
            all_names = np.concatenate([self._sorted_names, names[new]])
            all_codes = np.concatenate([self._sorted_codes, lut[new]])
            order = np.argsort(all_names, kind="stable")
            self._sorted_names, self._sorted_codes = all_names[order], all_codes[order]
        codes[present] = lut[inv]
        return codes

    def add(self, uid: NDArray[np.int64], truth: NDArray[np.object_]) -> None:
        """Count plots with labels ``truth`` for tracks ``uid`` (one entry per plot)."""
        self.add_chunks([(uid, truth)])

    def add_chunks(
        self,
        chunks: list[tuple[NDArray[np.int64], NDArray[np.object_]]],
        batch: NDArray[np.object_] | None = None,
    ) -> None:
        """:meth:`add` of each ``(uid, truth)`` chunk in turn, encoded and counted at once;
        ``batch``: the labels of every plot of the batch they came in (for
        :attr:`joined_other_seen`)."""
        if not chunks:
            return
        uid = np.concatenate([np.asarray(u, dtype=np.int64) for u, _ in chunks])
        truth = np.concatenate([t for _, t in chunks])
        chunk = np.repeat(np.arange(len(chunks), dtype=np.int64), [len(t) for _, t in chunks])
        code = self._encode(truth, chunk)
        have = code >= 0
        if not have.any():
            return
        at, held = _find(self._lead_uid, uid[have])
        led = held.copy()
        led[held] = self._lead_count[at[held]] >= LED_PLOTS
        self.joined_led += int(np.count_nonzero(led))
        own = self._lead_code[at[led]]
        own = own[own != code[have][led]]
        self.joined_other += int(own.shape[0])
        if own.shape[0] and batch is not None:
            labels = batch[np.not_equal(batch, _NONE, dtype=bool)].astype(str)
            where, known = _find(self._sorted_names, np.unique(labels))
            self.joined_other_seen += int(np.count_nonzero(np.isin(own, self._sorted_codes[where[known]])))
        key, plots = np.unique(uid[have] * (1 << 32) + code[have], return_counts=True)
        at, seen = _find(self._key, key)
        count = self._count.copy()
        count[at[seen]] += plots[seen]
        total = plots.copy()
        total[seen] = count[at[seen]]
        if seen.all():
            self._count = count
        else:
            self._key = np.insert(self._key, at[~seen], key[~seen])
            self._count = np.insert(count, at[~seen], plots[~seen])
        self._lead(key >> 32, key & 0xFFFFFFFF, total)

    def _lead(self, uid: NDArray[np.int64], code: NDArray[np.int64], count: NDArray[np.int64]) -> None:
        """Update the leaders with the new totals ``count`` of pairs ``(uid, code)``: a track's
        leader is its old one or one of its pairs that grew (the others did not change)."""
        at, held = _find(self._lead_uid, uid)
        if held.all() and bool(np.all(uid[1:] != uid[:-1])):  # the usual batch: one pair per led track
            k0, c0 = self._lead_count[at], self._lead_code[at]
            wins = (count > k0) | ((count == k0) & (code < c0))
            self._lead_code, self._lead_count = self._lead_code.copy(), self._lead_count.copy()
            self._lead_code[at[wins]], self._lead_count[at[wins]] = code[wins], count[wins]
            return
        old = np.unique(at[held])
        u = np.concatenate([uid, self._lead_uid[old]])
        c = np.concatenate([code, self._lead_code[old]])
        k = np.concatenate([count, self._lead_count[old]])
        order = np.lexsort((c, -k, u))  # per uid: most plots first, ties by first-seen code
        u, c, k = u[order], c[order], k[order]
        first = np.ones(u.shape[0], dtype=bool)
        first[1:] = u[1:] != u[:-1]
        u, c, k = u[first], c[first], k[first]
        at, held = _find(self._lead_uid, u)
        lead_code, lead_count = self._lead_code.copy(), self._lead_count.copy()
        lead_code[at[held]], lead_count[at[held]] = c[held], k[held]
        if held.all():
            self._lead_code, self._lead_count = lead_code, lead_count
            return
        new = at[~held]
        self._lead_uid = np.insert(self._lead_uid, new, u[~held])
        self._lead_code = np.insert(lead_code, new, c[~held])
        self._lead_count = np.insert(lead_count, new, k[~held])

    def keep(self, live: NDArray[np.int64]) -> None:
        """Forget the tracks not in ``live`` (deleted tracks; uids are never reused), once
        more than ``_DEAD_PER_LIVE`` tracks are held per live one: a deleted track's counts
        are never read again, so dropping them in bulk changes no label."""
        if self._lead_uid.shape[0] <= _DEAD_PER_LIVE * live.shape[0]:
            return
        live = np.sort(np.asarray(live, dtype=np.int64))
        alive = _find(live, self._key >> 32)[1]
        self._key, self._count = self._key[alive], self._count[alive]
        alive = _find(live, self._lead_uid)[1]
        self._lead_uid, self._lead_code, self._lead_count = (
            self._lead_uid[alive],
            self._lead_code[alive],
            self._lead_count[alive],
        )

    def of(self, uids: NDArray[np.int64]) -> NDArray[np.object_]:
        """The most common truth name of each track in ``uids``, None where none."""
        out = np.full(uids.shape[0], None, dtype=object)
        at, ok = _find(self._lead_uid, uids)
        out[ok] = self._names[self._lead_code[at[ok]]]
        return out


class TruthLabelledTracker(Tracker):
    """A :class:`TrackManager` whose tracks carry the truth of their plots (``truth_id``), from
    the plots that joined each track."""

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

    def follow(self, site: Site) -> None:
        self.inner.follow(site)
        self.window_s = self.inner.window_s

    def update(self, plots: PlotColumns, time_s: float) -> None:
        self.inner.update(plots, time_s)
        joined = self.inner.joined
        if np.not_equal(plots.truth_id, _NONE, dtype=bool).any():  # (real radar data: never)
            self.tally.add_chunks([(uid, p.truth_id) for uid, p in joined], plots.truth_id)
        if self.tally:
            self.tally.keep(self.inner.uids)

    def take_aid(self, partners: PartnerReferences | None) -> None:
        self.inner.take_aid(partners)

    def wants_aid(self, time_s: float) -> bool:
        return self.inner.wants_aid(time_s)

    def drop_tracks(self) -> None:
        self.inner.drop_tracks()
        self.tally.keep(self.inner.uids)

    def tracks(self) -> TrackTable:
        table = self.inner.tracks()
        if not len(table):
            return table
        if not self.tally:
            return table  # (no plot carried a truth_id: the column stays None)
        return replace(table, truth_id=self.tally.of(self.inner.uids))

    @property
    def window_plots(self) -> int:
        return self.inner.window_plots

    @property
    def window_evicted(self) -> int:
        return self.inner.window_evicted

    @property
    def plots_coincident(self) -> int:
        return self.inner.plots_coincident

    @property
    def aided_associations(self) -> int:
        return self.inner.aided_associations

    @property
    def pd_measured(self) -> float | None:
        return self.inner.pd_measured

    @property
    def misses_to_delete(self) -> int | None:
        return self.inner.misses_to_delete

    @property
    def scan_period_observed_s(self) -> float | None:
        return self.inner.scan_period_observed_s

    @property
    def measurement_sigma_scale(self) -> float:
        return self.inner.measurement_sigma_scale
