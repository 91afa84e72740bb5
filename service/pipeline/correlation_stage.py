"""The correlation stage: one ``PairCorrelator`` per pair of sources, on a data-time cadence.

Radar pairs use the configured method.  A reference source (AIS) is bias-free: each radar is
correlated with it by ``cfar`` (the method built for cooperative references) and the pairs
feed the joint bias estimate, which then is absolute rather than relative.

Cost follows tracks, not ids:

* a pair is correlated once per ``cadence_scans`` scans of the slower of its radars (the
  tracks of both have been refreshed by then; more often re-tests the same plots), and never
  more often than ``min_interval_s``;
* a pair is first correlated only once both sides have at least ``min_confirmed_tracks``
  confirmed tracks: sources without tracks cost nothing (an existing pair keeps its cadence,
  so a side whose tracks are gone empties its book);
* radars farther apart than ``max_site_distance_m`` are never paired, and a reference source
  is paired with a radar only if one of its reference tracks lies within
  ``max_reference_range_m`` of the radar;
* the joint bias solve over every pair runs once per ``bias_interval_s`` of data time, inside
  the update that crosses it: never because someone read the result.

Partitioned (``--partition K/N``, :mod:`.partition`): the stage correlates only the pairs its
worker owns, and hands out the registration rows each update adds (:meth:`take_rows`) for
the worker that solves the joint bias estimate, which mirrors every other worker's rows
(:meth:`mirror_rows`) and solves over all of them: the same memories one worker would hold.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, fields
from typing import Annotated, Any

import numpy as np
from annotated_types import Ge, Gt

from service.correlation import CorrelationParams, PairCorrelator, joint_solution
from service.correlation.correlator import positions_at
from service.correlation.pairkeys import TrackKeys, isin_sorted
from service.correlation.registration import (
    BiasSolution,
    RegistrationMemory,
    RegistrationRowsData,
    solution_from_state,
    solution_state,
    to_estimates,
)
from service.fusion.members import Links
from service.geo import Site
from service.pipeline.partition import Partition
from service.pipeline.read_model import PairSetView
from service.pipeline.shared_links import Crossing, PairRegistration, SharedLinks
from service.pipeline.system_stage import LAST, Drawing, Picture, SystemStage, take_picture
from service.reference import ReferenceKind, ReferenceParams, ReferenceTracks
from service.tracking.base import TrackTable
from service.wire.outputs import bias_dict

#: Method used between a radar and a reference source.
REFERENCE_METHOD = "cfar"
#: Upper bounds (s) of the pair update time histogram (``/status`` ``correlation``
#: ``duration_buckets``, Prometheus ``le``): a pair of a few tracks takes about a millisecond,
#: a national network's busiest pairs tens, and anything near the scan period (seconds) is an
#: update that falls behind the radars.
DURATION_BUCKETS_S = np.array([0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0])
#: The bucket names: each bound as Python writes it, then ``+Inf`` (every update).
DURATION_LABELS = (*(repr(float(b)) for b in DURATION_BUCKETS_S), "+Inf")
#: Pair update times kept for the quantiles (``p50_ms``, ``p99_ms``).
RECENT_UPDATES = 2048
#: Joint bias solutions kept with their data time (:attr:`CorrelationStage.bias_history`).
BIAS_HISTORY = 2880

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CadenceParams:
    """When pairs are correlated and biases solved (all in data time)."""

    #: A pair is correlated once per this many scans of the slower of its radars ...
    cadence_scans: float = 1.0
    #: ... and once per this many when it is settled: registered, no tentative pair, no
    #: ambiguous candidate, no fresh track left undecided.  Such an update only re-checks the
    #: confirmed pairs (a new track is decided when it is confirmed, a track that goes leaves
    #: its pairs at once), so a settled network costs about a third; a pair with anything open
    #: keeps ``cadence_scans``.
    settled_cadence_scans: float = 3.0
    #: ... and at most once per this many data seconds.
    min_interval_s: float = 1.0
    #: Between a pair's updates, the tracks confirmed since are decided at once
    #: (:meth:`~service.correlation.PairCorrelator.decide_new`), but at most once per this many
    #: scans of the slower radar: tracks confirmed sooner after a decision wait for the next
    #: one, together.  A decision's cost is mostly its fixed part (bringing the tables near the
    #: new tracks to the update time, compensating them, the rival and isolation tests), and a
    #: busy radar confirms a few tracks in every sector batch.  National network (120 s):
    #: 0 took 10 017 decisions, 0.25 scans 4 441 and 0.5 about 2 500.  Half a scan, measured
    #: against a quarter (docs/results.md): the correlation stage's CPU 17 % less (11.6
    #: against 13.9 s in one process), the median time to pair 0.25 against 0.12 scans
    #: (three-radar scenario 0.30; the service's goal is a median of at most 0.75 scans), p95
    #: 0.78 against 0.75 (the ambiguous pairs, which wait for updates anyway).  A track
    #: confirmed while the pair was quiet is still decided in the same release.  0: every
    #: batch's at once.
    prompt_interval_scans: float = 0.5
    #: A track confirmed between updates that its decision left open (a rival near, its
    #: neighbourhood crowded, or the pair not registered yet: at a service's start every
    #: aircraft is new at once and no pair is registered) waits for the pair's next update (and
    #: if still ambiguous then, for a second look, ``EvidenceParams.min_looks``, on the pair's
    #: cadence): that update comes at most this many scans of the slower radar after the
    #: pair's previous one.
    #: National network (120 s, from the start): time to pair p95 1.75 scans at 1 (the pair's
    #: cadence), 0.75 at 0.5, with 0 false pairs and the same CPU either way (docs/results.md).
    open_cadence_scans: float = 0.5
    #: Radars farther apart than this cannot share targets and are never correlated (m).
    max_site_distance_m: float = 800_000.0
    #: A reference source is correlated with a radar only if one of its tracks lies within
    #: this distance of the radar (m): beyond any radar's horizon.
    max_reference_range_m: float = 500_000.0
    #: A new pair is correlated only once both sides have this many confirmed tracks.
    min_confirmed_tracks: int = 1
    #: The joint bias estimate over every pair is solved once per this many data seconds.
    #: Biases drift over hours and the estimate averages ``RegistrationParams.memory_s`` of
    #: confirmed pairs; a national network's solve (66 pairs, a million rows) costs about
    #: 150 ms, so every 30 s it costs 5 ms per data second.  The solves are at multiples of
    #: it (data time since the epoch).
    bias_interval_s: Annotated[float, Gt(0)] = 30.0
    #: The solve for time ``T`` runs once the data clock has passed ``T`` by this much (s), over
    #: the rows up to ``T``: in a partitioned network the bias worker then holds every other
    #: worker's rows up to ``T`` (they lag it by their release and the network, about a scan),
    #: so its estimate is the one a single worker makes.  Biases drift over hours: an estimate
    #: ten seconds old costs nothing.
    bias_lag_s: float = 10.0
    #: System tracks (contract §4.4) are rebuilt once per this many data seconds, at its
    #: multiples; 0 turns them off.  A rebuild costs in proportion to the network's tracks
    #: and confirmed pairs (national network: about 25 ms); the radars' scans are 4-12 s, so a
    #: rebuild every 2 s still refreshes each system track within a scan, and a track that
    #: goes leaves its system track at once (:mod:`.publication`).
    system_interval_s: Annotated[float, Ge(0)] = 2.0


@dataclass
class MirroredPair:
    """Another worker's pair: only its registration memory (the joint bias solve's input)."""

    memory: RegistrationMemory


@dataclass(frozen=True)
class SharedRows:
    """Rows an owned pair's update added, for the bias worker (``RegistrationRows`` on the wire)."""

    key: tuple[str, str]
    source_a: str  # the memory's A side: a radar
    source_b: str
    reference: bool  # source_b is a bias-free reference source
    rows: RegistrationRowsData


@dataclass(frozen=True)
class Source:
    """What the stage needs of one partner at an update."""

    source_id: str
    geometry: Site | None  # None: a bias-free reference source
    tracks: Callable[[float], TrackTable]
    confirmed: int


class CorrelationStage:
    """Pair correlators over the latest tracks of every source (see module docstring).

    The stage keeps its own view of every source (the latest track table of each radar, the
    reports of each reference), fed in the engine's release order, so it can run next to the
    engine or behind a pipe in another process (:mod:`.correlation_process`) alike.
    """

    def __init__(
        self,
        method: str,
        params: CadenceParams | None = None,
        reference: ReferenceParams | None = None,
        correlation: CorrelationParams | None = None,
        partition: Partition | None = None,
        aid: bool = False,
    ) -> None:
        """``aid``: the aid of association is on; every crossing of the links' grid is handed
        out with the owned pairs' links and registrations (:meth:`take_crossings`)."""
        self.method = method
        self.partition = partition or Partition()
        self.params = params or CadenceParams()
        self.reference_params = reference or ReferenceParams()
        self.correlation_params = correlation or CorrelationParams()
        self.pair_correlators: dict[tuple[str, str], PairCorrelator] = {}
        self.views: dict[tuple[str, str], PairSetView] = {}
        self.next_due: dict[tuple[str, str], float] = {}
        #: Per pair not due: the ids of each side's tracks confirmed since its last update or
        #: decision, still to be decided, and the data time its next decision may run.
        self._undecided: dict[tuple[str, str], dict[str, list[np.ndarray]]] = {}
        self._next_decision: dict[tuple[str, str], float] = {}
        self.timings_ms: deque[float] = deque(maxlen=RECENT_UPDATES)
        self.updates = 0
        self.last_ms = 0.0
        #: Every update's time, not only the recent ones: updates per bucket of
        #: ``DURATION_BUCKETS_S`` (the last one above them all), and their sum (s).
        self.duration_counts = np.zeros(len(DURATION_LABELS), dtype=np.int64)
        self.duration_sum_s = 0.0
        #: :meth:`timings` as of the update count it was taken at: they change only with an
        #: update, and a snapshot asks after every message (two percentiles each time).
        self._timings: tuple[int, dict[str, Any]] | None = None
        self.biases: list[dict[str, Any]] = []
        #: Every solve's ``biases`` with its data time, the newest ``BIAS_HISTORY`` (at one
        #: solve per ``bias_interval_s``, 30 s: a day); ``topofusion assess`` charts them.
        self.bias_history: deque[tuple[float, list[dict[str, Any]]]] = deque(maxlen=BIAS_HISTORY)
        self._next_bias_s = -np.inf
        self._joint: BiasSolution | None = None
        self._radars: dict[str, tuple[Site, TrackTable]] = {}
        #: Each source's track keys, shared by all its pairs (:class:`PairCorrelator`).
        self._track_keys: dict[str, TrackKeys] = {}
        self._references: dict[str, ReferenceTracks] = {}
        self._silent: set[str] = set()
        #: The latest data time released to the stage (a radar's table or a reference batch):
        #: the end of the input, where the last picture is drawn.
        self._clock_s = -np.inf
        #: Other workers' pairs (the bias worker of a partitioned network).
        self.mirrors: dict[tuple[str, str], MirroredPair] = {}
        #: Rows the owned pairs added since :meth:`take_rows` (partitioned, not the bias worker).
        self._rows_out: list[SharedRows] = []
        self._share_rows = not self.partition.whole and not self.partition.solves_biases
        self._solves = self.partition.solves_biases
        #: System tracks: drawn by one worker (worker 1 of N, from every worker's links).
        self.system = SystemStage(
            self.params.system_interval_s,
            self.partition,
            self.correlation_params.cycles,
            aid,
        )

    # -- the sources ---------------------------------------------------------------------------
    def reference(
        self,
        source_id: str,
        time_s: float,
        report_time_s: np.ndarray,
        ids: np.ndarray,
        latitude_deg: np.ndarray,
        longitude_deg: np.ndarray,
        altitude_m: np.ndarray,
        kind: ReferenceKind,
    ) -> None:
        """A released batch of a reference source's reports (``altitude_m`` NaN: not reported)."""
        refs = self._references.get(source_id)
        if refs is None or refs.kind != kind:
            refs = self._references[source_id] = ReferenceTracks(self.reference_params, kind)
        refs.add(report_time_s, ids, latitude_deg, longitude_deg, altitude_m, time_s)
        self._silent.discard(source_id)
        self._clock_s = max(self._clock_s, time_s)

    def silent(self, source_id: str) -> None:
        """A reference source expired: it is offered to no radar until it reports again."""
        self._silent.add(source_id)

    def forget(self, source_id: str) -> None:
        """A source left the engine: its pairs go."""
        change_radars(self._radars, "forget", (source_id,))
        self._references.pop(source_id, None)
        self._silent.discard(source_id)
        self._track_keys.pop(source_id, None)
        for key in [k for k in self.pair_correlators if source_id in k]:
            del self.pair_correlators[key]
            self.views.pop(key, None)
            self.next_due.pop(key, None)
            self._undecided.pop(key, None)
            self._next_decision.pop(key, None)
        for key in [k for k in self.mirrors if source_id in k]:
            del self.mirrors[key]
        self.system.forget(source_id)

    def moved(self, site: Site) -> None:
        """A radar moved: its pairs keep their books but re-register from scratch.

        The remembered registration rows were measured from the old position; pairs of the
        other radars are untouched.
        """
        change_radars(self._radars, "moved", (site,))
        for key, old in list(self.pair_correlators.items()):
            if site.site_id not in key:
                continue
            a = site if old.site_a.site_id == site.site_id else old.site_a
            b = site if old.site_b is not None and old.site_b.site_id == site.site_id else old.site_b
            # same parameters and track keys (the book's), new geometry
            new = PairCorrelator(old.method, a, b, old.params, old.track_keys)
            new.book = old.book
            self.pair_correlators[key] = new
        for key in [k for k in self.mirrors if site.site_id in k]:
            del self.mirrors[key]  # its owner re-registers it from scratch too

    # -- the joint bias estimate of a partitioned network -------------------------------------
    def take_rows(self) -> list[SharedRows]:
        """Rows added by owned pairs since the last call (only a partitioned worker that does
        not solve the biases)."""
        out, self._rows_out = self._rows_out, []
        return out

    def mirror_rows(
        self, key: tuple[str, str], site_a: Site, site_b: Site | None, rows: RegistrationRowsData
    ) -> None:
        """Rows another worker's pair ``key`` added (``site_b`` None: a reference source)."""
        if not self._solves or key in self.pair_correlators:
            return
        mirror = self.mirrors.get(key)
        if mirror is None:
            mirror = self.mirrors[key] = MirroredPair(RegistrationMemory(site_a, site_b))
        mirror.memory.add_rows(
            rows.time_s,
            rows.track_a,
            rows.track_b,
            rows.p_a,
            rows.p_b,
            rows.s,
            self.correlation_params.registration,
            prune=False,  # pruned for the times it is solved at (its rows may be far ahead)
            v=rows.v,
        )
        # ... but never beyond the row cap, whatever a peer sends between two solves
        mirror.memory.prune(-np.inf, self.correlation_params.registration)

    def _partners(self, radar_id: str) -> list[Source]:
        """Every other radar and every live reference source, in id order."""
        out = []
        for rid, (geometry, table) in sorted(self._radars.items()):
            if rid != radar_id:
                n = int(np.count_nonzero(table.confirmed))
                out.append(Source(rid, geometry, lambda t, table=table: table, n))  # type: ignore[misc]
        for sid, ref in sorted(self._references.items()):
            if sid not in self._silent:
                out.append(Source(sid, None, ref.table, len(ref)))
        return out

    # -- correlation ---------------------------------------------------------------------------
    def _reachable(self, radar: Site, other: Source, table: TrackTable | None) -> bool:
        p = self.params
        if other.geometry is not None:
            return bool(
                np.linalg.norm(radar.origin_ecef - other.geometry.origin_ecef) <= p.max_site_distance_m
            )
        if table is None or len(table) == 0:
            return False
        d2 = np.einsum("ij,ij->i", *(2 * [table.position_ecef_m - radar.origin_ecef]))
        return bool(d2.min() <= p.max_reference_range_m**2)

    @staticmethod
    def _scan(a: Site, b: Site | None) -> float:
        """The scan period of the slower radar of a pair (s)."""
        return max(a.scan_period_s, b.scan_period_s if b is not None else 0.0)

    def _keys_of(self, source_id: str) -> TrackKeys:
        """The track keys of ``source_id``'s tables, one for all its pairs."""
        keys = self._track_keys.get(source_id)
        if keys is None:
            keys = self._track_keys[source_id] = TrackKeys()
        return keys

    def _interval(self, a: Site, b: Site | None, scans: float) -> float:
        """Data time of ``scans`` scans of a pair's slower radar, at least ``min_interval_s``."""
        return max(self.params.min_interval_s, scans * self._scan(a, b))

    def radar(self, radar_id: str, geometry: Site, table: TrackTable, time_s: float) -> list[tuple[str, str]]:
        """A radar's tracks after one of its batches: correlate it with every partner due, and
        decide its newly confirmed tracks with every other partner at once."""
        before = self._radars.get(radar_id)
        change_radars(self._radars, "radar", (radar_id, geometry, table))
        self._clock_s = max(self._clock_s, time_s)
        me = Source(radar_id, geometry, lambda t: table, int(np.count_nonzero(table.confirmed)))
        fresh = _newly_confirmed(before[1] if before is not None else None, table, self._keys_of(radar_id))
        return self.update(me, self._partners(radar_id), time_s, fresh)

    def update(
        self, radar: Source, others: list[Source], time_s: float, fresh: np.ndarray | None = None
    ) -> list[tuple[str, str]]:
        """Correlate ``radar`` with every partner due for an update; a partner not due yet
        decides the radar's tracks confirmed since its previous table (``fresh``, their track
        keys) at once (:meth:`PairCorrelator.decide_new`).  The keys updated."""
        assert radar.geometry is not None
        p = self.params
        updated = []
        own: TrackTable | None = None
        own_now: np.ndarray | None = None
        for other in others:
            key = (min(radar.source_id, other.source_id), max(radar.source_id, other.source_id))
            corr = self.pair_correlators.get(key)
            if corr is None and not self.partition.owns_pair(*key, self._references):
                continue
            if key in self.views and time_s < self.views[key].time_s:
                # A table released late (a worker back after the grace, released out of
                # order: docs/scale-out.md) never takes a pair's book back in data time.
                continue
            if time_s < self.next_due.get(key, -np.inf):
                if corr is not None and fresh is not None and len(fresh):
                    self._undecided.setdefault(key, {}).setdefault(radar.source_id, []).append(fresh)
                waiting = time_s < self._next_decision.get(key, -np.inf)
                if corr is None or key not in self._undecided or waiting:
                    continue
                if own_now is None:  # every track of the radar at the update time, once
                    own_now = positions_at(radar.tracks(time_s), time_s)
                if self._prompt(corr, radar, other, time_s, self._undecided.pop(key), own_now):
                    self._changed(key, corr, time_s, radar.source_id)
                    updated.append(key)
                scans = self.params.prompt_interval_scans
                self._next_decision[key] = time_s + scans * self._scan(radar.geometry, other.geometry)
                if not corr.settled:  # a fresh track left open: the next update must not wait
                    soon = corr.time_s + self._interval(radar.geometry, other.geometry, p.open_cadence_scans)
                    self.next_due[key] = min(self.next_due[key], soon)
                continue
            if corr is None and min(radar.confirmed, other.confirmed) < p.min_confirmed_tracks:
                continue
            table = other.tracks(time_s) if other.geometry is None else None
            if corr is None and not self._reachable(radar.geometry, other, table):
                continue
            # The correlator's A side is a radar; a reference source is always its B side.
            first, second = (
                (radar, other) if other.geometry is None or key[0] == radar.source_id else (other, radar)
            )
            if corr is None:
                method = self.method if second.geometry is not None else REFERENCE_METHOD
                assert first.geometry is not None
                # A radar's keys are shared by its pairs (a track absent from its table is
                # deleted); a reference source's are each pair's own: its table at a pair's
                # update leaves out the tracks not heard from lately, which may report again,
                # and a pair keeps such a track's pair unless its own update found it absent.
                keys = (
                    self._keys_of(first.source_id),
                    self._keys_of(second.source_id) if second.geometry is not None else TrackKeys(),
                )
                corr = self.pair_correlators[key] = PairCorrelator(
                    method, first.geometry, second.geometry, self.correlation_params, keys
                )
                self._adopt(key, corr)
            own = radar.tracks(time_s) if own is None else own
            other_table = table if table is not None else other.tracks(time_s)
            ta, tb = (own, other_table) if first is radar else (other_table, own)
            chains = self.system.implied(key, time_s) if second.geometry is not None else None
            corr.update(ta, tb, time_s, chains)
            self._undecided.pop(key, None)  # (the update decided them)
            cadence = p.settled_cadence_scans if corr.settled else p.cadence_scans
            self.next_due[key] = time_s + self._interval(radar.geometry, other.geometry, cadence)
            self.updates += 1
            self.last_ms = float(corr.last_update_ms)
            self.timings_ms.append(self.last_ms)
            # side="left": a time equal to a bound counts in that bound's bucket (``le``)
            self.duration_counts[np.searchsorted(DURATION_BUCKETS_S, self.last_ms / 1000.0)] += 1
            self.duration_sum_s += self.last_ms / 1000.0
            self._changed(key, corr, time_s, radar.source_id)
            updated.append(key)
            if self._share_rows and corr.last_rows is not None:
                self._rows_out.append(
                    SharedRows(
                        key, corr.site_a.site_id, second.source_id, corr.site_b is None, corr.last_rows
                    )
                )
        if self._solves:
            self._solve_due(time_s)
        self.system.due(time_s, radar.source_id, self._picture, self._radars.keys())
        return updated

    def _changed(self, key: tuple[str, str], corr: PairCorrelator, time_s: float, release: str) -> None:
        """A pair's book changed at the release of ``release``'s table at ``time_s``."""
        self.views[key] = PairSetView.of(key, corr, time_s)
        registration = lambda: PairRegistration.of(corr)  # noqa: E731  (read at the crossing)
        self.system.updated(key, lambda: _links(key, corr), time_s, release, registration)

    def _prompt(
        self,
        corr: PairCorrelator,
        radar: Source,
        other: Source,
        time_s: float,
        undecided: dict[str, list[np.ndarray]],
        own_now: np.ndarray,
    ) -> bool:
        """A partner not due: the tracks of either radar confirmed since the pair's last
        update or decision (``undecided``, ids by radar) decided now (clear pairs confirm);
        ``own_now``: the radar's tracks brought to ``time_s``."""
        if other.geometry is None:
            return False  # reference sources: their own method, on the cadence
        own, theirs = radar.tracks(time_s), other.tracks(time_s)
        mine, others = (_keys_in(undecided.get(s.source_id)) for s in (radar, other))
        if corr.site_a.site_id == radar.source_id:
            return corr.decide_new(own, theirs, time_s, mine, others, now_a=own_now)
        return corr.decide_new(theirs, own, time_s, others, mine, now_b=own_now)

    def _picture(self, time_s: float, release: str) -> Picture:
        """What the system tracks of ``time_s`` are drawn from (:mod:`.system_stage`)."""
        own = {key: _links(key, corr) for key, corr in self.pair_correlators.items()}
        return take_picture(time_s, release, self._radars, self._references, self._silent, self._joint, own)

    def take_drawings(self) -> list[Drawing]:
        """The system-track pictures ready to draw since the last call, oldest first (drawn by
        the runner's :class:`~service.pipeline.system_stage.SystemDrawer`)."""
        return self.system.take_drawings()

    def take_links(self) -> list[SharedLinks]:
        """Links of the owned pairs updated since the last call (partitioned, not worker 1)."""
        return self.system.take_links()

    def take_crossings(self) -> list[Crossing]:
        """The links' grid's crossings since the last call, with the owned pairs' links and
        registrations (the aid of association on; none otherwise)."""
        return self.system.take_crossings()

    def mirror_links(self, shared: SharedLinks) -> None:
        """Another worker's pair's links (worker 1 draws the picture from them)."""
        self.system.mirror(shared)

    def others_through(self, time_s: float) -> None:
        """Every other live worker has correlated through ``time_s`` (worker 1): the pictures
        up to it are drawn."""
        self.system.through(time_s)

    def finish(self) -> None:
        """End of the input: the joint bias estimate at the last update's data time, and the
        system tracks at the last release's."""
        times = [c.time_s for c in self.pair_correlators.values() if np.isfinite(c.time_s)]
        times += [float(m.memory.time[-1]) for m in self.mirrors.values() if len(m.memory)]
        if times and self._solves:
            self._solve_biases(max(times))
        # the last picture at the end of the input, never before the pictures drawn on the way
        # (none when nothing was released since the start: a restart without input)
        clock = self._clock_s
        self.system.finish(self._picture(clock, LAST) if np.isfinite(clock) else None)

    def _solve_biases(self, time_s: float) -> None:
        # Warm-started from the previous solve: the rows changed little since, so one or two
        # Gauss-Newton steps reach the same fixed point a cold solve does.
        for mirror in self.mirrors.values():
            mirror.memory.prune(time_s, self.correlation_params.registration)
        # In key order: one worker and the bias worker of N sum the same rows in the same order.
        everything: dict[tuple[str, str], PairCorrelator | MirroredPair] = {
            **self.mirrors,
            **self.pair_correlators,
        }
        pairs = [everything[k] for k in sorted(everything)]
        joint = joint_solution(pairs, time_s, self.correlation_params.registration, self._joint)
        if joint is None:
            return  # no rows in its window (e.g. a clock far ahead): the grid time stays due
        self._set_joint(joint, time_s)

    def _set_joint(self, joint: BiasSolution, time_s: float) -> None:
        """The joint solution for ``time_s`` and the biases it gives (``GET /biases``)."""
        self._next_bias_s = time_s
        self._joint = joint
        self.biases = [b for b in map(bias_dict, to_estimates(joint, time_s)) if b is not None]
        self.bias_history.append((time_s, self.biases))

    def _solve_due(self, clock_s: float) -> None:
        """Solve for the latest grid time ``T`` (a multiple of ``bias_interval_s``) with
        ``T + bias_lag_s <= clock_s`` not solved yet, over the rows of ``[T - memory_s, T]``.

        The grid and the lag make the solve a function of the rows alone: the bias worker of a
        partitioned network has every other worker's rows up to ``T`` by then, so it solves
        what one worker would, at the same ``T``, whichever worker correlated what.
        """
        p = self.params
        grid = np.floor((clock_s - p.bias_lag_s) / p.bias_interval_s) * p.bias_interval_s
        if grid > self._next_bias_s:
            self._solve_biases(float(grid))

    def pair_views(self) -> list[PairSetView]:
        return [self.views[k] for k in sorted(self.views)]

    # -- kept across a restart (service.state) -------------------------------------------------
    def export_state(self) -> dict[str, Any]:
        """What a restart keeps of the stage (contract §4.6 "State"): every pair's registration
        memory (owned and mirrored pairs, :meth:`RegistrationMemory.export`, with the sites it
        was measured from) and the joint bias solution with its time.  Pair books, reference
        tracks and the sources' tables are not kept: the input that follows rebuilds them.
        Plain values and numpy arrays; the arrays are views that later input leaves as they are."""
        memories = {k: p.memory for k, p in self.mirrors.items()}
        memories.update({k: c.memory for k, c in self.pair_correlators.items()})
        return {
            "memories": [
                {
                    "key": list(key),
                    "site_a": _site_state(m.site_a),
                    "site_b": None if m.site_b is None else _site_state(m.site_b),
                    "rows": m.export(),
                }
                for key, m in sorted(memories.items())
                if len(m)
            ],
            "joint": None if self._joint is None else solution_state(self._joint),
            "joint_time_s": self._next_bias_s,
        }

    def restore_state(self, state: Mapping[str, Any] | None, sites: Mapping[str, Site]) -> None:
        """Take what :meth:`export_state` gave (``None``: nothing), before any input.

        Each registration memory waits as a mirror until its pair's correlator is made, which
        then takes it over (:meth:`_adopt`): the pair registers at its first update instead of
        after minutes of confirmed pairs.  A memory of a radar that is not at the same place in
        ``sites`` now (its site moved or is unknown) is left out: its rows were measured from
        elsewhere.  The joint solution and biases are those of before.  Everything is read
        before anything changes (``KeyError``, ``TypeError`` or ``ValueError`` on a state that is not one)."""
        mirrors: dict[tuple[str, str], MirroredPair] = {}
        joint: tuple[BiasSolution, float] | None = None
        if state is not None:
            for kept in state["memories"]:
                key = (str(kept["key"][0]), str(kept["key"][1]))
                site_a = sites.get(kept["site_a"]["site_id"])
                site_b = None if kept["site_b"] is None else sites.get(kept["site_b"]["site_id"])
                if (
                    key[0] < key[1]
                    and site_a is not None
                    and _same_place(kept["site_a"], site_a)
                    and (kept["site_b"] is None or _same_place(kept["site_b"], site_b))
                ):
                    mirrors[key] = MirroredPair(RegistrationMemory.restored(site_a, site_b, kept["rows"]))
            if state["joint"] is not None:
                joint = (solution_from_state(state["joint"]), float(state["joint_time_s"]))
        self.mirrors = mirrors
        if joint is not None:
            self._set_joint(*joint)

    def _adopt(self, key: tuple[str, str], corr: PairCorrelator) -> None:
        """A new pair takes over the registration memory a restart kept of it (held as a mirror
        until now; a move of its radar since has dropped it, :meth:`moved`)."""
        kept = self.mirrors.pop(key, None)
        if kept is not None and kept.memory.site_a.site_id == corr.site_a.site_id:
            corr.memory = kept.memory

    def timings(self) -> dict[str, Any]:
        """``/status`` ``correlation`` (:func:`timings_dict`), taken again only after an update
        (the same dict until then: not to be changed by its readers)."""
        if self._timings is None or self._timings[0] != self.updates:
            self._timings = (
                self.updates,
                timings_dict(
                    self.updates, self.last_ms, self.timings_ms, self.duration_counts, self.duration_sum_s
                ),
            )
        return self._timings[1]


def change_radars(radars: dict[str, tuple[Site, TrackTable]], op: str, args: tuple[Any, ...]) -> None:
    """What the stage's call ``op`` with ``args`` does to its radars' sites and tables (in
    place): the one place of it, so that the child process's parent, which holds the same
    tables, keeps them as the child does (:mod:`.correlation_process`).  A call whose
    arguments are not what it takes raises before it changes anything."""
    if op == "radar":
        radars[args[0]] = (args[1], args[2])
    elif op == "forget":
        radars.pop(args[0], None)
    elif op == "moved":
        site_id = args[0].site_id
        if site_id in radars:
            radars[site_id] = (args[0], radars[site_id][1])


def _links(key: tuple[str, str], corr: PairCorrelator) -> Links:
    """A pair's confirmed pairs, its A side first."""
    first = corr.site_a.site_id
    return Links.of_book(first, key[1] if key[0] == first else key[0], corr.book)


def _keys_in(parts: list[np.ndarray] | None) -> np.ndarray:
    """The track keys of ``parts`` together, sorted, each once (none: an empty array)."""
    return np.unique(np.concatenate(parts)) if parts else np.empty(0, dtype=np.int64)


def _newly_confirmed(before: TrackTable | None, now: TrackTable, keys: TrackKeys) -> np.ndarray:
    """The track keys (``keys``: the radar's) of the tracks confirmed in ``now`` that were not
    confirmed in ``before`` (none at a radar's first table)."""
    if before is None:
        return np.empty(0, dtype=np.int64)
    was = keys.of(before.track_id)[before.confirmed]  # (the table keyed last: no search)
    now_keys = keys.of(now.track_id)[now.confirmed]
    return now_keys[~isin_sorted(now_keys, was)]


def _site_state(site: Site) -> dict[str, Any]:
    return {f.name: getattr(site, f.name) for f in fields(Site) if f.init}


def _same_place(saved: Mapping[str, Any], now: Site | None) -> bool:
    """A site now at the position it was saved with (sigmas and scan period may differ)."""
    return now is not None and (saved["latitude_deg"], saved["longitude_deg"], saved["altitude_m"]) == (
        now.latitude_deg,
        now.longitude_deg,
        now.altitude_m,
    )


def timings_dict(
    updates: int = 0,
    last_ms: float = 0.0,
    recent_ms: Collection[float] = (),
    duration_counts: np.ndarray | None = None,
    duration_sum_s: float = 0.0,
) -> dict[str, Any]:
    """``/status`` ``correlation`` (``CorrelationTimings``); without arguments: before any update.

    ``duration_buckets`` is cumulative, as Prometheus wants it: the updates that took at most
    each bound; its ``+Inf`` is every update.
    """
    t = np.asarray(recent_ms) if len(recent_ms) else np.zeros(1)
    counts = np.zeros(len(DURATION_LABELS), dtype=np.int64) if duration_counts is None else duration_counts
    return {
        "updates": updates,
        "last_ms": round(last_ms, 3),
        "p50_ms": round(float(np.percentile(t, 50)), 3),
        "p99_ms": round(float(np.percentile(t, 99)), 3),
        "duration_buckets": dict(zip(DURATION_LABELS, np.cumsum(counts).tolist(), strict=True)),
        "duration_sum_s": duration_sum_s,
    }
