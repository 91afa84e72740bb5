"""The read model: immutable state for readers; contract JSON built when first read.

A snapshot holds references to immutable columns (a radar's :class:`TrackTable`, a copy of a
pair book's columns), never JSON: a ``TrackBatch`` or ``PairSet`` is built only when somebody
reads it (an HTTP handler, a queryable, a publisher with subscribers) and then kept.  Taking a
snapshot therefore costs in proportion to the number of radars and pairs, not tracks.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.correlation.pairkeys import comparable, find, isin_sorted
from service.geo import ecef_to_geodetic
from service.tracking.base import TrackTable
from service.wire.models import RadarSite, RadarStatus
from service.wire.outputs import pair_rows, track_rows

_NONE = np.array(None, dtype=object)
#: A source whose track ids are Mode S addresses (ADS-B), as :meth:`Snapshot.identity` keys it.
_ADSB = object()


def selects(radars: tuple[str | None, str | None], key: tuple[str, str]) -> bool:
    """Whether ``GET /pairs`` with ``radar_a``, ``radar_b`` (``radars``; None: not given) asks
    for the pair set of ``key``: with one radar, every pair set with it; with two, the pair set
    of the two, in either order (none for a radar with itself)."""
    given = [x for x in radars if x is not None]
    return sorted(given) == sorted(key) if len(given) == 2 else all(x in key for x in given)


def track_batch(radar_id: str, time_s: float, tracks: TrackTable, status: str = "all") -> dict[str, Any]:
    """The contract's ``TrackBatch`` for a radar's tracks (``status``: confirmed, tentative, all)."""
    if status == "confirmed":
        tracks = tracks.take(tracks.confirmed)
    elif status == "tentative":
        tracks = tracks.take(~tracks.confirmed)
    return {"radar_id": radar_id, "time_s": time_s, "tracks": track_rows(track_columns(tracks))}


def track_columns(tracks: TrackTable) -> dict[str, np.ndarray]:
    """The columns of a ``TrackBatch``'s tracks (:func:`~service.wire.outputs.track_rows`)."""
    lat, lon, alt = ecef_to_geodetic(tracks.position_ecef_m)
    return {
        "track_id": tracks.track_id,
        "confirmed": tracks.confirmed,
        "time_s": tracks.time_s,
        "latitude_deg": np.atleast_1d(lat),
        "longitude_deg": np.atleast_1d(lon),
        "altitude_m": np.atleast_1d(alt),
        "position_ecef_m": tracks.position_ecef_m,
        "velocity_ecef_mps": tracks.velocity_ecef_mps,
        "plots": tracks.plots,
        "truth_id": tracks.truth_id,
        "mode_3a": tracks.mode_3a,
        "mode_s": tracks.mode_s,
        "quality": tracks.quality,
    }


@dataclass(frozen=True)
class PairSetView:
    """One radar pair's book at one update: copied columns, the ``PairSet`` built when read."""

    radar_a: str
    radar_b: str
    time_s: float
    method: str
    columns: dict[str, np.ndarray]
    confirmed: int
    tentative: int
    #: Of the tentative pairs, those held (``PairBook.held``).
    held_pairs: int = 0
    _cache: dict[str, dict[str, Any]] = field(default_factory=dict, compare=False, repr=False)
    #: The identity counts of the confirmed pairs with the Mode S sources they were last
    #: counted against, one entry once counted (:meth:`Snapshot.identity`): a view outlives
    #: many snapshots.
    _identity: list[tuple[Any, Any, int, int]] = field(default_factory=list, compare=False, repr=False)

    @staticmethod
    def of(key: tuple[str, str], corr: Any, time_s: float) -> PairSetView:
        """Capture ``corr``'s book (a :class:`~service.correlation.PairCorrelator`) for ``key``."""
        book = corr.book
        swap = corr.site_a.site_id != key[0]
        ta, tb = (book.track_b, book.track_a) if swap else (book.track_a, book.track_b)
        order = np.lexsort(comparable(tb, ta))
        cols = {
            "track_a": ta[order],
            "track_b": tb[order],
            "confirmed": book.confirmed[order],
            "score": book.published_score[order],
            "neighbors": book.neighbors[order],
            "hits": book.hits[order],
            "basis": book.basis[order],
            "held": book.held[order],
            **{k: v[order] for k, v in book.cols.items()},  # fancy indexing copies
        }
        n_conf = int(np.count_nonzero(cols["confirmed"]))
        n_held = int(np.count_nonzero(cols["held"]))
        return PairSetView(key[0], key[1], time_s, corr.method, cols, n_conf, len(order) - n_conf, n_held)

    def held(self, side: int, held_ids: np.ndarray) -> PairSetView:
        """The view without the pairs whose track of side ``side`` (0: A, 1: B) is not among
        ``held_ids`` (sorted): the same view when none goes."""
        return self._kept(isin_sorted(self.columns["track_a" if side == 0 else "track_b"], held_ids))

    def without(self, side: int, gone_ids: np.ndarray) -> PairSetView:
        """The view without the pairs whose track of side ``side`` is among ``gone_ids`` (sorted;
        a table's lost tracks, a few: cheaper than :meth:`held` against the whole table when the
        view names only tracks of the table before): the same view when none goes."""
        return self._kept(~isin_sorted(self.columns["track_a" if side == 0 else "track_b"], gone_ids))

    def _kept(self, keep: np.ndarray) -> PairSetView:
        if keep.all():
            return self
        cols = {k: v[keep] for k, v in self.columns.items()}
        n_conf = int(np.count_nonzero(cols["confirmed"]))
        return PairSetView(
            self.radar_a,
            self.radar_b,
            self.time_s,
            self.method,
            cols,
            n_conf,
            len(cols["confirmed"]) - n_conf,
            int(np.count_nonzero(cols["held"])),
        )

    def body(self, status: str = "all") -> dict[str, Any]:
        """The contract's ``PairSet``, pairs filtered by ``status`` (built once per status)."""
        got = self._cache.get(status)
        if got is None:
            if "all" not in self._cache:
                self._cache["all"] = {
                    "radar_a": self.radar_a,
                    "radar_b": self.radar_b,
                    "time_s": self.time_s,
                    "method": self.method,
                    "pairs": pair_rows(self.columns),
                }
            got = self._cache["all"]
            if status != "all":
                got = {**got, "pairs": [p for p in got["pairs"] if p["status"] == status]}
                self._cache[status] = got
        return got


@dataclass(frozen=True)
class SystemTrackView:
    """The system tracks of one update: copied columns, the ``SystemTrackBatch`` built when read."""

    time_s: float
    number: np.ndarray
    confirmed: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    sigma_m: np.ndarray
    #: The members ``(source, track id)``, grouped by system track (in source order within
    #: one); system track ``k``'s are rows ``bounds[k]:bounds[k + 1]``.
    member_source: np.ndarray
    member_track: np.ndarray
    bounds: np.ndarray
    _cache: dict[str, dict[str, Any]] = field(default_factory=dict, compare=False, repr=False)

    @staticmethod
    def of(time_s: float, tracks: Any, members: Any) -> SystemTrackView:
        """From :class:`~service.fusion.system_tracks.SystemTracks` and their ``Members``."""
        rows = np.flatnonzero(tracks.member_group >= 0)
        rows = rows[np.lexsort((members.source[rows], tracks.member_group[rows]))]
        bounds = np.searchsorted(tracks.member_group[rows], np.arange(len(tracks) + 1))
        return SystemTrackView(
            time_s,
            tracks.number.copy(),
            tracks.confirmed.copy(),
            tracks.position.copy(),
            tracks.velocity.copy(),
            tracks.position_sigma_m(),
            members.source[rows],
            members.track_id[rows],
            bounds,
        )

    def __len__(self) -> int:
        return int(self.number.shape[0])

    def held(self, source_id: str, held_ids: np.ndarray) -> SystemTrackView:
        """The view without the members of ``source_id`` that are not among ``held_ids``
        (sorted), and without the system tracks left with no member: the same view when none
        goes.  The states stay as fused (until the next rebuild)."""
        return self._kept(source_id, held_ids, True)

    def without(self, source_id: str, gone_ids: np.ndarray) -> SystemTrackView:
        """The view without the members of ``source_id`` among ``gone_ids`` (sorted; see
        :meth:`PairSetView.without`), and the system tracks left with no member."""
        return self._kept(source_id, gone_ids, False)

    def _kept(self, source_id: str, ids: np.ndarray, held: bool) -> SystemTrackView:
        """Members of ``source_id`` kept where their track is among ``ids`` (``held``) or is not."""
        mine = self.member_source == source_id
        if not mine.any():
            return self
        keep = ~mine
        keep[mine] = isin_sorted(self.member_track[mine], ids) == held
        if keep.all():
            return self
        group = np.repeat(np.arange(len(self)), np.diff(self.bounds))
        counts = np.bincount(group[keep], minlength=len(self))
        alive = counts > 0
        bounds = np.concatenate([[0], np.cumsum(counts[alive])])
        return SystemTrackView(
            self.time_s,
            self.number[alive],
            self.confirmed[alive],
            self.position[alive],
            self.velocity[alive],
            self.sigma_m[alive],
            self.member_source[keep],
            self.member_track[keep],
            bounds,
        )

    def body(self, status: str = "confirmed") -> dict[str, Any]:
        """The contract's ``SystemTrackBatch``, tracks filtered by ``status``."""
        got = self._cache.get(status)
        if got is not None:
            return got
        keep = np.ones(len(self), dtype=bool)
        if status == "confirmed":
            keep = self.confirmed
        elif status == "tentative":
            keep = ~self.confirmed
        idx = np.flatnonzero(keep)
        lat, lon, alt = (np.atleast_1d(c) for c in ecef_to_geodetic(self.position[idx].reshape(-1, 3)))
        tracks = [
            {
                "system_track_id": f"T-{n}",
                "status": "confirmed" if c else "tentative",
                "time_s": self.time_s,
                "latitude_deg": la,
                "longitude_deg": lo,
                "altitude_m": al,
                "position_ecef_m": p,
                "velocity_ecef_mps": v,
                "position_sigma_m": s,
                "members": [
                    {"radar_id": src, "track_id": tid}
                    for src, tid in zip(
                        self.member_source[self.bounds[k] : self.bounds[k + 1]].tolist(),
                        self.member_track[self.bounds[k] : self.bounds[k + 1]].tolist(),
                        strict=True,
                    )
                ],
            }
            for k, n, c, la, lo, al, p, v, s in zip(
                idx.tolist(),
                self.number[idx].tolist(),
                self.confirmed[idx].tolist(),
                lat.tolist(),
                lon.tolist(),
                alt.tolist(),
                self.position[idx].tolist(),
                self.velocity[idx].tolist(),
                self.sigma_m[idx].tolist(),
                strict=True,
            )
        ]
        got = self._cache[status] = {"time_s": self.time_s, "system_tracks": tracks}
        return got


@dataclass(frozen=True)
class RadarRow:
    """One radar's site and counters (``/radars``, ``/status``), in the wire's own models."""

    site: RadarSite
    status: RadarStatus


@dataclass(frozen=True)
class Snapshot:
    """Immutable state for readers (HTTP handlers, queryables) on other threads."""

    tracks: dict[str, tuple[float, TrackTable]]
    radar_rows: list[RadarRow]
    pair_views: list[PairSetView]
    biases_all: list[dict[str, Any]]
    correlation: dict[str, Any]
    rejected: dict[str, int]
    method: str
    prefix: str
    #: Every known site (a partitioned worker knows every radar's, tracks only its own).
    sites: dict[str, RadarSite] = field(default_factory=dict)
    #: Partitioned: how far this worker has got (``Engine.progress``).
    progress: dict[str, Any] = field(default_factory=dict)
    #: The ADS-B sources (their track ids are Mode S addresses).
    adsb_sources: frozenset[str] = frozenset()
    #: The latest system tracks (None before the first).
    system: SystemTrackView | None = None
    #: The data time up to which these outputs reflect every input processed (None: none yet).
    outputs_time_s: float | None = None
    #: Each radar's performance against the references (a ``PerformanceView``; None: none).
    performance: Any = None
    _batches: dict[tuple[str, str], dict[str, Any]] = field(default_factory=dict, compare=False, repr=False)
    #: Per source: whether its table carries any Mode S address (:meth:`_mode_s_source`).
    _carries_mode_s: dict[str, bool] = field(default_factory=dict, compare=False, repr=False)

    def track_batch(self, radar_id: str, status: str = "confirmed") -> dict[str, Any] | None:
        """The radar's ``TrackBatch`` (None: no such radar).  A radar known by its site whose
        first table is not out yet (no batch, or its batches waiting for the other sources'
        clocks) has no tracks: an empty batch at data time 0."""
        if radar_id not in self.tracks and radar_id not in self.sites:
            return None
        got = self._batches.get((radar_id, status))
        if got is None:
            time_s, table = self.tracks.get(radar_id, (0.0, TrackTable.empty()))
            got = self._batches[(radar_id, status)] = track_batch(radar_id, time_s, table, status)
        return got

    def track_batches(self, status: str = "all") -> list[dict[str, Any]]:
        return [b for rid in self.tracks if (b := self.track_batch(rid, status)) is not None]

    def radar_performance(self, radar_id: str) -> dict[str, Any] | None:
        """The radar's ``RadarPerformance`` (contract §5.3); None: no such radar."""
        if radar_id not in self.sites and radar_id not in self.tracks:
            return None
        if self.performance is None:
            return None
        got: dict[str, Any] = self.performance.of(radar_id)
        return got

    def pair_sets(
        self, radar_a: str | None = None, radar_b: str | None = None, status: str = "confirmed"
    ) -> list[dict[str, Any]]:
        """Pair sets involving both given radars (either order), pairs filtered by ``status``."""
        return [
            v.body(status) for v in self.pair_views if selects((radar_a, radar_b), (v.radar_a, v.radar_b))
        ]

    def biases(self) -> list[dict[str, Any]]:
        return list(self.biases_all)

    def system_tracks(self, status: str = "confirmed") -> dict[str, Any]:
        """``SystemTrackBatch`` (``time_s`` null before the first system tracks)."""
        if self.system is None:
            return {"time_s": None, "system_tracks": []}
        return self.system.body(status)

    def status_core(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "prefix": self.prefix,
            "radars": [r.status.model_dump() for r in self.radar_rows],
            "pairs_confirmed": sum(v.confirmed for v in self.pair_views),
            "pairs_tentative": sum(v.tentative for v in self.pair_views),
            "pairs_held": sum(v.held_pairs for v in self.pair_views),
            "correlation": self.correlation,
            "outputs_time_s": self.outputs_time_s,
            "rejected": self.rejected,
            "identity": self.identity(),
        }

    def _mode_s_source(self, source_id: str) -> Any:
        """Where a source's Mode S addresses come from: ``_ADSB`` (its track ids), its table
        (a track's ``mode_s``), or None (none known, or a table that carries none)."""
        if source_id in self.adsb_sources:
            return _ADSB
        held = self.tracks.get(source_id)
        if held is None:
            return None
        # A table without any address (most radars' plots carry none) gives none: its pairs
        # are then counted without a search (a status is built every second; tables change
        # with every batch).
        carries = self._carries_mode_s.get(source_id)
        if carries is None:
            carries = self._carries_mode_s[source_id] = bool(np.not_equal(held[1].mode_s, _NONE).any())
        return held[1] if carries else None

    @staticmethod
    def _mode_s(source: Any, track_ids: np.ndarray) -> np.ndarray:
        """The Mode S address of each of a source's tracks (``source``: ``_ADSB`` or a table;
        None: none, or unknown track)."""
        if source is _ADSB:
            return track_ids.astype(object)
        out = np.full(track_ids.shape[0], None, dtype=object)
        if track_ids.shape[0]:
            at = find(source.track_id, track_ids)
            out[at >= 0] = source.mode_s[at[at >= 0]]
        return out

    def _identity_of(self, v: PairSetView) -> tuple[int, int]:
        """A view's confirmed pairs whose two tracks both carry a Mode S address, and how many
        of those agree: counted once per view and pair of sources' tables (a status is asked
        for far more often than a table changes; a table is remembered weakly)."""
        sa, sb = self._mode_s_source(v.radar_a), self._mode_s_source(v.radar_b)
        if sa is None or sb is None:
            return 0, 0  # a side without addresses: no pair has one on both
        if v._identity:  # (once set, never emptied)
            ka, kb, n, k = v._identity[0]
            if _holds(ka, sa) and _holds(kb, sb):
                return n, k
        c = v.columns["confirmed"]
        a = self._mode_s(sa, v.columns["track_a"][c])
        b = self._mode_s(sb, v.columns["track_b"][c])
        both = np.not_equal(a, _NONE, dtype=bool) & np.not_equal(b, _NONE, dtype=bool)
        n, k = int(both.sum()), int(np.count_nonzero(a[both] == b[both]))
        v._identity[:] = [(_remembered(sa), _remembered(sb), n, k)]
        return n, k

    def identity(self) -> dict[str, Any]:
        """Identity quality (contract §4.1): among confirmed pairs whose two tracks both carry
        a Mode S address, how many have equal addresses; overall and per source pair."""
        rows: list[dict[str, Any]] = []
        for v in self.pair_views:
            if not v.confirmed:
                continue
            n, k = self._identity_of(v)
            if n:
                rows.append(
                    {"radar_a": v.radar_a, "radar_b": v.radar_b, "pairs_with_mode_s": n, "mode_s_equal": k}
                )
        n = int(sum(r["pairs_with_mode_s"] for r in rows))
        k = int(sum(r["mode_s_equal"] for r in rows))
        return {"pairs_with_mode_s": n, "mode_s_equal": k, "agreement": k / n if n else None, "by_pair": rows}

    def status(self) -> dict[str, Any]:
        """Status without process-level fields (the node adds uptime, zenoh and queue)."""
        return {"uptime_s": 0.0, "zenoh": {"mode": "none", "listen": [], "connect": []}, **self.status_core()}

    def radars(self) -> list[dict[str, Any]]:
        keys = {"batches", "plots", "rejected", "lost_batches", "last_time_s"}
        return [{**r.site.model_dump(), **r.status.model_dump(include=keys)} for r in self.radar_rows]


def _remembered(source: Any) -> Any:
    """A Mode S source as a view remembers it: a table weakly (a view must not keep an old
    table alive), the markers as they are."""
    return weakref.ref(source) if isinstance(source, TrackTable) else source


def _holds(remembered: Any, source: Any) -> bool:
    """Whether a remembered Mode S source is ``source``."""
    if isinstance(remembered, weakref.ref):
        return remembered() is source
    return remembered is source


def build_snapshot(
    *,
    tracking: Any,
    sources: Mapping[str, Any],
    owned: Callable[[str], bool],
    tables: Mapping[str, tuple[float, TrackTable]],
    pair_views: list[PairSetView],
    system: SystemTrackView | None,
    biases: list[dict[str, Any]],
    correlation: dict[str, Any],
    rejected: dict[str, int],
    method: str,
    prefix: str,
    progress: dict[str, Any],
    adsb_sources: frozenset[str],
    outputs_time_s: float | None,
    performance: Any = None,
) -> Snapshot:
    """The engine's state as a :class:`Snapshot`: the radars this worker tracks (``tracking``,
    a :class:`~.tracking_stage.TrackingStage`, with the sequencer's ``sources`` clocks) and
    what is published: the tables as published (``tables``, the same moment as the pair sets
    and system tracks), pair sets, system tracks."""
    tracks = dict(tables)
    rows = []
    for rid, r in sorted(tracking.tracked.items()):
        if not owned(rid):
            continue
        clock = sources.get(rid)
        confirmed = r.confirmed
        pd_measured, misses_to_delete = tracking.detection(rid)
        status = RadarStatus(
            radar_id=rid,
            batches=clock.batches if clock else 0,
            plots=clock.plots if clock else 0,
            rejected=clock.rejected if clock else 0,
            lost_batches=clock.lost_batches if clock else 0,
            window_plots=tracking.window_plots(rid),
            tracks_confirmed=confirmed,
            tracks_tentative=len(r.table) - confirmed,
            last_time_s=clock.last_time_s if clock else None,
            restarts=clock.restarts if clock else 0,
            window_evicted=tracking.window_evicted(rid),
            plots_coincident=tracking.plots_coincident(rid),
            scan_period_observed_s=tracking.scan_period_observed(rid),
            measurement_sigma_scale=tracking.sigma_scale(rid),
            aided_associations=tracking.aided_associations(rid),
            pd_measured=None if pd_measured is None else round(pd_measured, 4),
            misses_to_delete=misses_to_delete,
            expired=clock.expired if clock else False,
        )
        rows.append(RadarRow(r.site, status))
    return Snapshot(
        tracks=tracks,
        radar_rows=rows,
        pair_views=pair_views,
        biases_all=biases,
        correlation=correlation,
        rejected=rejected,
        method=method,
        prefix=prefix,
        sites={rid: r.site for rid, r in tracking.tracked.items()},
        progress=progress,
        adsb_sources=adsb_sources,
        system=system,
        outputs_time_s=outputs_time_s,
        performance=performance,
    )
