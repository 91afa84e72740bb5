"""The stateful worker: ``ingest(key, payload) -> outgoing messages``.  No I/O, no threads.

Data time, not wall time
------------------------
Per radar, batches are taken strictly in ``seq`` order.  Across radars, an accepted batch is
held until every *live* radar has reported at least up to its ``time_s`` (the watermark) and
then released in ``(time_s, radar_id, seq)`` order.  Tracking and correlation therefore see
the same sequence whatever the interleaving of radars on arrival, so a replay at any speed
gives the same tracks and pairs as the live stream.  A radar whose data clock lags the newest
one by more than :attr:`EngineConfig.max_lag_s` stops holding the others back (an outage must
not freeze the picture); its late batches are still tracked when they come.  AIS sources
take part in the same ordering, so the reference tracks a radar is correlated with at an
update are the same in every replay.
"""

from __future__ import annotations

import heapq
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import TypeAdapter, ValidationError

from service.correlation import PairCorrelator
from service.geo import Site
from service.keys import Keys
from service.messages import (
    MAX_PAYLOAD_BYTES,
    AisBatch,
    PlotBatch,
    RadarSite,
    RejectionReason,
    dump_json,
    rejection_reason,
)
from service.pairing import CorrelationStage, Source
from service.reference import ReferenceParams, ReferenceTracks
from service.snapshot import Snapshot, track_batch
from service.tracking.base import PlotColumns, Tracker, TrackTable

TrackerFactory = Callable[[Site, "float | None", str, str], Tracker]


@dataclass(frozen=True)
class Outgoing:
    """A message the transport should publish."""

    key: str
    payload: bytes


@dataclass(frozen=True)
class EngineConfig:
    """Everything that decides the engine's results (all in data time)."""

    prefix: str = "fusion"
    #: Correlation method (CONTRACT.md: svd-topology, basic-topology, nearest, gmm, cfar).
    method: str = "svd-topology"
    #: Sliding window of unused plots per radar, data seconds; ``None``: the tracker's default.
    window_s: float | None = None
    #: Track initiator (``service.tracking.INITIATORS``).
    initiator: str = "logic"
    #: Sites known at start-up (setting ``TOPOFUSION_SITES``).
    sites: tuple[RadarSite, ...] = ()
    #: Minimum data time between two correlation updates of one radar pair (s).  0: every update.
    correlation_interval_s: float = 1.0
    #: Radars farther apart than this cannot share targets and are never correlated (m).
    max_site_distance_m: float = 800_000.0
    #: A radar lagging the newest data time by more than this no longer holds back the
    #: cross-radar release of batches (s of data time).
    max_lag_s: float = 30.0
    #: How AIS reports become reference tracks.
    reference: ReferenceParams = field(default_factory=ReferenceParams)


@dataclass
class RadarState:
    site: RadarSite | None = None
    geometry: Site | None = None
    tracker: Tracker | None = None
    last_seq: int | None = None
    batches: int = 0
    plots: int = 0
    rejected: int = 0
    lost_batches: int = 0
    last_time_s: float | None = None  # data clock of accepted batches
    released_time_s: float | None = None
    pending: deque[tuple[float, int, PlotColumns]] = field(default_factory=deque)


@dataclass
class AisState:
    reference: ReferenceTracks
    last_seq: int | None = None
    batches: int = 0
    reports: int = 0
    rejected: int = 0
    lost_batches: int = 0
    last_time_s: float | None = None
    released_time_s: float | None = None
    pending: deque[tuple[float, int, AisBatch]] = field(default_factory=deque)


class RejectionError(Exception):
    def __init__(self, reason: RejectionReason, detail: str, radar_id: str | None = None) -> None:
        super().__init__(detail)
        self.reason: RejectionReason = reason
        self.detail = detail
        self.radar_id = radar_id


def _check_body_id(field_name: str, body_id: str, key_id: str) -> None:
    if body_id != key_id:
        raise RejectionError("schema", f"{field_name} {body_id!r} in body != {key_id!r} in key", key_id)


def _accept_seq(state: RadarState | AisState, seq: int, source_id: str) -> None:
    """Contract: ``seq`` strictly increases per source; a jump counts the missing batches as lost."""
    if state.last_seq is not None:
        if seq <= state.last_seq:
            raise RejectionError("duplicate_seq", f"seq {seq} <= last accepted {state.last_seq}", source_id)
        state.lost_batches += seq - state.last_seq - 1
    state.last_seq = seq
    state.batches += 1


_SITE_LIST = TypeAdapter(list[RadarSite])


def load_sites(path: str | Path) -> tuple[RadarSite, ...]:
    """Sites from a JSON file holding a list of ``RadarSite`` (setting ``TOPOFUSION_SITES``)."""
    p = Path(path)
    try:
        return tuple(_SITE_LIST.validate_json(p.read_bytes()))
    except FileNotFoundError:
        raise ValueError(f"sites file not found: {p}") from None
    except ValidationError as exc:
        raise ValueError(f"sites file {p} is not a JSON list of RadarSite: {exc}") from None


def _default_tracker_factory(site: Site, window_s: float | None, initiator: str, id_prefix: str) -> Tracker:
    from service.tracking import make_tracker
    from service.truth_labels import TruthLabelledTracker

    # TrackBatch.truth_id (evaluation only) is tallied outside the tracker
    tracker = make_tracker(site, window_s=window_s, initiator=initiator, id_prefix=id_prefix)
    return TruthLabelledTracker(tracker)


def to_geometry(site: RadarSite) -> Site:
    return Site(
        site_id=site.radar_id,
        latitude_deg=site.latitude_deg,
        longitude_deg=site.longitude_deg,
        altitude_m=site.altitude_m,
        range_sigma_m=site.range_sigma_m,
        azimuth_sigma_deg=site.azimuth_sigma_deg,
        elevation_sigma_deg=site.elevation_sigma_deg,
        scan_period_s=site.scan_period_s,
    )


def plot_columns(batch: PlotBatch) -> PlotColumns:
    p = batch.plots
    n = len(p.time_s)
    nan = np.full(n, np.nan)
    truth = np.empty(n, dtype=object)
    if p.truth_id is not None:
        truth[:] = p.truth_id
    return PlotColumns(
        time_s=np.asarray(p.time_s, dtype=float),
        range_m=np.asarray(p.range_m, dtype=float),
        azimuth_deg=np.asarray(p.azimuth_deg, dtype=float),
        elevation_deg=np.asarray(p.elevation_deg, dtype=float) if p.elevation_deg is not None else nan,
        altitude_m=np.asarray(p.altitude_m, dtype=float) if p.altitude_m is not None else nan.copy(),
        truth_id=truth,
    )


class Engine:
    """Per-radar windows and trackers, AIS references, cross-source correlation, rejections."""

    def __init__(
        self, config: EngineConfig | None = None, tracker_factory: TrackerFactory | None = None
    ) -> None:
        self.config = config or EngineConfig()
        self.keys = Keys(self.config.prefix)
        self._tracker_factory = tracker_factory or _default_tracker_factory
        self.radars: dict[str, RadarState] = {}
        self.ais: dict[str, AisState] = {}
        self.rejected: Counter[str] = Counter()
        # heads of the sources' pending queues: (clock, kind, source id, seq); kind 0 AIS, 1 radar
        self._heap: list[tuple[float, int, str, int]] = []
        self._first_clock = np.inf
        self._correlation = CorrelationStage(
            self.config.method, self.config.correlation_interval_s, self.config.max_site_distance_m
        )
        self.version = 0  # bumps on every state change; snapshots are cached by it
        self._snapshot: Snapshot | None = None
        for site in self.config.sites:
            self._set_site(site)

    # -- ingest ------------------------------------------------------------------------
    def ingest(self, key: str, payload: bytes, receive_time_s: float | None = None) -> list[Outgoing]:
        """Validate and apply one input message; returns what to publish.  Never raises on input."""
        kind = self.keys.classify(key)
        try:
            if kind is None:
                raise RejectionError("schema", f"not an input key of prefix {self.config.prefix!r}: {key}")
            what, source_id = kind
            if len(payload) > MAX_PAYLOAD_BYTES:
                raise RejectionError(
                    "too_large", f"payload of {len(payload)} bytes > {MAX_PAYLOAD_BYTES}", source_id
                )
            if what == "site":
                self._ingest_site(source_id, payload)
                return []
            if what == "plots":
                self._ingest_plots(source_id, payload)
            else:
                self._ingest_ais(source_id, payload)
            return self._release(until=self._watermark())
        except RejectionError as rejection:
            return [self._reject(key, rejection, receive_time_s)]
        except Exception as exc:  # a bug must cost one message, never the service
            internal = RejectionError("internal", f"{type(exc).__name__}: {exc}", kind[1] if kind else None)
            return [self._reject(key, internal, receive_time_s)]

    def correlators(self) -> list[PairCorrelator]:
        """The live pair correlators, one per correlated source pair (evaluation, diagnostics)."""
        return list(self._correlation.correlators.values())

    def flush(self) -> list[Outgoing]:
        """Release every held batch regardless of the watermark (end of a replay or shutdown)."""
        return self._release(until=np.inf)

    def _reject(self, key: str, rej: RejectionError, receive_time_s: float | None) -> Outgoing:
        self.rejected[rej.reason] += 1
        if rej.radar_id is not None:
            state = self.ais.get(rej.radar_id) if "/ais/" in key else self.radars.get(rej.radar_id)
            if state is not None:
                state.rejected += 1
        self._changed()
        body = {
            "key": key,
            "radar_id": rej.radar_id,
            "reason": rej.reason,
            "detail": rej.detail,
            "time_s": receive_time_s if receive_time_s is not None else time.time(),
        }
        return Outgoing(self.keys.errors, dump_json(body))

    @staticmethod
    def _parse(model: type[Any], payload: bytes, source_id: str) -> Any:
        try:
            return model.model_validate_json(payload)
        except ValidationError as exc:
            reason, detail = rejection_reason(exc)
            raise RejectionError(reason, detail, source_id) from None

    def _ingest_site(self, radar_id: str, payload: bytes) -> None:
        site: RadarSite = self._parse(RadarSite, payload, radar_id)
        _check_body_id("radar_id", site.radar_id, radar_id)
        self._set_site(site)

    def _set_site(self, site: RadarSite) -> None:
        state = self.radars.setdefault(site.radar_id, RadarState())
        if state.site == site:
            return
        state.site = site
        state.geometry = to_geometry(site)
        if state.tracker is None:
            state.tracker = self._tracker_factory(
                state.geometry, self.config.window_s, self.config.initiator, site.radar_id
            )
        else:  # a moved or re-characterised radar: same tracks, new geometry for new plots
            state.tracker.site = state.geometry
        self._correlation.forget(site.radar_id)
        self._changed()

    def _ingest_plots(self, radar_id: str, payload: bytes) -> None:
        batch: PlotBatch = self._parse(PlotBatch, payload, radar_id)
        _check_body_id("radar_id", batch.radar_id, radar_id)
        state = self.radars.get(radar_id)
        if state is None or state.tracker is None:
            raise RejectionError("unknown_radar", f"no site known for radar {radar_id!r}", radar_id)
        plots = plot_columns(batch)
        _accept_seq(state, batch.seq, radar_id)  # accepted: from here on the batch changes state
        state.plots += len(plots)
        self._enqueue(state, 1, radar_id, batch.seq, batch.time_s, plots)

    def _ingest_ais(self, source_id: str, payload: bytes) -> None:
        batch: AisBatch = self._parse(AisBatch, payload, source_id)
        _check_body_id("source_id", batch.source_id, source_id)
        state = self.ais.get(source_id) or AisState(ReferenceTracks(self.config.reference))
        _accept_seq(state, batch.seq, source_id)
        self.ais[source_id] = state
        state.reports += len(batch.reports.time_s)
        self._enqueue(state, 0, source_id, batch.seq, batch.time_s, batch)

    def _enqueue(
        self, state: RadarState | AisState, kind: int, source_id: str, seq: int, time_s: float, item: Any
    ) -> None:
        clock = max(time_s, state.last_time_s if state.last_time_s is not None else -np.inf)
        state.last_time_s = clock
        if not state.pending:
            heapq.heappush(self._heap, (clock, kind, source_id, seq))
        state.pending.append((clock, seq, item))
        self._changed()

    # -- data-time release ---------------------------------------------------------------
    def _watermark(self) -> float:
        states: list[RadarState | AisState] = [*self.radars.values(), *self.ais.values()]
        clocks = [s.last_time_s for s in states if s.last_time_s is not None]
        if not clocks:
            return -np.inf
        newest = max(clocks)
        # A radar whose site is known but which has not reported yet holds the others back
        # from the first data time seen, within the same lag bound.
        if any(s.last_time_s is None and s.tracker is not None for s in self.radars.values()):
            self._first_clock = min(self._first_clock, *clocks)
            clocks.append(self._first_clock)
        return min(c for c in clocks if c >= newest - self.config.max_lag_s)

    def _release(self, until: float) -> list[Outgoing]:
        out: list[Outgoing] = []
        while self._heap and self._heap[0][0] <= until:
            _, kind, source_id, _ = heapq.heappop(self._heap)
            try:
                if kind == 0:
                    ais = self.ais[source_id]
                    clock, batch = self._pop(ais, kind, source_id)
                    self._process_ais(ais, batch, clock)
                else:
                    radar = self.radars[source_id]
                    clock, plots = self._pop(radar, kind, source_id)
                    out.extend(self._process(source_id, radar, plots, clock))
            except Exception as exc:  # a bug costs this batch's outputs, never the service
                detail = f"processing failed: {type(exc).__name__}: {exc}"
                key = self.keys.ais(source_id) if kind == 0 else self.keys.plots(source_id)
                out.append(self._reject(key, RejectionError("internal", detail, source_id), None))
        return out

    def _pop(self, state: RadarState | AisState, kind: int, source_id: str) -> tuple[float, Any]:
        """Take the head of a source's pending queue and put its next batch on the heap."""
        clock, _seq, item = state.pending.popleft()
        if state.pending:
            head = state.pending[0]
            heapq.heappush(self._heap, (head[0], kind, source_id, head[1]))
        return clock, item

    def _process_ais(self, state: AisState, batch: AisBatch, clock: float) -> None:
        r = batch.reports
        state.reference.add(
            np.asarray(r.time_s, dtype=float),
            np.asarray(r.mmsi, dtype=str),
            np.asarray(r.latitude_deg, dtype=float),
            np.asarray(r.longitude_deg, dtype=float),
            clock,
        )
        state.released_time_s = clock
        self._changed()

    def _process(self, radar_id: str, state: RadarState, plots: PlotColumns, clock: float) -> list[Outgoing]:
        assert state.tracker is not None and state.geometry is not None
        state.tracker.update(plots, clock)
        state.released_time_s = clock
        tracks = state.tracker.tracks()
        out = [Outgoing(self.keys.tracks(radar_id), dump_json(track_batch(radar_id, clock, tracks)))]
        me = Source(radar_id, state.geometry, lambda t: tracks)
        for ps in self._correlation.update(me, self._partners(radar_id), clock):
            out.append(Outgoing(self.keys.pairs(ps["radar_a"], ps["radar_b"]), dump_json(ps)))
        self._changed()
        return out

    def _partners(self, radar_id: str) -> list[Source]:
        """Every other radar with tracks and every AIS source with reports, in id order."""
        out = []
        for rid, r in sorted(self.radars.items()):
            if rid != radar_id and r.tracker is not None and r.released_time_s is not None:
                out.append(Source(rid, r.geometry, _tracks_of(r.tracker)))
        for sid, a in sorted(self.ais.items()):
            if a.released_time_s is not None:
                out.append(Source(sid, None, a.reference.table))
        return out

    # -- snapshots -----------------------------------------------------------------------
    def _changed(self) -> None:
        self.version += 1
        self._snapshot = None

    def snapshot(self) -> Snapshot:
        """An immutable view of the current state, cheap to take repeatedly."""
        if self._snapshot is None:
            self._snapshot = self._build_snapshot()
        return self._snapshot

    def _build_snapshot(self) -> Snapshot:
        tracks: dict[str, tuple[float, TrackTable]] = {}
        rows = []
        for rid, s in sorted(self.radars.items()):
            table = s.tracker.tracks() if s.tracker is not None else TrackTable.empty()
            tracks[rid] = (s.released_time_s if s.released_time_s is not None else 0.0, table)
            rows.append(
                {
                    "site": s.site.model_dump() if s.site is not None else {"radar_id": rid},
                    "radar_id": rid,
                    "batches": s.batches,
                    "plots": s.plots,
                    "rejected": s.rejected,
                    "lost_batches": s.lost_batches,
                    "window_plots": s.tracker.window_plots if s.tracker is not None else 0,
                    "tracks_confirmed": int(table.confirmed.sum()),
                    "tracks_tentative": int((~table.confirmed).sum()),
                    "last_time_s": s.last_time_s,
                }
            )
        return Snapshot(
            tracks=tracks,
            radar_rows=rows,
            pair_sets_all=self._correlation.pair_sets(),
            biases_all=list(self._correlation.biases()),
            correlation=self._correlation.timings(),
            rejected=dict(sorted(self.rejected.items())),
            method=self.config.method,
            prefix=self.config.prefix,
        )


def _tracks_of(tracker: Tracker) -> Callable[[float], TrackTable]:
    return lambda time_s: tracker.tracks()
