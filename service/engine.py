"""The stateful worker: ``ingest(key, payload) -> outgoing messages``.  No I/O, no threads.

Data time, not wall time
------------------------
Per radar, batches are taken strictly in ``seq`` order.  Across radars, an accepted batch is
held until every *live* radar has reported at least up to its ``time_s`` (the watermark) and
then released in ``(time_s, radar_id, seq)`` order.  Tracking and correlation therefore see
the same sequence whatever the interleaving of radars on arrival, so a replay at any speed
gives the same tracks and pairs as the live stream.  A radar whose data clock lags the newest
one by more than :attr:`EngineConfig.max_lag_s` stops holding the others back (an outage must
not freeze the picture); its late batches are still tracked when they come.
"""

from __future__ import annotations

import heapq
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import TypeAdapter, ValidationError

from service.geo import Site, ecef_to_geodetic
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
    last_seq: int | None = None
    batches: int = 0
    reports: int = 0
    rejected: int = 0
    lost_batches: int = 0
    last_time_s: float | None = None


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

    return make_tracker(site, window_s=window_s, initiator=initiator, id_prefix=id_prefix)


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
    """Per-radar windows and trackers, cross-radar correlation, rejection bookkeeping."""

    def __init__(
        self, config: EngineConfig | None = None, tracker_factory: TrackerFactory | None = None
    ) -> None:
        self.config = config or EngineConfig()
        self.keys = Keys(self.config.prefix)
        self._tracker_factory = tracker_factory or _default_tracker_factory
        self.radars: dict[str, RadarState] = {}
        self.ais: dict[str, AisState] = {}
        self.rejected: Counter[str] = Counter()
        self._heap: list[tuple[float, str, int]] = []
        self._first_clock = np.inf  # heads of radars' pending queues
        self._correlation = _CorrelationStage(self.config)
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
                return self._ingest_plots(source_id, payload)
            self._ingest_ais(source_id, payload)
            return []
        except RejectionError as rejection:
            return [self._reject(key, rejection, receive_time_s)]
        except Exception as exc:  # a bug must cost one message, never the service
            internal = RejectionError("internal", f"{type(exc).__name__}: {exc}", kind[1] if kind else None)
            return [self._reject(key, internal, receive_time_s)]

    def flush(self) -> list[Outgoing]:
        """Release every held batch regardless of the watermark (end of a replay or shutdown)."""
        return self._release(until=np.inf)

    def _reject(self, key: str, rej: RejectionError, receive_time_s: float | None) -> Outgoing:
        self.rejected[rej.reason] += 1
        if rej.radar_id is not None:
            if rej.radar_id in self.radars:
                self.radars[rej.radar_id].rejected += 1
            elif rej.radar_id in self.ais:
                self.ais[rej.radar_id].rejected += 1
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
        self._correlation.site_changed(site.radar_id)
        self._changed()

    def _ingest_plots(self, radar_id: str, payload: bytes) -> list[Outgoing]:
        batch: PlotBatch = self._parse(PlotBatch, payload, radar_id)
        _check_body_id("radar_id", batch.radar_id, radar_id)
        state = self.radars.get(radar_id)
        if state is None or state.tracker is None:
            raise RejectionError("unknown_radar", f"no site known for radar {radar_id!r}", radar_id)
        plots = plot_columns(batch)
        _accept_seq(state, batch.seq, radar_id)  # accepted: from here on the batch changes state
        state.plots += len(plots)
        clock = batch.time_s if state.last_time_s is None else max(state.last_time_s, batch.time_s)
        state.last_time_s = clock
        if not state.pending:
            heapq.heappush(self._heap, (clock, radar_id, batch.seq))
        state.pending.append((clock, batch.seq, plots))
        self._changed()
        return self._release(until=self._watermark())

    def _ingest_ais(self, source_id: str, payload: bytes) -> None:
        batch: AisBatch = self._parse(AisBatch, payload, source_id)
        _check_body_id("source_id", batch.source_id, source_id)
        state = self.ais.get(source_id, AisState())
        _accept_seq(state, batch.seq, source_id)
        self.ais[source_id] = state
        state.reports += len(batch.reports.time_s)
        state.last_time_s = max(batch.time_s, state.last_time_s or -np.inf)
        self._changed()

    # -- data-time release ---------------------------------------------------------------
    def _watermark(self) -> float:
        clocks = [s.last_time_s for s in self.radars.values() if s.last_time_s is not None]
        if not clocks:
            return -np.inf
        newest = max(clocks)
        # A radar whose site is known but which has not reported yet holds the others back
        # from the first data time seen, within the same lag bound.
        if any(s.last_time_s is None and s.tracker is not None for s in self.radars.values()):
            self._first_clock = min(self._first_clock, *clocks)
            clocks.append(self._first_clock)
        live = [c for c in clocks if c >= newest - self.config.max_lag_s]
        return min(live)

    def _release(self, until: float) -> list[Outgoing]:
        out: list[Outgoing] = []
        while self._heap and self._heap[0][0] <= until:
            _, radar_id, _ = heapq.heappop(self._heap)
            state = self.radars[radar_id]
            clock, _seq, plots = state.pending.popleft()
            if state.pending:
                head = state.pending[0]
                heapq.heappush(self._heap, (head[0], radar_id, head[1]))
            try:
                out.extend(self._process(radar_id, state, plots, clock))
            except Exception as exc:  # a bug costs this batch's outputs, never the service
                detail = f"processing failed: {type(exc).__name__}: {exc}"
                out.append(
                    self._reject(
                        self.keys.plots(radar_id), RejectionError("internal", detail, radar_id), clock
                    )
                )
        return out

    def _process(self, radar_id: str, state: RadarState, plots: PlotColumns, clock: float) -> list[Outgoing]:
        assert state.tracker is not None
        state.tracker.update(plots, clock)
        state.released_time_s = clock
        tracks = state.tracker.tracks()
        out = [Outgoing(self.keys.tracks(radar_id), dump_json(track_batch(radar_id, clock, tracks)))]
        for pair_set in self._correlation.update(radar_id, clock, self.radars):
            out.append(
                Outgoing(self.keys.pairs(pair_set["radar_a"], pair_set["radar_b"]), dump_json(pair_set))
            )
        self._changed()
        return out

    # -- snapshots -----------------------------------------------------------------------
    def _changed(self) -> None:
        self.version += 1
        self._snapshot = None

    def snapshot(self) -> Snapshot:
        """An immutable view of the current state, cheap to take repeatedly."""
        if self._snapshot is None:
            self._snapshot = Snapshot.of(self)
        return self._snapshot


def track_batch(radar_id: str, time_s: float, tracks: TrackTable, status: str = "all") -> dict[str, Any]:
    """The contract's ``TrackBatch`` for a radar's tracks (``status``: confirmed, tentative, all)."""
    if status == "confirmed":
        tracks = tracks.take(tracks.confirmed)
    elif status == "tentative":
        tracks = tracks.take(~tracks.confirmed)
    lat, lon, alt = ecef_to_geodetic(tracks.position_ecef_m)
    rows = [
        {
            "track_id": str(tracks.track_id[i]),
            "status": "confirmed" if tracks.confirmed[i] else "tentative",
            "time_s": float(tracks.time_s[i]),
            "latitude_deg": float(lat[i]),
            "longitude_deg": float(lon[i]),
            "altitude_m": float(alt[i]),
            "position_ecef_m": [float(v) for v in tracks.position_ecef_m[i]],
            "velocity_ecef_mps": [float(v) for v in tracks.velocity_ecef_mps[i]],
            "plots": int(tracks.plots[i]),
            "truth_id": tracks.truth_id[i],
        }
        for i in range(len(tracks))
    ]
    return {"radar_id": radar_id, "time_s": time_s, "tracks": rows}


class _CorrelationStage:
    """One ``PairCorrelator`` per radar pair, updated on a data-time schedule."""

    def __init__(self, config: EngineConfig) -> None:
        self.config = config
        self.correlators: dict[tuple[str, str], Any] = {}
        self.next_due: dict[tuple[str, str], float] = {}
        self.last_time: dict[tuple[str, str], float] = {}
        self.timings_ms: deque[float] = deque(maxlen=2048)
        self.updates = 0
        self.last_ms = 0.0
        self.biases: list[dict[str, Any]] = []

    def site_changed(self, radar_id: str) -> None:
        for key in [k for k in self.correlators if radar_id in k]:
            del self.correlators[key]
            self.next_due.pop(key, None)
            self.last_time.pop(key, None)

    def update(self, radar_id: str, time_s: float, radars: dict[str, RadarState]) -> list[dict[str, Any]]:
        from service.correlation import PairCorrelator, estimate_biases

        me = radars[radar_id]
        assert me.geometry is not None
        results = []
        for other_id, other in sorted(radars.items()):
            if other_id == radar_id or other.tracker is None or other.released_time_s is None:
                continue
            assert other.geometry is not None
            if (
                np.linalg.norm(me.geometry.origin_ecef - other.geometry.origin_ecef)
                > self.config.max_site_distance_m
            ):
                continue
            key = (min(radar_id, other_id), max(radar_id, other_id))
            if time_s < self.next_due.get(key, -np.inf):
                continue
            self.next_due[key] = time_s + self.config.correlation_interval_s
            a, b = radars[key[0]], radars[key[1]]
            assert a.tracker is not None and b.tracker is not None
            assert a.geometry is not None and b.geometry is not None
            corr = self.correlators.get(key)
            if corr is None:
                corr = self.correlators[key] = PairCorrelator(self.config.method, a.geometry, b.geometry)
            corr.update(a.tracker.tracks(), b.tracker.tracks(), time_s)
            self.last_time[key] = time_s
            self.updates += 1
            self.last_ms = float(corr.last_update_ms)
            self.timings_ms.append(self.last_ms)
            results.append(pair_set(key[0], key[1], time_s, self.config.method, corr.pairs()))
        if results:
            self.biases = [bias_dict(b) for b in estimate_biases(list(self.correlators.values()), time_s)]
        return results

    def pair_sets(self) -> list[dict[str, Any]]:
        return [
            pair_set(a, b, self.last_time.get((a, b), 0.0), self.config.method, c.pairs())
            for (a, b), c in sorted(self.correlators.items())
        ]

    def timings(self) -> dict[str, Any]:
        t = np.asarray(self.timings_ms) if self.timings_ms else np.zeros(1)
        return {
            "updates": self.updates,
            "last_ms": round(self.last_ms, 3),
            "p50_ms": round(float(np.percentile(t, 50)), 3),
            "p99_ms": round(float(np.percentile(t, 99)), 3),
        }


def pair_set(radar_a: str, radar_b: str, time_s: float, method: str, pairs: Iterable[Any]) -> dict[str, Any]:
    return {
        "radar_a": radar_a,
        "radar_b": radar_b,
        "time_s": time_s,
        "method": method,
        "pairs": [
            {
                "track_a": p.track_a,
                "track_b": p.track_b,
                "status": p.status,
                "score": float(p.score),
                "statistic": _finite_or_none(p.statistic),
                "rotation_weight": _finite_or_none(p.rotation_weight),
                "scale": _finite_or_none(p.scale),
                "neighbors": int(p.neighbors),
                "hits": int(p.hits),
                "first_time_s": float(p.first_time_s),
                "last_time_s": float(p.last_time_s),
            }
            for p in pairs
        ],
    }


def _finite_or_none(x: float) -> float | None:
    """JSON has no NaN: a quantity the decision did not produce is ``null``."""
    return float(x) if np.isfinite(x) else None


def bias_dict(b: Any) -> dict[str, Any]:
    return {
        "radar_id": b.radar_id,
        "range_bias_m": float(b.range_bias_m),
        "azimuth_bias_deg": float(b.azimuth_bias_deg),
        "elevation_bias_deg": float(b.elevation_bias_deg),
        "pairs_used": int(b.pairs_used),
        "time_s": float(b.time_s),
    }


def _filter_status(items: list[dict[str, Any]], status: str) -> list[dict[str, Any]]:
    return items if status == "all" else [p for p in items if p["status"] == status]


@dataclass(frozen=True)
class Snapshot:
    """Immutable state for readers (HTTP handlers, queryables) on other threads."""

    tracks: dict[str, tuple[float, TrackTable]]
    radar_rows: list[dict[str, Any]]
    pair_sets_all: list[dict[str, Any]]
    biases_all: list[dict[str, Any]]
    correlation: dict[str, Any]
    rejected: dict[str, int]
    method: str
    prefix: str

    @staticmethod
    def of(engine: Engine) -> Snapshot:
        tracks: dict[str, tuple[float, TrackTable]] = {}
        rows = []
        for rid, s in sorted(engine.radars.items()):
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
            pair_sets_all=engine._correlation.pair_sets(),
            biases_all=list(engine._correlation.biases),
            correlation=engine._correlation.timings(),
            rejected=dict(sorted(engine.rejected.items())),
            method=engine.config.method,
            prefix=engine.config.prefix,
        )

    def radar_ids(self) -> list[str]:
        return [r["radar_id"] for r in self.radar_rows]

    def track_batch(self, radar_id: str, status: str = "confirmed") -> dict[str, Any] | None:
        if radar_id not in self.tracks:
            return None
        time_s, table = self.tracks[radar_id]
        return track_batch(radar_id, time_s, table, status)

    def track_batches(self, status: str = "all") -> list[dict[str, Any]]:
        return [b for rid in self.tracks if (b := self.track_batch(rid, status)) is not None]

    def pair_sets(
        self, radar_a: str | None = None, radar_b: str | None = None, status: str = "confirmed"
    ) -> list[dict[str, Any]]:
        wanted = {x for x in (radar_a, radar_b) if x is not None}
        out = []
        for ps in self.pair_sets_all:
            if not wanted <= {ps["radar_a"], ps["radar_b"]}:
                continue
            out.append({**ps, "pairs": _filter_status(ps["pairs"], status)})
        return out

    def biases(self) -> list[dict[str, Any]]:
        return list(self.biases_all)

    def status_core(self) -> dict[str, Any]:
        pairs = [p for ps in self.pair_sets_all for p in ps["pairs"]]
        return {
            "method": self.method,
            "prefix": self.prefix,
            "radars": [{k: v for k, v in r.items() if k != "site"} for r in self.radar_rows],
            "pairs_confirmed": sum(p["status"] == "confirmed" for p in pairs),
            "pairs_tentative": sum(p["status"] == "tentative" for p in pairs),
            "correlation": self.correlation,
            "rejected": self.rejected,
        }

    def status(self) -> dict[str, Any]:
        """Status without process-level fields (the node adds uptime, zenoh and queue)."""
        return {
            "uptime_s": 0.0,
            "zenoh": {"mode": "none", "listen": [], "connect": []},
            **self.status_core(),
        }

    def radars(self) -> list[dict[str, Any]]:
        return [
            {
                **r["site"],
                **{k: r[k] for k in ("batches", "plots", "rejected", "lost_batches", "last_time_s")},
            }
            for r in self.radar_rows
        ]
