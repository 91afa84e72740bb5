"""The stateful worker: ``ingest(key, payload) -> outgoing messages``.  No I/O, no threads.

A thin coordinator of the stages in :mod:`service.pipeline`: it decodes a message, lets the
:class:`~service.pipeline.sequencer.Sequencer` admit it (``seq``, data clock, hostile-input
policies) and release whatever the watermark allows in data-time order, runs each released
batch through the tracking and correlation stages, and hands back the outputs to publish.  The
read model (:meth:`Engine.snapshot`) is immutable views whose JSON is built only when read.

A message is checked whole before anything changes: a rejected message changes no state, and
a released batch whose processing fails is rolled back by its stage (the tracker applies a
batch whole or not at all) and reported as ``internal``.

What a restart keeps (contract §4.6 "State") is :meth:`Engine.export_state`, an
:class:`EngineState` that :mod:`service.state` writes and gives back to
:meth:`Engine.restore_state` at the next start.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import TypeAdapter, ValidationError

from service.config import EngineConfig
from service.correlation import PairCorrelator
from service.correlation.registration import RegistrationRowsData
from service.geo import Site
from service.pipeline.correlation_process import RemoteCorrelation
from service.pipeline.correlation_stage import CorrelationStage, SharedRows
from service.pipeline.errors import RejectionError
from service.pipeline.merger import TableMerger
from service.pipeline.read_model import RadarRow, Snapshot, track_batch
from service.pipeline.sequencer import RADAR, REFERENCE, Release, Sequencer, SourceClock
from service.pipeline.track_exchange import StatesReceiver, StatesSender, decode_states
from service.pipeline.tracking_stage import SiteChange, TrackerFactory, TrackingStage, to_geometry
from service.tracking.base import PlotColumns, Tracker, TrackTable
from service.wire.keys import Keys
from service.wire.models import (
    MAX_PAYLOAD_BYTES,
    AdsbBatch,
    AisBatch,
    AisReportsModel,
    BiasSet,
    PlotBatch,
    RadarSite,
    RadarStatus,
    RegistrationRows,
    WorkerClock,
    rejection_reason,
)
from service.wire.outputs import encode, rejection

__all__ = [
    "Engine",
    "EngineConfig",
    "EngineState",
    "Outgoing",
    "RejectionError",
    "Snapshot",
    "load_sites",
    "plot_columns",
]


class Outgoing:
    """A message the transport should publish; its payload is encoded when first read.

    A transport with nobody listening on ``key`` never reads it, so unread outputs cost nothing.
    """

    def __init__(self, key: str, body: Callable[[], Any]) -> None:
        self.key = key
        #: The payload as a JSON-ready object, built when called.
        self.body = body

    @cached_property
    def payload(self) -> bytes:
        return encode(self.body())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Outgoing) and (self.key, self.payload) == (other.key, other.payload)

    def __hash__(self) -> int:
        return hash((self.key, self.payload))

    def __repr__(self) -> str:
        return f"Outgoing({self.key!r})"


_SITE_LIST = TypeAdapter(list[RadarSite])
#: Partitioned: track states of radars whose site has not come yet, held until it comes (the
#: owner can hear a radar's site before this worker does, and the workers' messages are taken
#: ahead of inputs); at most this many messages and payload bytes in all: beyond, the oldest
#: held is given up, rejected ``unknown_radar``.
MAX_PENDING_STATES = 256
MAX_PENDING_STATES_BYTES = 64 * 1024 * 1024


def load_sites(path: str | Path) -> tuple[RadarSite, ...]:
    """Sites from a JSON file holding a list of ``RadarSite`` (setting ``TOPOFUSION_SITES``)."""
    p = Path(path)
    try:
        return tuple(_SITE_LIST.validate_json(p.read_bytes()))
    except FileNotFoundError:
        raise ValueError(f"sites file not found: {p}") from None
    except ValidationError as exc:
        raise ValueError(f"sites file {p} is not a JSON list of RadarSite: {exc}") from None


def tracker_for(config: EngineConfig, epoch: Callable[[], int] = lambda: 0) -> TrackerFactory:
    """The tracker of each radar: the configured initiator, window and parameters, its track
    ids numbered from the id epoch ``epoch()`` gives when the tracker is made (at the radar's
    first batch; :meth:`Engine.restore_state`)."""
    from service.tracking import make_tracker
    from service.truth_labels import TruthLabelledTracker

    make_tracker(Site("check", 0.0, 0.0), config.window_s, config.initiator, "check", config.tracking)

    def factory(site: Site, radar_id: str) -> Tracker:
        # TrackBatch.truth_id (evaluation only) is tallied outside the tracker
        tracker = make_tracker(
            site, config.window_s, config.initiator, radar_id, config.tracking, epoch=epoch()
        )
        return TruthLabelledTracker(tracker)

    return factory


@dataclass(frozen=True)
class EngineState:
    """What the engine keeps across a restart (contract §4.6 "State"; :mod:`service.state`
    writes and reads it), in plain values and numpy arrays.

    ``sites``: every radar's ``RadarSite``; ``sources``: each source's latest ``seq`` and data
    clock (:meth:`Sequencer.export_state`); ``reference_kinds``: each reference source's input
    kind (``ais`` or ``adsb``); ``published_biases``: the ``BiasSet`` the bias worker last
    published (another partitioned worker's ``GET /biases``); ``correlation``: the registration
    memories and the joint bias solution (:meth:`CorrelationStage.export_state`);
    ``data_clock_s``: the newest data clock when taken (None: no data yet).  Tracks and pair
    books are not kept: the input that follows rebuilds them.
    """

    sites: list[dict[str, Any]]
    sources: list[dict[str, Any]]
    reference_kinds: dict[str, str]
    published_biases: dict[str, Any] | None
    correlation: dict[str, Any]
    data_clock_s: float | None

    def summary(self) -> str:
        """One line of what it holds (for the log)."""
        memories = self.correlation["memories"]
        rows = sum(len(m["rows"]["time"]) for m in memories)
        joint = self.correlation["joint"]
        return (
            f"{len(self.sites)} radar sites, {len(self.sources)} source clocks, "
            f"{len(memories)} registration memories ({rows} rows), "
            f"biases of {len(joint['radar_ids']) if joint else 0} radars"
        )


def plot_columns(batch: PlotBatch) -> PlotColumns:
    p = batch.plots
    n = len(p.time_s)
    return PlotColumns(
        time_s=np.asarray(p.time_s, dtype=float),
        range_m=np.asarray(p.range_m, dtype=float),
        azimuth_deg=np.asarray(p.azimuth_deg, dtype=float),
        elevation_deg=_floats(p.elevation_deg, n),
        altitude_m=_floats(p.altitude_m, n),
        truth_id=_labels(p.truth_id, n),
        mode_3a=_labels(p.mode_3a, n),
        mode_s=_labels(p.mode_s, n),
    )


def _floats(column: Sequence[float | None] | None, n: int) -> np.ndarray:
    """A wire column of numbers or nulls as floats, NaN for null (all NaN when left out)."""
    if column is None:
        return np.full(n, np.nan)
    if None in column:
        return np.array([np.nan if x is None else x for x in column], dtype=float)
    return np.asarray(column, dtype=float)


def _labels(column: list[str | None] | None, n: int) -> np.ndarray:
    """A wire label column as an object array (all None when left out)."""
    out = np.full(n, None, dtype=object)
    if column is not None:
        out[:] = column
    return out


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _rows_body(r: SharedRows) -> dict[str, Any]:
    """The ``RegistrationRows`` payload of rows an owned pair added."""
    rows = r.rows
    return {
        "source_a": r.source_a,
        "source_b": r.source_b,
        "reference": r.reference,
        "time_s": rows.time_s,
        "track_a": rows.track_a.tolist(),
        "track_b": rows.track_b.tolist(),
        "p_a": rows.p_a.tolist(),
        "p_b": rows.p_b.tolist(),
        "s": rows.s.reshape(len(rows), 9).tolist(),
    }


def _parse(model: type[Any], payload: bytes, source_id: str | None) -> Any:
    try:
        return model.model_validate_json(payload)
    except ValidationError as exc:
        reason, detail = rejection_reason(exc)
        raise RejectionError(reason, detail, source_id) from None


def _check_body_id(field_name: str, body_id: str, key_id: str) -> None:
    if body_id != key_id:
        raise RejectionError("schema", f"{field_name} {body_id!r} in body != {key_id!r} in key", key_id)


class Engine:
    """Per-radar windows and trackers, AIS references, cross-source correlation, rejections."""

    def __init__(
        self,
        config: EngineConfig | None = None,
        tracker_factory: TrackerFactory | None = None,
        correlation_process: bool = False,
    ) -> None:
        """``correlation_process``: run the correlation stage in a child process (two cores:
        tracking and correlation at once; same results, pair sets handed out a little later,
        and :meth:`close` stops it)."""
        self.config = config or EngineConfig()
        self.keys = Keys(self.config.prefix)
        self.sequencer = Sequencer(self.config.sequencer)
        #: The track-id epoch (:meth:`restore_state`): 0 unless a state directory says otherwise.
        self.epoch = 0
        self.tracking = TrackingStage(
            tracker_factory or tracker_for(self.config, lambda: self.epoch), self.config.site
        )
        c = self.config
        self.correlation: CorrelationStage | RemoteCorrelation
        stage_args = (c.method, c.cadence, c.reference, c.correlation, c.partition)
        if correlation_process:
            self.correlation = RemoteCorrelation(*stage_args)
        else:
            self.correlation = CorrelationStage(*stage_args)
        self.partition = c.partition
        #: Partitioned: the correlation stage's input, every radar's tables (own and peers')
        #: and the references, in data-time order (see "Partitioned workers" above).
        self.merger = TableMerger()
        #: Partitioned: the workers whose liveliness token is present (the transport tells).
        self.alive: set[int] = set(range(1, self.partition.count + 1))
        self._clock_sent: dict[str, Any] | None = None
        self._progress_sent: dict[str, Any] | None = None
        self._idle = False
        #: Partitioned: each other worker's ``correlated_s`` (the bias worker waits for them).
        self._correlated_by: dict[int, float] = {}
        self.sender = StatesSender(self.config.exchange)
        self.receiver = StatesReceiver()
        #: (radar id, decoded message, payload bytes, key), oldest first.
        self._pending_states: deque[tuple[str, Any, int, str]] = deque()
        self._pending_bytes = 0
        #: The joint bias estimate as the bias worker last published it (other workers).
        self.published_biases: dict[str, Any] | None = None
        self._biases_sent: object = None
        self.plots: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        #: Each reference source's input kind (``ais`` or ``adsb``): an id is one or the other.
        self.reference_kinds: dict[str, str] = {}
        self._snapshot: Snapshot | None = None
        for site in self.config.sites:
            self._set_site(site)

    # -- views of the stages' state (tests, evaluation, diagnostics) ------------------------------
    @property
    def radars(self) -> dict[str, SourceClock]:
        return {k: s for k, s in self.sequencer.sources.items() if s.kind == RADAR}

    @property
    def ais(self) -> dict[str, SourceClock]:
        return {k: s for k, s in self.sequencer.sources.items() if s.kind == REFERENCE}

    def correlators(self) -> list[PairCorrelator]:
        """The live pair correlators, one per correlated source pair (none in this process when
        the correlation runs in its own)."""
        if isinstance(self.correlation, RemoteCorrelation):
            return []
        return list(self.correlation.correlators.values())

    def close(self) -> None:
        """Stop the correlation process, if any (the engine's only resource)."""
        if isinstance(self.correlation, RemoteCorrelation):
            self.correlation.close()

    # -- kept across a restart (service.state) -------------------------------------------------
    @property
    def data_clock_s(self) -> float:
        """The newest data clock of an accepted batch (-inf: none yet); never goes back."""
        return self.sequencer.newest_s

    def export_state(self) -> EngineState:
        """What a restart keeps (:class:`EngineState`), taken between two messages.  With the
        correlation in its own process this waits until it has answered everything sent to it,
        so the state is of one moment (:meth:`request_state` does not wait)."""
        return EngineState(correlation=self.correlation.export_state(), **self._own_state())

    def request_state(self) -> Callable[[], EngineState | None]:
        """:meth:`export_state` without waiting for the correlation process: the engine's own
        part is taken now, the correlation's at the same point of its input, and the returned
        function gives the state once the process has answered (None until then; the answer is
        taken with the next messages or :meth:`poll`; ``RuntimeError`` if the process died
        meanwhile).  In process the state is taken at once."""
        if not isinstance(self.correlation, RemoteCorrelation):
            state = self.export_state()
            return lambda: state
        own = self._own_state()
        correlation = self.correlation.request_state()

        def ready() -> EngineState | None:
            answered = correlation()
            return None if answered is None else EngineState(correlation=answered, **own)

        return ready

    def _own_state(self) -> dict[str, Any]:
        """The fields of :class:`EngineState` but the correlation's (new objects: later input
        changes none of them)."""
        clock = self.data_clock_s
        return {
            "sites": [r.site.model_dump(mode="json") for _, r in sorted(self.tracking.radars.items())],
            "sources": self.sequencer.export_state(),
            "reference_kinds": dict(sorted(self.reference_kinds.items())),
            "published_biases": self.published_biases,
            "data_clock_s": clock if np.isfinite(clock) else None,
        }

    def restore_state(self, state: EngineState | None, epoch: int) -> None:
        """Take what :meth:`export_state` gave, before any input (``None``: nothing but the epoch).

        New radar tracks (each radar's tracker is made at its next batch) and new system tracks
        are numbered from the first number of id epoch ``epoch``
        (:func:`~service.tracking.base.first_number`), so no id of an earlier start comes again
        (a ``tracker_factory`` given to the engine numbers its own).  A saved site of a radar
        the configuration names gives way to the configuration's; the others come back as if
        announced again.  Everything is read before anything changes: a state that is not one
        raises (``KeyError``, ``TypeError``, ``ValueError``) and leaves the engine as it was.
        """
        configured = {site.radar_id for site in self.config.sites}
        sites: list[RadarSite] = []
        sources: list[tuple[float, str, int, int]] = []
        kinds: dict[str, str] = {}
        published = None
        if state is not None:
            sites = [
                site
                for site in (RadarSite.model_validate(s) for s in state.sites)
                if site.radar_id not in configured
            ]
            sources = Sequencer.read_state(state.sources)
            kinds = {str(k): str(v) for k, v in state.reference_kinds.items()}
            if not set(kinds.values()) <= {"ais", "adsb"}:
                raise ValueError(f"reference kinds {sorted(set(kinds.values()))}")
            if state.published_biases is not None:
                try:
                    published = BiasSet.model_validate(state.published_biases).model_dump()
                except ValidationError:  # of an older wire model: the bias worker's next one comes
                    published = None
        geometries = {rid: r.geometry for rid, r in self.tracking.radars.items()}
        geometries.update({site.radar_id: to_geometry(site) for site in sites})
        self.correlation.restore_state(None if state is None else state.correlation, epoch, geometries)
        # from here on nothing raises
        self.epoch = epoch
        for site in sites:
            try:
                self._set_site(site)
            except RejectionError:  # more sites than the sequencer holds (max_sources): the rest wait
                break
        self.sequencer.restore_state(sources)
        self.reference_kinds.update(kinds)
        self.published_biases = published
        self._snapshot = None

    # -- ingest ------------------------------------------------------------------------
    def ingest(self, key: str, payload: bytes, receive_time_s: float | None = None) -> list[Outgoing]:
        """Validate and apply one input message; returns what to publish.  Never raises on input."""
        kind = self.keys.classify(key)
        peer = self.keys.classify_peer(key) if kind is None and not self.partition.whole else None
        try:
            if len(payload) > MAX_PAYLOAD_BYTES:
                raise self._too_large(key, len(payload))
            if peer is not None:
                return self._ingest_peer(peer[0], peer[1], payload)
            if kind is None:
                raise RejectionError("schema", f"not an input key of prefix {self.config.prefix!r}: {key}")
            what, source_id = kind
            if what == "plots" and not self.partition.owns(source_id):
                return []  # another worker's radar: not even parsed
            if what == "site":
                site: RadarSite = _parse(RadarSite, payload, source_id)
                _check_body_id("radar_id", site.radar_id, source_id)
                self._set_site(site)
                return []
            if what == "plots":
                self._admit_plots(source_id, payload)
            else:
                self._admit_reference(what, source_id, payload)
            return self._process(self.sequencer.release())
        except RejectionError as rejection:
            return self._rejected(key, rejection, receive_time_s, peer is not None)
        except Exception as exc:  # a bug must cost one message, never the service
            internal = RejectionError("internal", f"{type(exc).__name__}: {exc}", kind[1] if kind else None)
            return self._rejected(key, internal, receive_time_s, peer is not None)

    def _too_large(self, key: str, size: int) -> RejectionError:
        kind = self.keys.classify(key)
        return RejectionError(
            "too_large", f"payload of {size} bytes > {MAX_PAYLOAD_BYTES}", kind[1] if kind else None
        )

    def reject_too_large(self, key: str, size: int, receive_time_s: float | None = None) -> list[Outgoing]:
        """A payload of ``size`` bytes the transport did not even copy (above
        ``MAX_PAYLOAD_BYTES``): rejected as :meth:`ingest` rejects it."""
        peer = not self.partition.whole and self.keys.classify_peer(key) is not None
        return self._rejected(key, self._too_large(key, size), receive_time_s, peer)

    def _rejected(
        self, key: str, rej: RejectionError, receive_time_s: float | None, peer: bool
    ) -> list[Outgoing]:
        """A rejected message: counted and reported, by the worker that owns its source (every
        worker sees every input; one reports it, as one worker alone would)."""
        if not peer and not self.partition.owns(rej.source_id or key):
            return []
        return [self._reject(key, rej, receive_time_s)]

    def flush(self) -> list[Outgoing]:
        """Release every held batch regardless of the watermark (end of a replay or shutdown)."""
        out = self._process(self.sequencer.flush())
        if not self.partition.whole:
            out.extend(self._correlate(self.merger.flush()))
        self.correlation.finish()
        out.extend(self._remote_results())
        self._snapshot = None
        return out

    def _reject(self, key: str, rej: RejectionError, receive_time_s: float | None) -> Outgoing:
        self.rejected[rej.reason] += 1
        self.sequencer.count_rejected(rej.source_id)
        self._snapshot = None
        when = receive_time_s if receive_time_s is not None else time.time()
        body = rejection(key, rej.source_id, rej.reason, rej.detail, when)
        return Outgoing(self.keys.errors, lambda: body)

    def _set_site(self, site: RadarSite) -> None:
        # Partitioned: every worker holds every site (the geometry of every pair it may
        # correlate); only the owner's sequencer waits for the radar's batches.
        if self.partition.owns(site.radar_id):
            self._drop(self.sequencer.announce(site.radar_id, RADAR))
        change = self.tracking.set_site(site)
        if change is SiteChange.MOVED:
            self.correlation.moved(self.tracking.radars[site.radar_id].geometry)
        if change is not SiteChange.SAME:
            self._snapshot = None
        if any(rid == site.radar_id for rid, _, _, _ in self._pending_states):
            kept: deque[tuple[str, Any, int, str]] = deque()
            for held in self._pending_states:
                if held[0] == site.radar_id:
                    self._pending_bytes -= held[2]
                    self._apply_states(held[0], held[1])
                else:
                    kept.append(held)
            self._pending_states = kept

    def _drop(self, source_ids: Iterable[str]) -> None:
        for sid in source_ids:
            self.reference_kinds.pop(sid, None)
            self.tracking.drop(sid)
            self.plots.pop(sid, None)
            self.correlation.forget(sid)
            self.sender.forget(sid)
            self.receiver.forget(sid)

    def _admit_plots(self, radar_id: str, payload: bytes) -> None:
        batch: PlotBatch = _parse(PlotBatch, payload, radar_id)
        _check_body_id("radar_id", batch.radar_id, radar_id)
        if radar_id not in self.tracking.radars:
            raise RejectionError("unknown_radar", f"no site known for radar {radar_id!r}", radar_id)
        plots = plot_columns(batch)
        adm = self.sequencer.check(radar_id, RADAR, batch.seq, batch.time_s)
        self._drop(self.sequencer.accept(adm, plots))  # accepted: from here on it changes state
        self.plots[radar_id] += len(plots)
        self._snapshot = None

    def _admit_reference(self, kind: str, source_id: str, payload: bytes) -> None:
        """An AIS or ADS-B batch: one reference-source path for both (their reports differ
        only in the id column and in the altitude ADS-B may give)."""
        batch: AisBatch | AdsbBatch = _parse(AisBatch if kind == "ais" else AdsbBatch, payload, source_id)
        _check_body_id("source_id", batch.source_id, source_id)
        held = self.reference_kinds.get(source_id)
        if held is not None and held != kind:
            raise RejectionError("schema", f"source id {source_id!r} is taken by an {held} source", source_id)
        adm = self.sequencer.check(source_id, REFERENCE, batch.seq, batch.time_s)
        self._drop(self.sequencer.accept(adm, batch))
        self.reference_kinds[source_id] = kind
        self.plots[source_id] += len(batch.reports.time_s)
        self._snapshot = None

    # -- released batches ----------------------------------------------------------------
    def _process(self, released: Iterable[Release]) -> list[Outgoing]:
        out: list[Outgoing] = []
        for rel in released:
            self._snapshot = None
            try:
                if rel.kind == REFERENCE:
                    self._process_reference(rel)
                elif rel.expiry:
                    out.extend(self._process_radar(rel.source_id, None, rel.time_s))
                else:
                    out.extend(self._process_radar(rel.source_id, rel.item, rel.time_s))
            except Exception as exc:  # a bug costs this batch's outputs, never the service
                out.append(self._internal(rel, exc))
        if not self.partition.whole:
            self.merger.progress(self.partition.index, self.sequencer.last_limit)
            out.extend(self._correlate(self._merged()))
        out.extend(self._remote_results())
        return out

    def _merged(self) -> Iterable[Release]:
        """What the merger may release.  The bias worker's correlation stays within
        ``bias_lag_s`` of every other worker's (``correlated_s``), so that when it solves for
        a time ``T`` it holds every row up to ``T`` (``CorrelationStage._solve_due``)."""
        cap = np.inf
        if self.partition.solves_biases:
            others = self.alive - {self.partition.index}
            cap = min((self._correlated_by.get(k, -np.inf) for k in others), default=np.inf)
            cap += self.config.cadence.bias_lag_s
        return self.merger.release(self._owners(), cap)

    @property
    def answers_pending(self) -> bool:
        """The correlation process has not answered everything sent to it yet, or a progress
        message is held back (``poll`` sends both)."""
        if isinstance(self.correlation, RemoteCorrelation) and self.correlation.pending > 0:
            return True
        return (
            not self.partition.whole
            and self._progress_sent is not None
            and (self._progress_sent["released_s"] != _finite(self.sequencer.last_limit))
        )

    def poll(self) -> list[Outgoing]:
        """What the correlation process answered while no input came (an idle service must
        still publish the last pair updates)."""
        if isinstance(self.correlation, RemoteCorrelation):
            self.correlation.poll()
        elif self.partition.whole:
            return []
        self._idle = True
        try:
            out = self._remote_results()
        finally:
            self._idle = False
        if out:
            self._snapshot = None
        return out

    def progress(self) -> dict[str, Any]:
        """Partitioned: how far this worker has got (``/status`` ``partition.progress``)."""

        return {
            "released_s": _finite(self.sequencer.last_limit),
            "merged_s": _finite(self.merger.last_limit),
            "held": len(self.merger),
            "state_gaps": sum(self.receiver.gaps.values()),
            "waiting_for": sorted(
                k for k in self._owners() if self.merger.released.get(k, -np.inf) <= self.merger.last_limit
            ),
        }

    def set_alive(self, workers: set[int]) -> list[Outgoing]:
        """The workers that are up (liveliness): the merger waits for these only.  Returns
        what the merge then lets through (a worker that left no longer holds it back)."""
        self.alive = set(workers) | {self.partition.index}
        if self.partition.whole:
            return []
        self._snapshot = None
        return self._correlate(self._merged()) + self._remote_results()

    def _owners(self) -> set[int]:
        """The live workers the merger waits for: those owning a known radar, and this one."""
        owners = {self.partition.owner(rid) for rid in self.tracking.radars}
        return (owners & self.alive) | {self.partition.index}

    def _due(self, new: dict[str, Any], sent: dict[str, Any] | None, fields: tuple[str, ...]) -> bool:
        """A progress or clock message is sent once a value moved ``exchange.step_s`` of data
        time (or appeared), and whenever anything moved while idle (``poll``): a message per
        input would cost the peers more than the tables they carry."""
        if sent is None or new == sent:
            return sent is None
        if self._idle:
            return True
        old = sent.get("clocks", sent)
        now = new.get("clocks", new)
        step = self.config.exchange.step_s
        return any(
            (now.get(f) is not None) != (old.get(f) is not None)
            or (now.get(f) is not None and now[f] - old[f] >= step)
            for f in fields
        ) or set(now) != set(old)

    def _clock(self) -> list[Outgoing]:
        """This worker's state for the others, when it changed: its progress (how far it has
        released and correlated, :class:`~service.pipeline.merger.TableMerger`) and its radars'
        data clocks (the network watermark, :meth:`Sequencer.observe`)."""

        merged = self.merger.last_limit
        correlated = (
            self.correlation.correlated_through(merged)
            if isinstance(self.correlation, RemoteCorrelation)
            else merged
        )
        progress = {
            "partition": str(self.partition),
            "released_s": _finite(self.sequencer.last_limit),
            "correlated_s": _finite(correlated),
        }
        clocks = {
            "partition": str(self.partition),
            "clocks": {
                rid: s.last_time_s
                for rid, s in sorted(self.sequencer.sources.items())
                if s.kind == RADAR and not s.foreign and s.last_time_s is not None
            },
        }
        out = []
        if self._due(progress, self._progress_sent, ("released_s", "correlated_s")):
            self._progress_sent = progress
            out.append(Outgoing(self.keys.worker_progress(self.partition.index), lambda: progress))
        if self._due(clocks, self._clock_sent, tuple(clocks["clocks"])):
            self._clock_sent = clocks
            out.append(Outgoing(self.keys.worker_clock(self.partition.index), lambda: clocks))
        return out

    def _internal(self, rel: Release, exc: Exception) -> Outgoing:
        detail = f"processing failed: {type(exc).__name__}: {exc}"
        key = (
            self.keys.input(self.reference_kinds.get(rel.source_id, "ais"), rel.source_id)
            if rel.kind == REFERENCE
            else self.keys.plots(rel.source_id)
        )
        return self._reject(key, RejectionError("internal", detail, rel.source_id), None)

    def _remote_results(self) -> list[Outgoing]:
        """Pair sets and failures the correlation process answered since the last call, the
        registration rows to share and the biases to publish (partitioned workers)."""
        out = []
        if isinstance(self.correlation, RemoteCorrelation):
            out = [Outgoing(self.keys.pairs(*k), view.body) for k, view in self.correlation.take_ready()]
            for source_id, detail in self.correlation.take_errors():
                key = self.keys.plots(source_id) if source_id else self.keys.errors
                out.append(self._reject(key, RejectionError("internal", detail, source_id or None), None))
        if not self.partition.whole:
            out.extend(self._partition_outputs())
            out.extend(self._clock())  # after the rows: it says they are all out
        for view in self.correlation.take_system():
            self._snapshot = None
            out.append(Outgoing(self.keys.system_tracks, lambda view=view: view.body("confirmed")))  # type: ignore[misc]
        return out

    def _partition_outputs(self) -> list[Outgoing]:
        out = [
            Outgoing(self.keys.registration(*r.key), lambda r=r: _rows_body(r))  # type: ignore[misc]
            for r in self.correlation.take_rows()
        ]
        biases = self.correlation.biases
        if self.partition.solves_biases and biases is not self._biases_sent and biases:
            self._biases_sent = biases
            body = {
                "time_s": max(b["time_s"] for b in biases),
                "partition": str(self.partition),
                "biases": list(biases),
            }
            out.append(Outgoing(self.keys.biases, lambda: body))
        return out

    def _process_reference(self, rel: Release) -> None:
        if not self.partition.whole:
            # Into the merger, which orders it with every worker's radar tables.
            seq = 0 if rel.expiry else rel.item.seq
            self.merger.push(REFERENCE, rel.source_id, seq, rel.time_s, rel.item, expiry=rel.expiry)
            return
        if rel.expiry:
            self.correlation.silent(rel.source_id)
        else:
            self._reference_to_correlation(rel.source_id, rel.item, rel.time_s)

    def _reference_to_correlation(self, source_id: str, batch: AisBatch | AdsbBatch, clock: float) -> None:
        r = batch.reports
        if isinstance(r, AisReportsModel):
            ids, altitude = np.asarray(r.mmsi, dtype=str), np.zeros(len(r.time_s))  # vessels: sea level
        else:
            ids = np.asarray(r.icao24, dtype=str)
            altitude = _floats(r.altitude_m, len(r.time_s))  # NaN: not reported (ReferenceTracks.add)
        self.correlation.reference(
            source_id,
            clock,
            np.asarray(r.time_s, dtype=float),
            ids,
            np.asarray(r.latitude_deg, dtype=float),
            np.asarray(r.longitude_deg, dtype=float),
            altitude,
            "ais" if isinstance(batch, AisBatch) else "adsb",
        )

    def _process_radar(self, radar_id: str, plots: PlotColumns | None, clock: float) -> list[Outgoing]:
        """A released batch (``None``: the radar expired, its tracks coast out) and its pairs."""
        if plots is None:
            if not self.tracking.expire(radar_id, clock):
                return []
            table = self.tracking.radars[radar_id].table
        else:
            table = self.tracking.update(radar_id, plots, clock)
        out = [Outgoing(self.keys.tracks(radar_id), lambda: track_batch(radar_id, clock, table))]
        canonical = table.by_id()
        if not self.partition.whole:
            # Every message is a change on top of the previous one: built now, encoded when sent.
            body = self.sender.states(radar_id, canonical, clock)
            out.append(Outgoing(self.keys.track_states(radar_id), lambda: body))
            body["expiry"] = plots is None
            self.merger.push(RADAR, radar_id, body["seq"], clock, canonical, expiry=plots is None)
            return out
        return out + self._correlate_radar(radar_id, canonical, clock)

    def _correlate_radar(self, radar_id: str, table: TrackTable, clock: float) -> list[Outgoing]:
        geometry = self.tracking.radars[radar_id].geometry
        return [
            Outgoing(self.keys.pairs(*key), self.correlation.views[key].body)
            for key in self.correlation.radar(radar_id, geometry, table, clock)
        ]

    # -- partitioned workers -------------------------------------------------------------
    def _correlate(self, released: Iterable[Release]) -> list[Outgoing]:
        """The merger's releases (every radar's tables and the references in data-time order)
        into the correlation stage, which correlates the pairs this worker owns."""
        out: list[Outgoing] = []
        for rel in released:
            self._snapshot = None
            try:
                if rel.kind == REFERENCE:
                    if rel.expiry:
                        self.correlation.silent(rel.source_id)
                    else:
                        self._reference_to_correlation(rel.source_id, rel.item, rel.time_s)
                elif not rel.expiry and rel.source_id in self.tracking.radars:
                    # (an expired radar's owner sends the table its tracks coasted out to)
                    out.extend(self._correlate_radar(rel.source_id, rel.item, rel.time_s))
            except Exception as exc:  # a bug costs this update's outputs, never the service
                out.append(self._internal(rel, exc))
        return out

    def _ingest_peer(self, kind: str, ids: tuple[str, ...], payload: bytes) -> list[Outgoing]:
        """What another worker of the partitioned network published for the others."""
        if kind == "track_states":
            radar_id = ids[0]
            if self.partition.owns(radar_id):
                return []  # our own, heard back
            msg = decode_states(payload, radar_id)
            _check_body_id("radar_id", msg.radar_id, radar_id)
            if radar_id not in self.tracking.radars:
                return self._hold_states(radar_id, msg, len(payload), self.keys.track_states(radar_id))
            self._apply_states(radar_id, msg)
            return []  # released once its owner says how far it has published (worker_progress)
        if kind in ("worker_clock", "worker_progress"):
            clock: WorkerClock = _parse(WorkerClock, payload, None)
            worker = int(ids[0])
            if clock.partition != f"{worker}/{self.partition.count}":
                raise RejectionError("schema", f"worker {clock.partition} on the key of worker {worker}")
            if worker == self.partition.index:
                return []
            if kind == "worker_clock":
                for rid, c in clock.clocks.items():
                    if not self.partition.owns(rid):
                        self.sequencer.observe(rid, c)
            else:
                self.merger.progress(worker, clock.released_s if clock.released_s is not None else -np.inf)
                self._correlated_by[worker] = (
                    clock.correlated_s if clock.correlated_s is not None else -np.inf
                )
            return self._process(self.sequencer.release())
        if kind == "registration":
            if not self.partition.solves_biases:
                return []
            rows: RegistrationRows = _parse(RegistrationRows, payload, ids[0])
            if sorted((rows.source_a, rows.source_b)) != sorted(ids):
                raise RejectionError(
                    "schema", f"sources {rows.source_a}, {rows.source_b} != key {ids}", ids[0]
                )
            if self.partition.owns_pair(rows.source_a, rows.source_b):
                return []  # our own pair
            site_a = self._geometry(rows.source_a)
            site_b = None if rows.reference else self._geometry(rows.source_b)
            k = len(rows.p_a)
            data = RegistrationRowsData(
                rows.time_s,
                np.asarray(rows.track_a, dtype=str),
                np.asarray(rows.track_b, dtype=str),
                np.asarray(rows.p_a, dtype=float).reshape(k, 3),
                np.asarray(rows.p_b, dtype=float).reshape(k, 3),
                np.asarray(rows.s, dtype=float).reshape(k, 3, 3),
            )
            self.correlation.mirror_rows((ids[0], ids[1]), site_a, site_b, data)
            return []
        if kind == "biases":
            if not self.partition.solves_biases:
                self.published_biases = _parse(BiasSet, payload, None).model_dump()
                self._snapshot = None
            return []
        return []  # worker status: the transport's

    def _hold_states(self, radar_id: str, msg: Any, size: int, key: str) -> list[Outgoing]:
        """Hold a radar's track states until its site comes; beyond the bounds the oldest held
        messages are given up, each reported as its own rejection."""
        self._pending_states.append((radar_id, msg, size, key))
        self._pending_bytes += size
        out = []
        while (
            len(self._pending_states) > MAX_PENDING_STATES or self._pending_bytes > MAX_PENDING_STATES_BYTES
        ):
            rid, _, n, k = self._pending_states.popleft()
            self._pending_bytes -= n
            rej = RejectionError("unknown_radar", f"no site known for radar {rid!r}", rid)
            out.extend(self._rejected(k, rej, None, True))
        return out

    def _apply_states(self, radar_id: str, msg: Any) -> None:
        table = self.receiver.apply(msg)
        if table is not None:
            self.merger.push(RADAR, radar_id, msg.seq, msg.time_s, table, expiry=msg.expiry)
        self._snapshot = None

    def _geometry(self, radar_id: str) -> Any:
        radar = self.tracking.radars.get(radar_id)
        if radar is None:
            raise RejectionError("unknown_radar", f"no site known for radar {radar_id!r}", radar_id)
        return radar.geometry

    # -- read model ----------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        """An immutable view of the current state; costs O(radars + pairs), not O(tracks)."""
        if self._snapshot is None:
            self._snapshot = self._build_snapshot()
        return self._snapshot

    def _build_snapshot(self) -> Snapshot:
        tracks = {}
        rows = []
        sources = self.sequencer.sources
        for rid in self.receiver.radars():
            tracks[rid] = self.receiver.latest(rid)
        for rid, r in sorted(self.tracking.radars.items()):
            if not self.partition.owns(rid):
                continue
            clock = sources.get(rid)
            tracks[rid] = (
                clock.released_time_s if clock and clock.released_time_s is not None else 0.0,
                r.table,
            )
            confirmed = r.confirmed
            rows.append(
                RadarRow(
                    r.site,
                    RadarStatus(
                        radar_id=rid,
                        batches=clock.batches if clock else 0,
                        plots=self.plots.get(rid, 0),
                        rejected=clock.rejected if clock else 0,
                        lost_batches=clock.lost_batches if clock else 0,
                        window_plots=self.tracking.window_plots(rid),
                        tracks_confirmed=confirmed,
                        tracks_tentative=len(r.table) - confirmed,
                        last_time_s=clock.last_time_s if clock else None,
                        restarts=clock.restarts if clock else 0,
                        window_evicted=self.tracking.window_evicted(rid),
                        expired=clock.expired if clock else False,
                    ),
                )
            )
        return Snapshot(
            tracks=tracks,
            radar_rows=rows,
            pair_views=self.correlation.pair_views(),
            biases_all=list(
                self.correlation.biases
                if self.partition.solves_biases or self.published_biases is None
                else self.published_biases["biases"]
            ),
            correlation=self.correlation.timings(),
            rejected=dict(sorted(self.rejected.items())),
            method=self.config.method,
            prefix=self.config.prefix,
            sites={rid: r.site for rid, r in self.tracking.radars.items()},
            progress=self.progress() if not self.partition.whole else {},
            adsb_sources=frozenset(k for k, kind in self.reference_kinds.items() if kind == "adsb"),
            system=self.correlation.system_view,
        )
