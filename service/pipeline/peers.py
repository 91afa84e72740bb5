"""The other workers of a partitioned network (``--partition K/N``): what goes to them and
what comes from them.

Each worker tracks its own radars and correlates its own pairs (:mod:`.partition`).  To the
others it sends every table its radars' batches give (a change on top of the previous one,
:mod:`.track_exchange`), how far it has released and correlated, its radars' data clocks, and
the registration rows and links its pairs add (for worker 1, which solves the joint biases and
draws the system tracks, and sends back the biases).  From them it takes the same.  The
tables of every worker meet in the engine's :class:`~.merger.TableMerger`, which puts them in
the order one worker would have released them in.

A worker alone (``1/1``) is the one-owner case: it sends nothing, takes nothing, and its
merger releases each table as soon as it is pushed.  :class:`Peers` never calls the engine: it
works on the stages it is given and returns what to publish.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np

from service.correlation.correlator import CorrelationParams
from service.pipeline.correlation_runner import CorrelationRunner
from service.pipeline.correlation_stage import CadenceParams
from service.pipeline.decode import check_body_id, parse
from service.pipeline.errors import RejectionError, unknown_radar
from service.pipeline.merger import TableMerger
from service.pipeline.pair_exchange import (
    decode_links,
    decode_rows,
    links_body,
    links_frame,
    rows_body,
    rows_frame,
)
from service.pipeline.partition import Partition
from service.pipeline.partner_aid import PartnerAid
from service.pipeline.sequencer import RADAR, Sequencer
from service.pipeline.shared_links import Position
from service.pipeline.track_exchange import (
    ExchangeParams,
    StatesForm,
    StatesReceiver,
    StatesSender,
    decode_states,
    states_frame,
)
from service.pipeline.tracking_stage import TrackingStage
from service.tracking.base import TrackTable
from service.wire.keys import Keys
from service.wire.models import BiasSet, WorkerClock
from service.wire.outgoing import Outgoing


class PeerConfig(Protocol):
    """What the exchange takes of the engine's configuration (``EngineConfig``, above)."""

    @property
    def partition(self) -> Partition: ...
    @property
    def exchange(self) -> ExchangeParams: ...
    @property
    def cadence(self) -> CadenceParams: ...
    @property
    def correlation(self) -> CorrelationParams: ...


#: Track states of radars whose site has not come yet, held until it comes (the owner can hear
#: a radar's site before this worker does, and the workers' messages are taken ahead of
#: inputs); at most this many messages and payload bytes in all: beyond, the oldest held is
#: given up, rejected ``unknown_radar``.
MAX_PENDING_STATES = 256
MAX_PENDING_STATES_BYTES = 64 * 1024 * 1024


def finite_or_none(x: float) -> float | None:
    """``x`` as a JSON number, or None for an infinite clock (none yet)."""
    return float(x) if np.isfinite(x) else None


@dataclass(frozen=True)
class PeerInput:
    """What a message of another worker gave: held messages given up (each a rejection on its
    key), and whether the watermark may have moved (release what it allows)."""

    given_up: tuple[tuple[str, RejectionError], ...] = ()
    moved: bool = False


class Released(NamedTuple):
    """How far a worker has released its batches into tracking (every table up to
    ``released_s`` published), the release order's place (data time, radar) of the oldest batch
    it holds for the aid of association (None: none; every table before it is published), and
    how many batches wait behind it."""

    released_s: float
    held: Position | None = None
    held_batches: int = 0
    forced: int = 0  # batches tracked without waiting, as too many waited


class Peers:
    """This worker's exchange with the others (nothing at all when it is the only one)."""

    def __init__(
        self,
        config: PeerConfig,
        keys: Keys,
        sequencer: Sequencer,
        tracking: TrackingStage,
        merger: TableMerger,
        correlation: CorrelationRunner,
        released: Callable[[], Released] | None = None,
        aid: PartnerAid | None = None,
    ) -> None:
        """``released``: how far this worker has released its batches into tracking, and the
        place of the oldest batch it holds for its aid (default: the sequencer's limit, none);
        ``aid``: the aid of association, which takes every other worker's links and tables
        (:mod:`.partner_aid`)."""
        self.partition = partition = config.partition
        self.released = released or (lambda: Released(sequencer.last_limit))
        self.aid = aid
        self.keys = keys
        self.exchange = exchange = config.exchange
        self.cadence = config.cadence
        #: Every worker takes the others' links for the cycle step (:mod:`.cycle_links`).
        self.cycles = config.correlation.cycles
        self.sequencer = sequencer
        self.tracking = tracking
        self.merger = merger
        self.correlation = correlation
        #: The workers the merge waits for: those whose liveliness token is present, and those gone
        #: for less than the grace (the transport tells: ``PeerWorkers.waited_changed``).
        self.waited: set[int] = set(range(1, partition.count + 1))
        self.sender = StatesSender(exchange)
        self.receiver = StatesReceiver()
        #: Each other worker's ``correlated_s`` (the bias worker waits for them).
        self._correlated_by: dict[int, float] = {}
        #: The earliest of them last told to the correlation (worker 1 draws the picture to it).
        self._through: float | None = None
        self._clock_sent: dict[str, Any] | None = None
        self._progress_sent: dict[str, Any] | None = None
        #: (radar id, decoded message, payload bytes, key), oldest first.
        self._pending_states: deque[tuple[str, Any, int, str]] = deque()
        self._pending_bytes = 0
        #: The joint bias estimate as the bias worker last published it (other workers).
        self.published_biases: dict[str, Any] | None = None
        self._biases_sent: object = None
        #: A lone worker's own numbering of its tables (the merger's tie order).
        self._table_seq: dict[str, int] = {}
        #: Each other worker's latest progress: what forms it says it reads (packed_states,
        #: frame_states, frame_links, frame_rows).
        self._progress_of: dict[int, WorkerClock] = {}
        #: Clock and progress messages refused as another network's (another N or salt, a K
        #: taken twice): the merge cannot go on while such a worker holds a K it waits for
        #: (``/readyz`` says so, ``transport.readiness``), and the latest refusal's reason.
        self.mismatches = 0
        self.mismatch = ""
        #: The other workers' radars whose tables reached the merge (a gap in the receiver since
        #: drops its table there, not its tracks from the merge: they expire all the same).
        self._heard: set[str] = set()

    @property
    def alone(self) -> bool:
        return self.partition.whole

    # -- this worker's radars ------------------------------------------------------------------
    def own_table(self, radar_id: str, table: TrackTable, time_s: float, expiry: bool) -> list[Outgoing]:
        """A table of a radar this worker tracks: into the merger, and to the others as track
        states (a change on top of the previous one, built now, encoded when sent)."""
        if self.alone:
            seq = self._table_seq[radar_id] = self._table_seq.get(radar_id, 0) + 1
            self.merger.push(RADAR, radar_id, seq, time_s, table, expiry=expiry)
            return []
        form = self._form()
        body = self.sender.states(radar_id, table, time_s, form)
        body["expiry"] = expiry
        self.merger.push(RADAR, radar_id, body["seq"], time_s, table, expiry=expiry)
        framed = (lambda: states_frame(body)) if form == "frame" else None
        return [Outgoing(self.keys.track_states(radar_id), lambda: body, framed)]

    def _form(self) -> StatesForm:
        """How this worker's track states go: as frames, or packed, once every other worker
        of the partition said, in its latest progress, that it reads them
        (:meth:`ExchangeParams.form`)."""
        return self.exchange.form(self._all_read("frame_states"), self._all_read("packed_states"))

    def _all_read(self, form: str) -> bool:
        """Every other worker of the partition said, in its latest progress, that it reads
        ``form`` (a ``WorkerClock`` field)."""
        others = set(range(1, self.partition.count + 1)) - {self.partition.index}
        return all(bool(getattr(self._progress_of.get(k), form, False)) for k in others)

    def forget(self, source_id: str) -> None:
        self.sender.forget(source_id)
        self.receiver.forget(source_id)
        self._heard.discard(source_id)
        self.merger.call_off(source_id)
        self._table_seq.pop(source_id, None)

    def site_known(self, radar_id: str) -> None:
        """A radar's site came: the track states held for it are applied."""
        if not any(rid == radar_id for rid, _, _, _ in self._pending_states):
            return
        kept: deque[tuple[str, Any, int, str]] = deque()
        for held in self._pending_states:
            if held[0] == radar_id:
                self._pending_bytes -= held[2]
                self._apply_states(held[0], held[1])
            else:
                kept.append(held)
        self._pending_states = kept

    # -- the merge -----------------------------------------------------------------------------
    def owners(self) -> set[int]:
        """The live workers the merger waits for: those owning a known radar, and this one."""
        owners = {self.partition.owner(rid) for rid in self.tracking.tracked}
        return (owners & self.waited) | {self.partition.index}

    def cap(self) -> float:
        """How far the merger may release.  With the cycle step on, a worker's correlation stays
        within ``cycles.lag_s`` of every other worker's (``correlated_s``), so that the chains
        of an update at ``t`` find every pair's links of ``t - lag_s`` (:mod:`.cycle_links`);
        the bias worker's within ``bias_lag_s``, so that when it solves for a time ``T`` it
        holds every row up to ``T`` (``CorrelationStage._solve_due``)."""
        lags = [self.cycles.lag_s] if self.cycles.enabled else []
        if self.partition.solves_biases:
            lags.append(self.cadence.bias_lag_s)
        if self.alone or not lags:
            return np.inf
        return self.others_correlated() + min(lags)

    def wait_for(self, workers: set[int]) -> None:
        self.waited = set(workers) | {self.partition.index}
        for radar_id in sorted(self._heard):
            if self.partition.owner(radar_id) in self.waited or not self.merger.expiring(radar_id):
                self._silent_owner(radar_id)  # (one armed before stays as it was)
        self._others_through()

    def _silent_owner(self, radar_id: str) -> None:
        """A radar of another worker, after its owner came or went or a table of it came: while
        its owner is not waited for, the radar is silent to this worker, and its tracks coast
        out as a silent radar's do, ``source_expiry_s`` of data time after its last table (not
        before the merge's clock: an empty table, :meth:`TableMerger.expire`); its owner back
        calls that off (its next table brings the tracks back)."""
        if self.partition.owner(radar_id) in self.waited:
            self.merger.call_off(radar_id)
            return
        time_s, _ = self.receiver.latest(radar_id)  # (none after a gap: it expires at once)
        due = max(time_s + self.sequencer.params.source_expiry_s, self.merger.last_limit)
        self.merger.expire(radar_id, due, TrackTable.empty())

    def others_correlated(self) -> float:
        """How far every other live worker has correlated (and sent its links; none: no limit)."""
        others = self.waited - {self.partition.index}
        return min((self._correlated_by.get(k, -np.inf) for k in others), default=np.inf)

    def _others_through(self) -> None:
        """Worker 1: tell the correlation how far every other live worker has correlated (it
        draws the system tracks up to there, :mod:`.system_stage`)."""
        if self.alone or not self.partition.solves_biases:
            return
        through = self.others_correlated()
        if through != self._through:
            self._through = through
            self.correlation.others_through(through)

    def progress(self) -> dict[str, Any]:
        """How far this worker has got (``/status`` ``partition.progress``; none alone)."""
        if self.alone:
            return {}
        released = self.released()
        return {
            "released_s": finite_or_none(released.released_s),
            "merged_s": finite_or_none(self.merger.last_limit),
            "aid_held": released.held_batches,
            "aid_forced": released.forced,
            "held": len(self.merger),
            "state_gaps": sum(self.receiver.gaps.values()),
            "reordered": self.merger.reordered,
            "waiting_for": sorted(
                k for k in self.owners() if self.merger.released.get(k, -np.inf) <= self.merger.last_limit
            ),
        }

    def biases(self) -> list[dict[str, Any]]:
        """The joint bias estimate this worker serves: its own (it solves them) or the one the
        bias worker published."""
        mine = self.partition.solves_biases or self.published_biases is None
        return list(self.correlation.biases if mine else self.published_biases["biases"])  # type: ignore[index]

    @property
    def progress_pending(self) -> bool:
        """A progress message is held back (sent when idle)."""
        return (
            not self.alone
            and self._progress_sent is not None
            and self._progress_sent["released_s"] != finite_or_none(self.released().released_s)
        )

    # -- what goes to the others -----------------------------------------------------------------
    def outputs(self, idle: bool = False) -> list[Outgoing]:
        """The registration rows the owned pairs added, the biases (bias worker) and this
        worker's progress and clocks (``idle``: sent whatever moved)."""
        if self.alone:
            return []
        rows_framed = self.exchange.frames and self._all_read("frame_rows")
        links_framed = self.exchange.frames and self._all_read("frame_links")
        out = [
            Outgoing(
                self.keys.registration(*r.key),
                lambda r=r: rows_body(r.source_a, r.source_b, r.reference, r.rows),  # type: ignore[misc]
                (lambda r=r: rows_frame(r.source_a, r.source_b, r.reference, r.rows))  # type: ignore[misc]
                if rows_framed
                else None,
            )
            for r in self.correlation.take_rows()
        ]
        out += [
            Outgoing(
                self.keys.links(*s.key),
                lambda s=s: links_body(s),  # type: ignore[misc]
                (lambda s=s: links_frame(s)) if links_framed else None,  # type: ignore[misc]
            )
            for s in self.correlation.take_links()
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
        return out + self._clock(idle)  # after the rows and links: it says they are all out

    def _due(
        self, new: dict[str, Any], sent: dict[str, Any] | None, fields: tuple[str, ...], idle: bool
    ) -> bool:
        """A progress or clock message is sent once a value moved ``exchange.step_s`` of data
        time (or appeared), and whenever anything moved while idle: a message per input would
        cost the peers more than the tables they carry."""
        if sent is None or new == sent:
            return sent is None
        if idle:
            return True
        old = sent.get("clocks", sent)
        now = new.get("clocks", new)
        step = self.exchange.step_s
        return any(
            (now.get(f) is not None) != (old.get(f) is not None)
            or (now.get(f) is not None and now[f] - old[f] >= step)
            for f in fields
        ) or set(now) != set(old)

    def _lone_moved(self, lone: dict[str, list[float]]) -> bool:
        """Whether this worker's lone clocks changed since the last clock message: one came or
        went, one started again (a withdrawn run, then a new one: its first time moved, its
        newest may go back), or one's newest time moved ``exchange.step_s`` on (rare: a start,
        an outage)."""
        sent = (self._clock_sent or {}).get("lone_clocks", {})
        if set(lone) != set(sent):
            return True
        return any(
            lone[rid][0] != sent[rid][0] or not 0 <= lone[rid][1] - sent[rid][1] < self.exchange.step_s
            for rid in lone
        )

    def _clock(self, idle: bool) -> list[Outgoing]:
        """This worker's state for the others, when it changed: its progress (how far it has
        released and correlated) and its radars' data clocks (the network watermark,
        :meth:`Sequencer.observe`)."""
        # How far everything is released: the merge's limit, or just short of the oldest
        # table it holds back (:meth:`cap`: a worker waiting for this one must hear it).
        merged = self.merger.through(self.owners())
        released, held, _, _ = self.released()
        salted = {"salt": self.partition.salt} if self.partition.salt else {}
        progress: dict[str, Any] = {
            "partition": str(self.partition),
            **salted,
            "released_s": finite_or_none(released),
            **({"held": list(held)} if held is not None else {}),
            "correlated_s": finite_or_none(self.correlation.correlated_through(merged)),
            **({"packed_states": True} if self.exchange.packed else {}),
            **(
                dict.fromkeys(("frame_states", "frame_links", "frame_rows"), True)
                if self.exchange.frames
                else {}
            ),
        }
        owned = [
            (rid, s) for rid, s in sorted(self.sequencer.sources.items()) if s.kind == RADAR and not s.foreign
        ]
        lone = {
            rid: [s.lone_time(), s.last_time_s]
            for rid, s in owned
            if s.lone is not None and s.last_time_s is not None
        }
        clocks: dict[str, Any] = {
            "partition": str(self.partition),
            **salted,
            "clocks": {rid: s.confirmed_clock() for rid, s in owned if s.confirmed_clock() is not None},
            **({"lone_clocks": lone} if lone else {}),
        }
        out = []
        # Workers holding batches for their aid wait on each other a step at a time (each the
        # other's released_s and correlated_s through its lag): while this one or another holds,
        # every move goes out at once, not after a step of data time or when idle.
        sent = self._progress_sent
        holding = progress.get("held") is not None or (sent or {}).get("held") is not None
        holding = holding or any(c.held is not None for k, c in self._progress_of.items() if k in self.waited)
        if (holding and progress != sent) or self._due(progress, sent, ("released_s", "correlated_s"), idle):
            self._progress_sent = progress
            out.append(Outgoing(self.keys.worker_progress(self.partition.index), lambda: progress))
        if self._due(clocks, self._clock_sent, tuple(clocks["clocks"]), idle) or self._lone_moved(lone):
            self._clock_sent = clocks
            out.append(Outgoing(self.keys.worker_clock(self.partition.index), lambda: clocks))
        return out

    # -- what comes from the others --------------------------------------------------------------
    def ingest(self, kind: str, ids: tuple[str, ...], payload: bytes) -> PeerInput:
        """What another worker published for the others."""
        if kind == "track_states":
            radar_id = ids[0]
            if self.partition.owns(radar_id):
                return PeerInput()  # our own (a former session's of this worker: the transport
                # takes no sample of its own session on these keys)
            msg = decode_states(payload, radar_id)
            check_body_id("radar_id", msg.radar_id, radar_id)
            if radar_id not in self.tracking.tracked:
                return PeerInput(self._hold_states(radar_id, msg, len(payload)))
            self._apply_states(radar_id, msg)
            return PeerInput()  # released once its owner says how far it has published
        if kind in ("worker_clock", "worker_progress"):
            clock: WorkerClock = parse(WorkerClock, payload, None)
            worker = int(ids[0])
            mismatch = self._mismatch(worker, clock)
            if mismatch:
                self.mismatches += 1
                self.mismatch = mismatch
                raise RejectionError("schema", mismatch)
            if kind == "worker_clock":
                for rid, c in clock.clocks.items():
                    if not self.partition.owns(rid):
                        self.sequencer.observe(rid, c)
                for rid, s in self.sequencer.sources.items():  # its radars no longer lone
                    stale = s.foreign_lone is not None and rid not in clock.lone_clocks
                    if stale and self.partition.owner(rid) == worker:
                        self.sequencer.observe_lone(rid, None)
                for rid, span in clock.lone_clocks.items():
                    if not self.partition.owns(rid):
                        self.sequencer.observe_lone(rid, span)
            else:
                self._progress_of[worker] = clock
                self.merger.progress(worker, clock.released_s if clock.released_s is not None else -np.inf)
                self._correlated_by[worker] = (
                    clock.correlated_s if clock.correlated_s is not None else -np.inf
                )
                self._others_through()
            return PeerInput(moved=True)
        if kind == "registration":
            self._registration(ids, payload)
        elif kind == "links":
            self._links(ids, payload)
        elif kind == "biases" and not self.partition.solves_biases:
            self.published_biases = parse(BiasSet, payload, None).model_dump()
        return PeerInput()  # worker status: the transport's

    def _mismatch(self, worker: int, clock: WorkerClock) -> str:
        """Why the worker whose clock or progress this is cannot be one of this network (every
        K from 1 to N once, the same N and the same salt), or "" (it can)."""
        if clock.partition != f"{worker}/{self.partition.count}":
            theirs = clock.partition.rpartition("/")[2]
            if theirs != str(self.partition.count):
                return (
                    f"worker {clock.partition} counts {theirs} workers, this worker "
                    f"{self.partition}: every worker needs the same N of --partition K/N"
                )
            return f"worker {clock.partition} on the key of worker {worker}"
        if (clock.salt or 0) != self.partition.salt:
            return (
                f"worker {worker} hashes with salt {clock.salt or 0}, this worker with "
                f"{self.partition.salt}: every worker needs the same TOPOFUSION_PARTITION_SALT"
            )
        if worker == self.partition.index:
            # (this session's own are never delivered on these keys: another process runs
            # the same K, or this worker's previous session is still alive)
            return (
                f"another worker runs partition {self.partition} too: every K from 1 to N must "
                "run exactly once (two owners of the same radars publish two tracks of each)"
            )
        return ""

    def _ours(self, a: str, b: str) -> bool:
        """Whether a pair's links or rows, heard back, are this worker's own (a former session's:
        the transport takes none of its own session), so left unread.  Only when every reading
        of the pair says so: its name's owner, and, when one side is no radar this worker knows
        (a reference source, whose pair is its radar's owner's, :meth:`Partition.owns_pair`; or
        a radar whose site has not come yet), the other side's owner.  A worker that has not
        taken a reference's first batch or a radar's site yet must not drop another's rows."""
        unknown = {x for x in (a, b) if x not in self.tracking.tracked}  # (read as references)
        return self.partition.owns_pair(a, b) and self.partition.owns_pair(a, b, unknown)

    def _registration(self, ids: tuple[str, ...], payload: bytes) -> None:
        if not self.partition.solves_biases or self._ours(ids[0], ids[1]):
            return  # (our own pair's rows, e.g. a former session's of this worker: not even parsed)
        rows, data = decode_rows(payload, (ids[0], ids[1]))
        site_a = self._geometry(rows.source_a)
        site_b = None if rows.reference else self._geometry(rows.source_b)
        self.correlation.mirror_rows((ids[0], ids[1]), site_a, site_b, data)

    def _links(self, ids: tuple[str, ...], payload: bytes) -> None:
        wanted = self.partition.solves_biases or self.cycles.enabled
        if not (wanted or self.aid is not None) or self._ours(ids[0], ids[1]):
            return  # (our own pair's links, e.g. a former session's of this worker: not even parsed)
        shared = decode_links(payload, (ids[0], ids[1]))
        if wanted:
            self.correlation.mirror_links(shared)
        if self.aid is not None:
            self.aid.mirror(shared)

    def _hold_states(self, radar_id: str, msg: Any, size: int) -> tuple[tuple[str, RejectionError], ...]:
        """Hold a radar's track states until its site comes; beyond the bounds the oldest held
        messages are given up, each to be reported as its own rejection."""
        self._pending_states.append((radar_id, msg, size, self.keys.track_states(radar_id)))
        self._pending_bytes += size
        out = []
        while (
            len(self._pending_states) > MAX_PENDING_STATES or self._pending_bytes > MAX_PENDING_STATES_BYTES
        ):
            rid, _, n, key = self._pending_states.popleft()
            self._pending_bytes -= n
            out.append((key, unknown_radar(rid)))
        return tuple(out)

    def _apply_states(self, radar_id: str, msg: Any) -> None:
        table = self.receiver.apply(msg)
        if table is not None and self.aid is not None:
            self.aid.record(radar_id, msg.time_s, table)
        if table is not None:
            self.merger.push(RADAR, radar_id, msg.seq, msg.time_s, table, expiry=msg.expiry)
            self._heard.add(radar_id)
            if self.merger.expiring(radar_id) or self.partition.owner(radar_id) not in self.waited:
                self._silent_owner(radar_id)

    def _geometry(self, radar_id: str) -> Any:
        radar = self.tracking.tracked.get(radar_id)
        if radar is None:
            raise unknown_radar(radar_id)
        return radar.geometry
