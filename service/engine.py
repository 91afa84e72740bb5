"""The stateful worker: ``ingest(key, payload) -> outgoing messages``.  No I/O, no threads.

A thin coordinator of the stages in :mod:`service.pipeline`, one path for every message::

    decode -> sequencer (seq, data clock, release in data-time order)
           -> tracking (a radar's batch -> its table)
           -> merger (every radar's tables in release order; other workers' too)
           -> correlation (here or in its own process)
           -> publication (each table with what correlation answered for it: TrackBatch,
              then PairSet and system tracks, whole together)

A worker alone is the one-owner case of a partitioned network (:mod:`.pipeline.peers`): its
merger releases each table as soon as it is pushed.  A message is checked whole before
anything changes: a rejected message changes no state, and a released batch whose processing
fails is rolled back by its stage and reported as ``internal``.  What a restart keeps (contract
§4.6 "State") is :meth:`Engine.export_state`, given back to :meth:`Engine.restore_state`.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Callable, Collection, Iterable
from itertools import chain
from typing import Any

from service.config import EngineConfig, aid_problems
from service.correlation import PairCorrelator
from service.pipeline.assessment_feed import AssessmentFeed
from service.pipeline.correlation_process import ChildProcessRunner
from service.pipeline.correlation_runner import CorrelationRunner, InProcessRunner
from service.pipeline.decode import decode_input, plot_columns, reference_columns, reference_kind
from service.pipeline.errors import RejectionError, unknown_radar
from service.pipeline.feed import FeedWatch
from service.pipeline.merger import TableMerger
from service.pipeline.partner_aid import PartnerAid
from service.pipeline.peers import Peers, Released, finite_or_none
from service.pipeline.publication import Publication
from service.pipeline.read_model import Snapshot, build_snapshot
from service.pipeline.restart import EngineState, own_state, read_state, state_when_answered
from service.pipeline.sequencer import RADAR, REFERENCE, Refused, Release, Sequencer
from service.pipeline.shared_links import Position
from service.pipeline.system_stage import links_grid_s
from service.pipeline.tracking_stage import (
    SiteChange,
    TrackerFactory,
    TrackingStage,
    to_geometry,
    tracker_for,
)
from service.tracking.base import TrackTable
from service.wire.keys import Keys
from service.wire.models import MAX_PAYLOAD_BYTES, AdsbBatch, AisBatch, PlotBatch, RadarSite
from service.wire.outgoing import Outgoing
from service.wire.outputs import bounded, rejection

__all__ = ["Engine", "EngineConfig", "EngineState", "Outgoing", "RejectionError", "Snapshot"]


#: Releases held for the aid of association at most (partitioned: while another worker is
#: waited for and does not progress, at most ``TOPOFUSION_PEER_GRACE_S`` of wall time); beyond,
#: the oldest is tracked with the aid known, counted in ``aid_forced``.  Half the ingest
#: queue's default capacity: a stall of a few seconds at ten times real time fits.
MAX_AID_HELD = 2048


class Engine:
    """Per-radar windows and trackers, references, cross-source correlation, rejections."""

    def __init__(
        self,
        config: EngineConfig | None = None,
        tracker_factory: TrackerFactory | None = None,
        correlation_process: bool = False,
    ) -> None:
        """``correlation_process``: the correlation stage in a child process (two cores; the
        same outputs, a little later; :meth:`close` stops it)."""
        self.config = c = config or EngineConfig()
        self.keys = Keys(c.prefix)
        self.partition = c.partition
        self.sequencer = Sequencer(c.sequencer)
        #: The track-id epoch (:meth:`restore_state`): 0 unless a state directory says otherwise.
        self.epoch = 0
        self.tracking = TrackingStage(tracker_factory or tracker_for(c, lambda: self.epoch), c.site)
        runner = ChildProcessRunner if correlation_process else InProcessRunner
        self.correlation: CorrelationRunner = runner(
            c.method, c.cadence, c.reference, c.correlation, c.partition, c.tracking.aid.enabled
        )
        #: Every radar's tables and the references, in release order, into correlation.
        self.merger = TableMerger()
        #: The data time through which the outputs are complete, as last reported (it never
        #: goes back: :attr:`outputs_time_s`).
        self._outputs_through = -math.inf
        #: The aid of association (``tracking.aid``; None: off): every pair's links and
        #: registration by data time, fed back to the trackers (:mod:`.pipeline.partner_aid`).
        self.aid: PartnerAid | None = None
        if c.tracking.aid.enabled:
            problems = aid_problems(c)
            if problems:
                raise ValueError("; ".join(problems))
            self.aid = PartnerAid(c.tracking.aid, self.tracking, links_grid_s(c.cadence.system_interval_s))
        #: Released batches waiting for the other workers' links their aid reads (partitioned,
        #: the aid on: :meth:`_process`), in release order with whatever was released after them.
        self._held: deque[Release] = deque()
        #: Batches tracked without waiting for every worker's links and tables, as more than
        #: :data:`MAX_AID_HELD` waited (their aid may differ from one worker's).
        self.aid_forced = 0
        self.peers = Peers(
            c,
            self.keys,
            self.sequencer,
            self.tracking,
            self.merger,
            self.correlation,
            self._released,
            self.aid,
        )
        self.publication = Publication(self.keys)
        #: Tables sent to correlation and not answered yet: (radar, data time, table, own).
        self._unpublished: deque[tuple[str, float, TrackTable, bool]] = deque()
        self.rejected: Counter[str] = Counter()
        self.feed = FeedWatch(c.feed)
        #: Each reference source's input kind (``ais`` or ``adsb``): an id is one or the other.
        self.reference_kinds: dict[str, str] = {}
        self._snapshot: Snapshot | None = None
        self.assessment = AssessmentFeed(c.assessment)  # each radar against the references (§5.3)
        for site in c.sites:
            self._set_site(site)

    # -- views of the stages' state (tests, evaluation, diagnostics) ------------------------------
    def pair_correlators(self) -> list[PairCorrelator]:
        """The live pair correlators (none in this process when the correlation runs in its own)."""
        return self.correlation.pair_correlators()

    def close(self) -> None:
        """Stop the correlation process, if any (the engine's only resource)."""
        self.correlation.close()

    # -- kept across a restart (service.state) -------------------------------------------------
    @property
    def data_clock_s(self) -> float:
        """The newest data clock of an accepted batch (-inf: none yet); never goes back."""
        return self.sequencer.newest_s

    def export_state(self) -> EngineState:
        """What a restart keeps (:class:`EngineState`), taken between two messages (with the
        correlation in its own process, once it has answered everything sent to it)."""
        return EngineState(correlation=self.correlation.export_state(), **self._own_state())

    def request_state(self) -> Callable[[], EngineState | None]:
        """:meth:`export_state` without waiting for the correlation process: the engine's part
        now, the correlation's at the same point of its input (:func:`state_when_answered`)."""
        return state_when_answered(self._own_state(), self.correlation.request_state())

    def _own_state(self) -> dict[str, Any]:
        return own_state(self.tracking, self.sequencer, self.reference_kinds, self.peers.published_biases)

    def restore_state(self, state: EngineState | None, epoch: int) -> None:
        """Take what :meth:`export_state` gave, before any input (``None``: nothing but the epoch).

        New radar tracks and system tracks are numbered from id epoch ``epoch``, so no id of
        an earlier start comes again.  A saved site of a radar the configuration names gives
        way to the configuration's.  Everything is read before anything changes: a state that
        is not one raises (``KeyError``, ``TypeError``, ``ValueError``) and changes nothing.
        """
        sites, sources, kinds, published = read_state(state, {site.radar_id for site in self.config.sites})
        geometries = {rid: r.geometry for rid, r in self.tracking.tracked.items()}
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
        self.peers.published_biases = published
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
                got = self.peers.ingest(peer[0], peer[1], payload)
                self._snapshot = None
                out = [self._reject(k, rej, None) for k, rej in got.given_up]
                if not got.moved:
                    return out
                # (another worker's clocks may settle this worker's lone ones, with no batch of
                # its own to come: the end of a stream, a radar of a long scan)
                return (
                    out
                    + self._report_refused(self.sequencer.settle())
                    + self._process(self.sequencer.release())
                )
            if kind is None:
                raise RejectionError("schema", f"not an input key of prefix {self.config.prefix!r}: {key}")
            what, source_id = kind
            if what == "plots" and not self.partition.owns(source_id):
                return []  # another worker's radar: not even parsed
            msg = decode_input(what, source_id, payload)
            if isinstance(msg, RadarSite):
                if source_id in self.reference_kinds:  # (one kind of source an id: contract §2)
                    raise RejectionError(
                        "schema",
                        f"source id {source_id!r} is taken by a reference source "
                        f"({self.reference_kinds[source_id]})",
                        source_id,
                    )
                return self._set_site(msg)
            return self._admit(what, source_id, msg, receive_time_s) + self._process(self.sequencer.release())
        except RejectionError as rej:
            return self._rejected(key, rej, receive_time_s, peer is not None)
        except Exception as exc:  # a bug must cost one message, never the service
            internal = RejectionError("internal", f"{type(exc).__name__}: {exc}", kind[1] if kind else None)
            return self._rejected(key, internal, receive_time_s, peer is not None)

    def _too_large(self, key: str, size: int) -> RejectionError:
        source = kind[1] if (kind := self.keys.classify(key)) else None
        return RejectionError("too_large", f"payload of {size} bytes > {MAX_PAYLOAD_BYTES}", source)

    def reject_too_large(self, key: str, size: int, receive_time_s: float | None = None) -> list[Outgoing]:
        """A payload the transport did not copy (over ``MAX_PAYLOAD_BYTES``): as :meth:`ingest` would."""
        peer = not self.partition.whole and self.keys.classify_peer(key) is not None
        return self._rejected(key, self._too_large(key, size), receive_time_s, peer)

    def _rejected(self, key: str, rej: RejectionError, received: float | None, peer: bool) -> list[Outgoing]:
        """A rejected message: counted and reported, by the worker that owns its source (every
        worker sees every input; one reports it, as one worker alone would)."""
        owner = peer or self.partition.owns(rej.source_id or key)
        return [self._reject(key, rej, received)] if owner else []

    def _reject(self, key: str, rej: RejectionError, receive_time_s: float | None) -> Outgoing:
        self.rejected[rej.reason] += 1
        # (the log line quotes no more of a hostile key, id or detail than the Rejection does)
        source = None if rej.source_id is None else bounded(rej.source_id, 80)
        self.feed.refused(source, rej.reason, bounded(key), bounded(rej.detail))
        self.sequencer.count_rejected(rej.source_id)
        self._snapshot = None
        when = receive_time_s if receive_time_s is not None else time.time()
        body = rejection(key, rej.source_id, rej.reason, rej.detail, when)
        return Outgoing(self.keys.errors, lambda: body)

    def flush(self) -> list[Outgoing]:
        """Release every held batch regardless of the watermark (end of a replay or shutdown)."""
        out = self._report_refused(self.sequencer.drop_held()) + self._process(
            self.sequencer.flush(), flushing=True
        )
        out += self._correlate(self.merger.flush())
        self.correlation.finish()
        out += self._results()
        self.assessment.finish()
        self._snapshot = None
        return out

    def expire_silent(self, now_s: float, waiting: Collection[str] = ()) -> list[Outgoing]:
        """Expire the sources silent for the feed's wall-clock limit (:mod:`.pipeline.feed`;
        ``now_s`` on ``time.monotonic()``; ``waiting``: the sources with input still queued)."""
        if not any([self.sequencer.expire_now(sid) for sid in self.feed.silent(now_s, waiting)]):
            return []
        self._snapshot = None
        seq = self.sequencer
        return self._process(chain(seq.release(until=seq.last_limit), seq.release()))

    def _set_site(self, site: RadarSite) -> list[Outgoing]:
        # Partitioned: every worker holds every site (the geometry of every pair it may
        # correlate); only the owner's sequencer waits for the radar's batches.
        owns = self.partition.owns(site.radar_id)
        out = self._drop(self.sequencer.announce(site.radar_id, RADAR)) if owns else []
        change = self.tracking.set_site(site)
        self.sequencer.sites_known = len(self.tracking.tracked)
        if change is SiteChange.MOVED:
            self.correlation.moved(self.tracking.tracked[site.radar_id].geometry)
        if change is not SiteChange.SAME:
            self._snapshot = None
        self.peers.site_known(site.radar_id)
        return out

    def _drop(self, source_ids: Iterable[str], keep_site: bool = False) -> list[Outgoing]:
        """Sources evicted, or forgotten (``keep_site``: site, counters and id numbering stay)."""
        out = []
        for sid in source_ids:
            self.reference_kinds.pop(sid, None)
            self.tracking.clear(sid) if keep_site else self.tracking.drop(sid)
            self.correlation.forget(sid)
            self.peers.forget(sid)
            if self.aid is not None:
                self.aid.forget(sid)
            self.feed.forget(sid)
            self.assessment.forget(sid)
            out += self.publication.forget(sid)
        self.sequencer.sites_known = len(self.tracking.tracked)
        return out

    def _admit(
        self,
        what: str,
        source_id: str,
        batch: PlotBatch | AisBatch | AdsbBatch,
        received: float | None = None,
    ) -> list[Outgoing]:
        """A radar's plot batch, or an AIS or ADS-B batch (one reference path for both),
        decoded: checked against the sources, then accepted by the sequencer."""
        item: Any
        if isinstance(batch, PlotBatch):
            if source_id not in self.tracking.tracked:
                raise unknown_radar(source_id)
            item, n, kind = plot_columns(batch), len(batch.plots.time_s), RADAR
        else:
            held = self.reference_kinds.get(source_id)
            if held is not None and held != what:
                detail = f"source id {source_id!r} is taken by an {held} source"
                raise RejectionError("schema", detail, source_id)
            item, n, kind = batch, len(batch.reports.time_s), REFERENCE
        adm = self.sequencer.check(source_id, kind, batch.seq, batch.time_s)
        # accepted: from here on it changes state
        evicted, refused = self.sequencer.accept(adm, item, n, received)
        out = self._drop(evicted) + self._report_refused(refused)
        self.feed.taken(source_id, self.sequencer.newest_s)
        if kind == REFERENCE:
            self.reference_kinds[source_id] = what
        self._snapshot = None
        return out

    def _report_refused(self, refused: list[Refused]) -> list[Outgoing]:
        """Batches held as a step ahead (``pipeline.sequencer``) and then refuted or unconfirmed,
        or taken with a lone clock that data refuted, each reported at its own receipt (offline,
        the recorded one: never the run's clock)."""
        return [self._reject(self._input_key(sid), rej, received) for sid, rej, received in refused]

    def _input_key(self, source_id: str) -> str:
        return self.keys.input(self.reference_kinds.get(source_id) or "plots", source_id)

    def _internal(self, source_id: str | None, detail: str) -> Outgoing:
        """A failure processing a source's message (None: of no one message), on its input key."""
        key = self._input_key(source_id) if source_id else self.keys.errors
        return self._reject(key, RejectionError("internal", detail, source_id), None)

    # -- released batches: the one path --------------------------------------------------
    def _process(self, released: Iterable[Release], flushing: bool = False) -> list[Outgoing]:
        """Released batches through tracking into the merger, then what the merger releases
        through correlation, then everything the correlation answered.  With the aid on, a
        batch waits for every pair's links through its lag (:meth:`_aid_ready`); partitioned,
        it and what was released after it are held until the other workers' are in
        (``flushing``: the end of the input, nothing more to wait for)."""
        out: list[Outgoing] = []
        self._run_held(out, flushing)
        for rel in released:  # (one at a time: the sequencer releases lazily)
            self._held.append(rel)
            self._run_held(out, flushing)
        self.merger.progress(self.partition.index, self._released_s())
        out += self._correlate(self.merger.release(self.peers.owners(), self.peers.cap()))
        return out + self._results()

    def _run_held(self, out: list[Outgoing], flushing: bool) -> None:
        """The released batches in order, each once its aid is ready (:meth:`_process`)."""
        held = self._held
        while held:
            rel = held[0]
            if self._asks_aid(rel):
                try:
                    ready = self._aid_ready((rel.time_s, rel.source_id), out) or flushing
                except Exception as exc:  # a bug costs this batch its aid, never the service
                    out.append(self._internal(rel.source_id, f"aid failed: {type(exc).__name__}: {exc}"))
                    ready = True
                if not ready and len(held) > MAX_AID_HELD:  # (a worker that stalls: not forever)
                    self.aid_forced += 1
                    ready = True
                if not ready:
                    return
            held.popleft()
            self._snapshot = None
            try:
                if rel.forget:
                    out += self._drop([rel.source_id], keep_site=True)
                elif rel.kind == REFERENCE:
                    seq = 0 if rel.expiry else rel.item.seq
                    self.merger.push(REFERENCE, rel.source_id, seq, rel.time_s, rel.item, expiry=rel.expiry)
                else:
                    out += self._track(rel.source_id, rel.item, rel.time_s)
            except Exception as exc:  # a bug costs this batch's outputs, never the service
                out.append(self._internal(rel.source_id, f"processing failed: {type(exc).__name__}: {exc}"))

    def _asks_aid(self, rel: Release) -> bool:
        """Whether a release is a batch whose tracker may ask for the aid of association (a
        track of it in a formation, or the search for formations due): only those wait for
        what the aid reads (on the national network about a batch in four)."""
        if self.aid is None or rel.kind == REFERENCE or rel.item is None or rel.forget:
            return False
        return rel.source_id in self.tracking.tracked and self.tracking.wants_aid(rel.source_id, rel.time_s)

    def _released_s(self) -> float:
        """How far this worker has released its batches into tracking: the sequencer's limit, or
        just short of the oldest batch held for its aid (the workers it waits for must hear
        that, or none of them could correlate through its lag)."""
        limit = self.sequencer.last_limit
        if self._held:
            limit = min(limit, math.nextafter(self._held[0].time_s, -math.inf))
        return limit

    def _released(self) -> Released:
        """:meth:`_released_s`, the place of the oldest batch held for its aid (every table
        before it is published) and how many releases wait."""
        head = self._held[0] if self._held else None  # (a batch: only a batch waits)
        place = None if head is None else (head.time_s, head.source_id)
        return Released(self._released_s(), place, len(self._held), self.aid_forced)

    def _aid_ready(self, position: Position, out: list[Outgoing]) -> bool:
        """Whether the aid of the batch at ``position`` (data time, radar) has all it reads:
        every pair's links and every radar's table through its lag's time (this worker's
        correlation through it, correlated now, its answers taken into ``out``, and,
        partitioned, every other live worker's tables, released through it to the merge, and
        links: their ``correlated_s``, sent after the links they cover)."""
        assert self.aid is not None
        due_s = self.aid.due_s(position[0])
        out += self._answers_through(due_s)
        if self.partition.whole:
            return True
        return self.merger.through(self.peers.owners()) >= due_s and self.peers.others_correlated() >= due_s

    def _track(self, radar_id: str, plots: Any, clock: float) -> list[Outgoing]:
        """A released batch of a radar (``None``: it expired, its tracks coast out)."""
        if plots is None:
            if not self.tracking.expire(radar_id, clock):
                return []
            table = self.tracking.tracked[radar_id].table
        else:
            aid = None
            if self.aid is not None and self.tracking.wants_aid(radar_id, clock):
                aid = self.aid.references(radar_id, clock)
            table = self.tracking.update(radar_id, plots, clock, aid)
            self.assessment.plots(radar_id, self.tracking.tracked[radar_id].geometry, plots, clock)
        table = table.by_id()
        if self.aid is not None:
            self.aid.record(radar_id, clock, table)  # (the table the other workers are sent)
        return self.peers.own_table(radar_id, table, clock, plots is None)

    def _answers_through(self, time_s: float) -> list[Outgoing]:
        """Every table up to data time ``time_s`` that the merge may release correlated and its
        answer taken (the aid of association: a batch's aid is the links a fixed data time
        before it, whichever way the correlation runs; this worker's batches before the one
        that asks are all released)."""
        index = self.partition.index
        if time_s > self.merger.released.get(index, -math.inf):
            self.merger.progress(index, time_s)
        out = self._correlate(self.merger.release(self.peers.owners(), self.peers.cap()))
        self.correlation.wait_through(time_s)
        return out + self._results()

    def _correlate(self, released: Iterable[Release]) -> list[Outgoing]:
        """The merger's releases (every radar's tables and the references in data-time order)
        into the correlation stage, which correlates the pairs this worker owns."""
        out: list[Outgoing] = []
        for rel in released:
            self._snapshot = None
            try:
                if rel.kind == REFERENCE and rel.expiry:
                    self.correlation.silent(rel.source_id)
                elif rel.kind == REFERENCE:
                    kind, cols = reference_kind(rel.item), reference_columns(rel.item)
                    self.assessment.reference(rel.source_id, kind, cols, rel.item, rel.time_s)
                    self.correlation.reference(rel.source_id, rel.time_s, *cols, kind)
                elif rel.source_id in self.tracking.tracked:
                    if self.aid is not None:  # (no later batch of this worker comes before it)
                        self.aid.passed((rel.time_s, rel.source_id))
                    # published with what the correlation answers for it (:meth:`_results`)
                    own = self.partition.owns(rel.source_id)
                    self._unpublished.append((rel.source_id, rel.time_s, rel.item, own))
                    geometry = self.tracking.tracked[rel.source_id].geometry
                    self.correlation.radar(rel.source_id, geometry, rel.item, rel.time_s)
            except Exception as exc:  # a bug costs this update's outputs, never the service
                out.append(self._internal(rel.source_id, f"processing failed: {type(exc).__name__}: {exc}"))
        return out

    def _results(self, idle: bool = False) -> list[Outgoing]:
        """What the correlation answered since the last call (pair sets, failures, system
        tracks), held to the tables as they are now, and what goes to the other workers (the
        answers come first: a capped merge sends nothing, yet its ``correlated_s`` must move)."""
        self.correlation.poll()
        out: list[Outgoing] = []
        for answer in self.correlation.take_answers():
            if answer.op == "radar":  # the table it answered for, then what the table changed
                radar = self._unpublished.popleft()
                out += self.publication.tracks(*radar)
            if self.aid is not None:
                for crossing in answer.crossings:
                    self.aid.crossed(crossing)
            out += [self.publication.pairs(key, view) for key, view in answer.updated]
            self.assessment.pairs(answer.updated, self.reference_kinds)
            if answer.system is not None:
                out.append(self.publication.system_tracks(answer.system))
        out += [self._internal(sid or None, detail) for sid, detail in self.correlation.take_errors()]
        out += self.peers.outputs(idle)
        if self.assessment.advance(self.outputs_time_s) or out:
            self._snapshot = None
        return out

    @property
    def answers_pending(self) -> bool:
        """The correlation process has not answered everything sent to it yet, or a progress
        message is held back (``poll`` sends both)."""
        return self.correlation.pending > 0 or self.peers.progress_pending

    def poll(self) -> list[Outgoing]:
        """What the correlation process answered while no input came (an idle service must
        still publish the last pair updates)."""
        return self._results(idle=True)

    def wait_for(self, workers: set[int]) -> list[Outgoing]:
        """The workers the merger waits for (up, or gone for less than the grace): these only.  Returns
        what the merge then lets through (a worker that left no longer holds it back)."""
        self.peers.wait_for(workers)
        self._snapshot = None
        return self._process(())  # (and the batches held for their aid, if it was waited for)

    @property
    def outputs_time_s(self) -> float | None:
        """The data time up to which every published output reflects every input processed
        (contract §5.1): what was released, as far as the correlation has answered it."""
        released = min(self._released_s(), self.merger.last_limit)
        # A watermark never goes back: a lagging source's batch released late (the release did
        # not wait for it) does not pull it back while the correlation answers that batch.
        through = self.correlation.correlated_through(released)
        if through > self._outputs_through:
            self._outputs_through = through
        return finite_or_none(self._outputs_through)

    # -- read model ----------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        """An immutable view of the current state; costs O(radars + pairs), not O(tracks)."""
        if self._snapshot is None or self._snapshot.correlation["pending"] != self.correlation.pending:
            self._snapshot = build_snapshot(
                tracking=self.tracking,
                sources=self.sequencer.sources,
                owned=self.partition.owns,
                tables=self.publication.tables,
                pair_views=self.publication.pair_views(),
                system=self.publication.system,
                biases=self.peers.biases(),
                correlation={**self.correlation.timings(), "pending": self.correlation.pending},
                rejected=dict(sorted(self.rejected.items())),
                method=self.config.method,
                prefix=self.config.prefix,
                progress=self.peers.progress(),
                adsb_sources=frozenset(k for k, kind in self.reference_kinds.items() if kind == "adsb"),
                outputs_time_s=self.outputs_time_s,
                performance=self.assessment.view,
            )
        return self._snapshot
