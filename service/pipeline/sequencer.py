"""The data-time sequencer: every source's ``seq`` and clock, and the release of its batches.

Data time, not wall time
------------------------
Per source, batches are taken strictly in ``seq`` order.  Across sources an accepted batch is
held until every *live* source has reported at least up to its ``time_s`` (the watermark) and
then released in ``(time_s, kind, source_id, seq)`` order, so the stages after it see the same
sequence whatever the interleaving on arrival: a replay at any speed equals the live run.

Valid but hostile input (each policy a named field of :class:`SequencerParams`)
------------------------------------------------------------------------------
* **A clock far ahead.**  A batch stamped more than ``max_clock_skew_s`` ahead of the other
  sources' data clock is rejected (``out_of_range``).  The reference is the *low median* of the
  live sources' clocks together with the candidate's own time, so one source cannot move it:
  a lone future batch is measured against the others, and a future source that came first is
  outvoted by the next honest one.  The watermark only listens to sources within
  ``max_clock_skew_s`` of that consensus, so a clock that got in before any other source was
  there cannot hold the others back or release them early.
* **An outage that ended.**  When the whole feed stops and comes back (a link or a bridge down
  for longer than ``max_clock_skew_s``), every source's first batch is that far ahead.  A jump
  is taken as the end of an outage, not as hostile input, once at least ``outage_quorum`` of
  the live sources (and never fewer than two) have sent batches within ``max_clock_skew_s`` of
  it: a lone source's jump is still refused.  Each source's last refused-as-ahead time is
  remembered for this vote (one number a source); the first batch the vote admits is logged
  and counted (:attr:`Sequencer.outages`), and the silent sources then expire in data time as
  usual, so the tracks of before the gap leave the picture.  An outage so long that every
  source expired on the wall clock leaves no quorum to ask: the first batch back more than
  ``max_clock_skew_s`` after the newest clock is counted as its end.
* **A first clock no one can check.**  When no other source has a live clock (a fresh service,
  or every source expired), nothing can say whether a batch's time is right: one stamped an hour
  ahead would set the network's clock, and its source's honest batches after it would be steps
  back for an hour.  Such a batch is taken (counted) but its clock is *lone*: nothing at or
  beyond it is released, and it moves neither the consensus nor ``newest_s``, until data
  confirms it: another source's first clock within ``max_step_s`` of it, a confirmed clock
  elsewhere that it is not more than ``max_step_s`` ahead of, a time within
  ``max_clock_skew_s`` after its own source's clock of before (a restart, a short silence), or
  its source's own next batches: where it is the network's only source (no other source, no
  other site known), its next batch not more than ``max_step_s`` behind it; else only once they
  have gone on for ``max_lag_s`` of data time with no jump of more than ``max_lag_s`` (while
  others are known, a source agreeing with itself proves nothing: a radar whose clock is an
  hour off from its first batch on must not set the network's clock; a known radar that has not
  reported holds the release back as long anyway).  Until then its batches are a *lone run*,
  withdrawn or confirmed together: at most ``max_lone_batches`` (a clock that stands still
  makes no run time), and a jump of more than ``max_lag_s`` inside it is held for the next
  batch as a lone step ahead is (one corrupted stamp must not carry the run; a long scan or a
  few missed batches are no jump), withdrawn with the run if data refutes it.  Partitioned,
  workers tell each other their radars' lone clocks (:meth:`Sequencer.observe_lone`), which
  agree with this worker's as two lone radars of one worker do.  Data refutes
  it: its source's next batch more than ``max_step_s`` behind its first batch (that batch is
  then judged as if the lone ones never came: its seq and clock of before), or a confirmed
  clock more than ``max_clock_skew_s`` behind its newest.  One between the two (its first more
  than ``max_step_s`` ahead of the confirmed clock, within the skew) waits for its source's
  next batch, as a held step does.  A refuted lone batch is withdrawn whole:
  rejected ``out_of_range``, its counts, seq and clock put back (a scrape of the counters in
  between sees them fall back), its pending events restored, nothing of it released.  An honest
  stream only ever confirms, and the first batch waits for the next one, so the outputs do not
  depend on which of the first two batches arrives first (a radar whose first batch comes after
  two others agreed on a later time is released late, as a lagging radar's batch is).  The end
  of the input withdraws the lone batches the confirmed clocks refute and releases the others
  as they are.  Partitioned, another worker's confirmed clock settles a lone clock at this
  worker's next batch.
* **A lone step ahead.**  A batch stamped more than ``max_step_s`` ahead of both the other
  sources' data clock and its own source's clock (but within ``max_clock_skew_s``) is *held*,
  not taken, until the source's next batch says what it was: a next batch nearer the source's
  clock of before than the held time shows the held one a glitch (one corrupted time stamp):
  it is then rejected (``out_of_range``) and nothing of it was applied; a next batch at or
  past the held time confirms it, and both are taken in order.  Taken at once, such a batch
  would move the source's clock ahead, and its honest batches after it, behind that clock,
  would find their tracks ahead of them: the radar would go dark until the true time caught
  up.  An honest stream only ever confirms (a source back from its own silence ahead of the
  others, the first sources back from a whole-feed outage), so what is taken, and in which
  order, does not change; the held source's batches are one batch later.  A source holds at
  most one such batch; one still held when the input ends (:meth:`Sequencer.drop_held`) is
  rejected, never confirmed.
* **A step back.**  A batch stamped more than ``max_step_s`` behind its own source's clock
  (its ``seq`` going on) is rejected (``out_of_range``): taken, its plots would be older than
  the source's tracks, and the tracker would make nothing of them, silently.
* **An absurd ``seq`` jump.**  A jump of more than ``max_seq_jump`` batches that is also more
  than ``max_batch_rate_hz`` times the data time since the source's last batch is rejected
  (``out_of_range``): a radar back after a day's outage may legitimately skip many numbers, a
  batch four seconds later cannot skip 10^30.
* **A publisher restart.**  A ``seq`` at or below the last accepted one is a duplicate, unless
  it is at most ``restart_max_seq`` (the counter started again) *and* its ``time_s`` is later
  than the source's clock: then it is a restart, counted, and the sequence goes on from there.
* **Sources that go silent** expire ``source_expiry_s`` of data time after their last batch
  (an event in the same data-time order as the batches, so replays expire them identically);
  the engine then drops what they cost (their tracks coast out, they leave correlation).
  A source still silent ``forget_after_s`` after its expiry is **forgotten** (another such
  event): its pair books, registration rows and tables go, in both processes, so memory stays
  flat while radar ids come and go; its site, ``seq`` and clock stay (a few numbers, bounded by
  ``max_sources``), and its track ids go on where they were when it comes back.
* **Too many ids.**  At most ``max_sources`` sources are held.  When full, an expired source
  (or one that announced itself and never reported) makes room; otherwise the newcomer is
  rejected (``out_of_range``).

A radar whose data clock lags the newest live clock by more than ``max_lag_s`` stops holding the
others back (an outage must not freeze the picture); its late batches are still released when
they come.  A clock running more than ``max_lag_s`` ahead of every other alone does not set
that pace while at least two others are still reporting (:meth:`Sequencer._pace`).
"""

from __future__ import annotations

import heapq
import logging
import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np
from annotated_types import Ge

from service.pipeline.errors import RejectionError

log = logging.getLogger(__name__)

#: Kinds of source, in their release order at equal data time.
REFERENCE, RADAR = 0, 1
#: Heap entries of this kind are expiry events, after every batch of the same data time.
EXPIRE = 2
#: Heap entries of this kind are forget events (``forget_after_s`` after an expiry).
FORGET = 3


@dataclass(frozen=True)
class SequencerParams:
    """Data-time ordering and the policies on sources' ``seq`` and clocks."""

    #: A source lagging the consensus data clock by more than this no longer holds back the
    #: release of the others (s of data time).
    max_lag_s: Annotated[float, Ge(0)] = 30.0
    #: A batch stamped more than this ahead of the other sources' data clock is rejected (s).
    #: Radars and bridges stamp their own data; ten minutes is far beyond any clock error of a
    #: working sensor, and far below the hours a wrong date or time zone would give.
    max_clock_skew_s: float = 600.0
    #: A batch stamped more than this (s) ahead of both the other sources' data clock and its own
    #: source's clock is held until the source's next batch confirms it (module docstring).
    #: Ten seconds is a few scans: well past the arrival skew of sources on one network, so an
    #: honest batch is held only after its source's own silence, and then just one batch long.
    #: A batch stamped more than this behind its own source's clock is rejected (a stale batch:
    #: a source's data time does not go back, and its tracks are ahead of it).
    max_step_s: float = 10.0
    #: A ``seq`` jump above this many batches may be rejected (see ``max_batch_rate_hz``).
    max_seq_jump: int = 10_000
    #: ...but only if it is also above this many batches per data second since the source's
    #: last batch: no sensor sends 100 batches a second, so a long outage passes, 10^30 does not.
    max_batch_rate_hz: float = 100.0
    #: A ``seq`` this low, below the last accepted one but at a later ``time_s``, is a publisher
    #: that restarted its counter (counted as a restart), not a duplicate.
    restart_max_seq: int = 1_000
    #: A source with no batch for this long (s of data time) expires: its tracks coast out and
    #: it leaves correlation until it reports again.
    source_expiry_s: float = 300.0
    #: A source still silent this long (s of data time) after its expiry is forgotten: its
    #: pair books, registration rows and tables go (module docstring).  Five minutes: ten of
    #: silence in all, so a radar back from a short maintenance keeps what its pairs learnt,
    #: while under id churn the ids held (and their pairs, which grow with the square of them)
    #: stay few: the churn soak's correlation process grows 2.4 MB/min with five minutes, 4.4
    #: with ten (bench/bench_churn_soak.py).
    forget_after_s: float = 300.0
    #: Share of the live sources whose batches must agree on a jump of more than
    #: ``max_clock_skew_s`` for it to be the end of a whole-feed outage (see module docstring);
    #: at least two sources always.  A half: the network's data clock is the low median of the
    #: sources' clocks, so this is the share that moves it.
    outage_quorum: float = 0.5
    #: Most sources held at once (radars and references).  Every held source costs a little
    #: memory and a term of the watermark; beyond this, expired sources make room.
    max_sources: Annotated[int, Ge(1)] = 1_024
    #: Most batches of one source held lone, waiting for data to confirm or refute its clock
    #: (module docstring); one more is rejected unless it confirms them.  A run confirms itself
    #: after ``max_lag_s`` of data: a thousand batches is 33 a second over that run, past any
    #: sensor's rate, so only a clock that stands still reaches it.
    max_lone_batches: Annotated[int, Ge(1)] = 1_000


@dataclass
class SourceClock:
    """One source's sequence, clock, pending batches and counters."""

    kind: int
    last_seq: int | None = None
    batches: int = 0
    #: Plots (a radar) or reports (a reference source) of its batches taken.
    plots: int = 0
    lost_batches: int = 0
    restarts: int = 0
    rejected: int = 0
    #: Data clock of accepted batches (never goes back).
    last_time_s: float | None = None
    #: Data clock of the last released batch.
    released_time_s: float | None = None
    expired: bool = False
    #: Consensus data clock when the source was announced (its site arrived).
    announced_s: float = -np.inf
    #: Another worker's radar (partitioned): only its clock is known here (:meth:`observe`).
    foreign: bool = False
    #: Another worker's radar whose clock is lone there: its first and newest data time
    #: (:meth:`observe_lone`), which this worker's lone clocks may agree with.
    foreign_lone: tuple[float, float] | None = None
    #: The data time of this source's last batch refused as too far ahead (the outage vote).
    ahead_s: float | None = None
    #: The clock came from the state file (a restart), not from a batch of this run.
    restored: bool = False
    #: The newest clock any source had (:attr:`Sequencer.top_s`) when this one last moved:
    #: a source still reporting while another runs ahead of every clock alone (``_pace``).
    heard_at_s: float = -np.inf
    #: A batch held as a lone step ahead, until the next batch confirms or refutes it.
    held: Held | None = None
    #: The batch that set a clock no other source could check, until data confirms it.
    lone: Lone | None = None
    pending: deque[tuple[float, int, Any]] = field(default_factory=deque)

    def lone_time(self) -> float:
        """The data time of its lone batch (inf: none)."""
        return self.lone.admission.time_s if self.lone is not None else np.inf

    def confirmed_clock(self) -> float | None:
        """Its data clock but a lone batch's: what it has shown to be right."""
        return self.lone.before_s if self.lone is not None else self.last_time_s

    def confirmed_seq(self) -> int | None:
        """Its last ``seq`` but a lone batch's."""
        return self.lone.before_seq if self.lone is not None else self.last_seq


@dataclass(frozen=True)
class Admission:
    """A batch that passed every check; :meth:`Sequencer.accept` applies it."""

    source_id: str
    kind: int
    seq: int
    time_s: float
    restart: bool
    lost: int
    #: > 0: the batch ends a whole-feed outage this long (s of data time); see the docstring.
    outage: float = 0.0
    #: From this source's clock of before (or the others'): a lone step ahead, to be held.
    step_from_s: float | None = None
    #: The source's held batch: +1 confirmed by this one (taken first), -1 refuted (rejected).
    resolves: int = 0
    #: This batch refutes its source's lone clock (module docstring): that batch is withdrawn.
    withdraws: bool = False


#: Why a held batch is rejected: its source's next batch refuted it, or none came to confirm it.
REFUTED = "the next batch came back to that clock"
UNCONFIRMED = "no next batch came to confirm it"


@dataclass(frozen=True)
class Held:
    """A batch stamped a lone step ahead (module docstring): not taken yet."""

    admission: Admission
    item: Any
    #: The source's clock it stepped from (or the others', for a source with none yet).
    before_s: float
    #: Its plots or reports.
    count: int
    #: When the service received it (None: not given), the time its rejection reports.
    received_s: float | None = None

    def refuted_by(self, time_s: float) -> bool:
        """A next batch at ``time_s`` nearer the clock of before than the held time."""
        return time_s < (self.before_s + self.admission.time_s) / 2

    def rejection(self, source_id: str, why: str) -> RejectionError:
        """Its rejection, saying ``why`` (:data:`REFUTED`, :data:`UNCONFIRMED`, or the lone run
        it stepped from withdrawn)."""
        a = self.admission
        return RejectionError(
            "out_of_range",
            f"batch seq {a.seq} at time_s {a.time_s:.3f} was held, {a.time_s - self.before_s:.1f} s ahead "
            f"of this source's data clock {self.before_s:.3f} (max_step_s), and {why}",
            source_id,
        )


@dataclass
class Lone:
    """The batches of a source taken while no other source had a confirmed clock (module
    docstring), oldest first, with what they changed of the source, to be put back if data
    refutes them."""

    #: Each batch's admission, plots or reports, and receipt.
    entries: list[tuple[Admission, int, float | None]]
    #: Where the source's continuous run began (a step of more than ``max_step_s`` starts it
    #: again): its own batches confirm it after ``max_lag_s`` of that run.
    run_from_s: float
    #: The source's clock, seq, flags and pending events before them.
    before_s: float | None
    before_seq: int | None
    expired: bool
    restored: bool
    expiry_due: float | None
    forget_due: float | None

    @property
    def admission(self) -> Admission:
        """The first lone batch's."""
        return self.entries[0][0]

    def rejections(self, source_id: str, why: str) -> list[Refused]:
        return [
            (
                source_id,
                RejectionError(
                    "out_of_range",
                    f"batch seq {a.seq} at time_s {a.time_s:.3f} came when no other source had a live "
                    f"data clock, and {why}: withdrawn, nothing of it was released",
                    source_id,
                ),
                received,
            )
            for a, _, received in self.entries
        ]


#: A batch refused after it was held or taken: its source, why, and when it was received.
Refused = tuple[str, RejectionError, "float | None"]


@dataclass(frozen=True)
class Release:
    """A released batch (``item`` as accepted), or a source's expiry (``item`` is None)."""

    kind: int
    source_id: str
    time_s: float
    item: Any
    #: An expired source that stayed silent ``forget_after_s``: what it costs goes.
    forget: bool = False

    @property
    def expiry(self) -> bool:
        return self.item is None


def _low_median(values: list[float]) -> float:
    values.sort()
    return values[(len(values) - 1) // 2]


class Sequencer:
    """Per-source ``seq`` and data clocks; releases accepted batches in data-time order."""

    def __init__(self, params: SequencerParams | None = None) -> None:
        self.params = params or SequencerParams()
        self.sources: dict[str, SourceClock] = {}
        # heads of the sources' pending queues and expiry events: (clock, kind, id, seq)
        self._heap: list[tuple[float, int, str, int]] = []
        self._expiry_due: dict[str, float] = {}
        self._forget_due: dict[str, float] = {}
        #: The sources whose clock is lone (module docstring); none while a clock is confirmed.
        self._lone: set[str] = set()
        #: Radars whose sites the engine knows, this worker's and (partitioned) the others':
        #: a lone source is the network's only one when it is the only source and site known.
        self.sites_known = 0
        self._first_clock = np.inf
        #: The data time up to which the last :meth:`release` released.
        self.last_limit = -np.inf
        #: The newest data clock of an accepted batch (-inf: none yet); never goes back.
        self.newest_s = -np.inf
        #: The newest confirmed clock of any source, this worker's or (partitioned) another's
        #: (-inf: none yet); never goes back (``_pace``).
        self.top_s = -np.inf
        #: Whole-feed outages that ended (jumps a quorum of the sources agreed on).
        self.outages = 0
        #: The data-time length of the last such outage (s).
        self.last_outage_s = 0.0

    # -- sources ---------------------------------------------------------------------------
    def announce(self, source_id: str, kind: int) -> list[str]:
        """Hold a source (a radar whose site arrived); returns the ids evicted to make room."""
        if source_id in self.sources:
            return []
        evicted = self._make_room(source_id)
        self.sources[source_id] = SourceClock(kind, announced_s=self.consensus())
        return evicted

    def _make_room(self, source_id: str) -> list[str]:
        if len(self.sources) < self.params.max_sources:
            return []
        now = self.consensus()
        idle = [
            (s.last_time_s if s.last_time_s is not None else s.announced_s, sid)
            for sid, s in self.sources.items()
            if not s.pending
            and (s.expired or (s.last_time_s is None and s.announced_s < now - self.params.source_expiry_s))
        ]
        if not idle:
            raise RejectionError(
                "out_of_range",
                f"source table full ({self.params.max_sources} sources, none expired): "
                f"not admitting {source_id!r}",
                source_id,
            )
        _, victim = min(idle)
        del self.sources[victim]
        self._cancel_events(victim)
        return [victim]

    def observe(self, source_id: str, clock_s: float) -> None:
        """Another worker's radar has accepted batches up to ``clock_s`` (partitioned workers):
        it takes part in the consensus, the watermark and its lag rule like a radar of this
        worker, so every worker releases at the pace one worker would; it never has batches
        here.  A radar this worker holds itself is left alone."""
        src = self.sources.get(source_id)
        if src is None:
            if len(self.sources) >= self.params.max_sources:
                return  # bounded like every source; this one then simply holds nothing back
            src = self.sources[source_id] = SourceClock(RADAR, announced_s=self.consensus(), foreign=True)
        if src.foreign:
            before = src.last_time_s
            src.last_time_s = max(clock_s, before if before is not None else -np.inf)
            src.foreign_lone = None
            if before is None or src.last_time_s > before:  # (its owner says every clock again)
                self._heard(src)

    def observe_lone(self, source_id: str, span: tuple[float, float] | None) -> None:
        """Another worker's radar has a lone clock (``span``: its first and newest data time),
        or no longer has one (None): a lone clock of this worker's within ``max_step_s`` of it
        agrees with it, as two lone radars of one worker do.  It holds nothing back here."""
        src = self.sources.get(source_id)
        if src is None and span is not None and len(self.sources) < self.params.max_sources:
            src = self.sources[source_id] = SourceClock(RADAR, announced_s=self.consensus(), foreign=True)
        if src is not None and src.foreign:
            src.foreign_lone = span

    def _cancel_events(self, source_id: str) -> None:
        """The source's pending expiry and forget events no longer apply (their heap entries
        are skipped when popped)."""
        self._expiry_due.pop(source_id, None)
        self._forget_due.pop(source_id, None)

    def expire_now(self, source_id: str) -> bool:
        """Expire a source that is silent on the wall clock while the data clock stands still
        (:mod:`.feed`): its expiry is released at the data time released so far, in order with
        everything else.  False if it holds pending batches or is not a live source here."""
        src = self.sources.get(source_id)
        if src is None or src.expired or src.pending or src.foreign or src.last_time_s is None:
            return False
        due = max(self.last_limit, src.last_time_s)
        self._expiry_due[source_id] = due
        heapq.heappush(self._heap, (due, EXPIRE, source_id, 0))
        return True

    def forget(self, source_id: str) -> None:
        """Drop a source that holds no pending batch (its state left the engine)."""
        src = self.sources.get(source_id)
        if src is not None and not src.pending:
            del self.sources[source_id]
            self._cancel_events(source_id)

    # -- admission -------------------------------------------------------------------------
    def check(self, source_id: str, kind: int, seq: int, time_s: float) -> Admission:
        """Every check of a batch, changing nothing; raises :class:`RejectionError`."""
        p = self.params
        src = self.sources.get(source_id)
        restart, lost = False, 0
        if src is not None and src.kind != kind:
            what = "a radar" if src.kind == RADAR else "a reference source"
            raise RejectionError("schema", f"source id {source_id!r} is taken by {what}", source_id)
        # a batch more than max_step_s behind its source's lone clock refutes it: it is judged
        # as if the lone batch never came (its seq and clock of before)
        last_seq, own = (src.last_seq, src.last_time_s) if src is not None else (None, None)
        lone = src.lone if src is not None else None
        withdraws = lone is not None and time_s < lone.admission.time_s - p.max_step_s
        if lone is not None and withdraws:
            last_seq, own = lone.before_seq, lone.before_s
        if src is not None and last_seq is not None:
            last_time = own if own is not None else -np.inf
            if seq <= last_seq:
                if not (seq <= p.restart_max_seq and time_s > last_time):
                    detail = self._duplicate(last_seq, own, src.restored, seq, time_s)
                    raise RejectionError("duplicate_seq", detail, source_id)
                restart = True
            else:
                lost = seq - last_seq - 1
                allowed = max(p.max_seq_jump, p.max_batch_rate_hz * max(0.0, time_s - last_time))
                if lost > allowed:
                    raise RejectionError(
                        "out_of_range",
                        f"seq {seq} skips {lost} batches after {last_seq} in "
                        f"{max(0.0, time_s - last_time):.3f} s of data time (max_seq_jump {p.max_seq_jump}, "
                        f"max_batch_rate_hz {p.max_batch_rate_hz:g})",
                        source_id,
                    )
        others = self._other_clocks(source_id)
        outage, step_from, resolves = 0.0, None, 0
        # (measured against the clock taken, not a held batch's: the held rule says what a batch
        # before that one means)
        if own is not None and time_s < own - p.max_step_s:
            raise RejectionError(
                "out_of_range",
                f"time_s {time_s:.3f} is {own - time_s:.1f} s behind this source's data clock "
                f"{own:.3f} (max_step_s {p.max_step_s:g}): a source's data time does not go back",
                source_id,
            )
        if src is not None and src.held is not None and not withdraws:  # it says what the held one was
            # (one held inside a lone run this batch refutes goes with the run)
            resolves = -1 if src.held.refuted_by(time_s) else 1
            if resolves > 0:
                own = src.held.admission.time_s if own is None else max(own, src.held.admission.time_s)
        running = lone is not None and not withdraws  # (this batch goes on with a lone run)
        full = lone is not None and len(lone.entries) >= p.max_lone_batches
        if running and full and src is not None and not self._confirmed(source_id, src, time_s):
            raise RejectionError(
                "out_of_range",
                f"{p.max_lone_batches} batches of this source wait for another source to confirm "
                f"its data clock (max_lone_batches), and time_s {time_s:.3f} does not go on for "
                f"max_lag_s {p.max_lag_s:g} s",
                source_id,
            )
        if others:
            reference = _low_median([*others, time_s])
            if time_s > reference + p.max_clock_skew_s:
                if not self._outage_vote(source_id, time_s):
                    if src is not None and not src.expired:
                        src.ahead_s = time_s  # the vote's memory; no state of the stream changes
                    raise RejectionError(
                        "out_of_range",
                        f"time_s {time_s:.3f} is {time_s - reference:.1f} s ahead of the other sources' "
                        f"data clock {reference:.3f} (max_clock_skew_s {p.max_clock_skew_s:g})",
                        source_id,
                    )
                outage = time_s - reference
            elif time_s > reference + p.max_step_s and (own is None or time_s > own + p.max_step_s):
                step_from = reference if own is None else own
        elif running and own is not None and time_s > own + p.max_lag_s and not self._alone(source_id):
            # a jump inside a lone run, where no other clock can judge it: held until the
            # source's next batch says what it was (one corrupted stamp must not carry the run)
            step_from = own
        elif np.isfinite(self.newest_s) and time_s > self.newest_s + p.max_clock_skew_s:
            # every source expired meanwhile (a silence past the wall-clock expiry): no quorum
            # to ask, yet the feed came back from an outage as long as this
            outage = time_s - self.newest_s
        if src is None and len(self.sources) >= p.max_sources:
            self._make_room_check(source_id)
        return Admission(source_id, kind, seq, time_s, restart, lost, outage, step_from, resolves, withdraws)

    @staticmethod
    def _duplicate(last_seq: int, clock: float | None, restored: bool, seq: int, time_s: float) -> str:
        """A duplicate's detail; a restarted publisher behind the source's clock is told why."""
        detail = f"seq {seq} <= last accepted {last_seq}"
        if clock is None or clock - time_s <= 0:
            return detail
        held = "restored from the state file, " if restored else ""
        return (
            f"{detail}, and time_s {time_s:.3f} is {clock - time_s:.1f} s behind this source's data clock "
            f"({held}{clock:.3f}): a publisher that restarted its seq must go on after "
            "that clock (e.g. topofusion simulate --start-time resume)"
        )

    def _outage_vote(self, source_id: str, time_s: float) -> bool:
        """Whether a quorum of the live sources has moved to (or tried to move to) within
        ``max_clock_skew_s`` of ``time_s``: the whole feed came back from an outage."""
        p = self.params
        live = agree = 0
        for sid, s in self.sources.items():
            if s.expired or s.last_time_s is None or s.lone is not None or sid == source_id:
                continue
            live += 1
            near = [t for t in (s.last_time_s, s.ahead_s) if t is not None]
            agree += any(abs(t - time_s) <= p.max_clock_skew_s for t in near)
        # the candidate is live and agrees with itself
        return agree + 1 >= max(2, math.ceil(p.outage_quorum * (live + 1)))

    def _other_clocks(self, source_id: str | None) -> list[float]:
        """The live, confirmed data clocks of the sources other than ``source_id`` (a lone
        clock is not one: module docstring)."""
        return [
            s.last_time_s
            for sid, s in self.sources.items()
            if sid != source_id and s.last_time_s is not None and not s.expired and s.lone is None
        ]

    def _make_room_check(self, source_id: str) -> None:
        """Raise as :meth:`_make_room` would, without evicting anything."""
        now = self.consensus()
        if not any(
            not s.pending
            and (s.expired or (s.last_time_s is None and s.announced_s < now - self.params.source_expiry_s))
            for s in self.sources.values()
        ):
            raise RejectionError(
                "out_of_range",
                f"source table full ({self.params.max_sources} sources, none expired): "
                f"not admitting {source_id!r}",
                source_id,
            )

    def accept(
        self, adm: Admission, item: Any, count: int = 0, received_s: float | None = None
    ) -> tuple[list[str], list[Refused]]:
        """Apply an admitted batch of ``count`` plots or reports (received at ``received_s``);
        returns the ids evicted to make room for a new source, and the batches this one refuted
        (its source's held batch, lone batches withdrawn), each to be reported rejected: nothing
        of them was released."""
        evicted: list[str] = []
        refused: list[Refused] = []
        src = self.sources.get(adm.source_id)
        if src is None:
            evicted = self._make_room(adm.source_id)
            src = self.sources[adm.source_id] = SourceClock(adm.kind, announced_s=self.consensus())
        if adm.withdraws:
            why = f"this source's next batch came back to {adm.time_s:.3f}"
            refused += self._withdraw(adm.source_id, why)
        held, src.held = src.held, None
        if held is not None and adm.resolves > 0:
            refused += self._take(src, held.admission, held.item, held.count, held.received_s)
        if held is not None and adm.resolves < 0:
            refused.append((adm.source_id, held.rejection(adm.source_id, REFUTED), held.received_s))
        if adm.step_from_s is not None:  # held, not taken: only its seq counts yet
            src.held = Held(adm, item, adm.step_from_s, count, received_s)
            self._count_seq(src, adm)
            return evicted, refused
        refused += self._take(src, adm, item, count, received_s)
        return evicted, refused

    def drop_held(self) -> list[Refused]:
        """The end of the input: every held batch is given up, and every lone clock the
        confirmed ones refute withdrawn (each to be reported rejected)."""
        out: list[Refused] = []
        for sid, src in self.sources.items():
            if src.held is not None:
                out.append((sid, src.held.rejection(sid, UNCONFIRMED), src.held.received_s))
                src.held = None
        return out + self._settle_lone()

    @staticmethod
    def _count_seq(src: SourceClock, adm: Admission) -> None:
        src.last_seq = adm.seq
        src.lost_batches += adm.lost
        src.restarts += adm.restart

    def _take(
        self, src: SourceClock, adm: Admission, item: Any, count: int, received_s: float | None = None
    ) -> list[Refused]:
        sid = adm.source_id
        p = self.params
        confirmed = self._confirmed(sid, src, adm.time_s)
        if not confirmed and src.lone is not None:  # its lone run goes on
            if src.last_time_s is not None and adm.time_s > src.last_time_s + p.max_lag_s:
                src.lone.run_from_s = adm.time_s
            src.lone.entries.append((adm, count, received_s))
        elif not confirmed:
            self._lone.add(sid)
            src.lone = Lone(
                [(adm, count, received_s)],
                adm.time_s,
                src.last_time_s,
                src.last_seq,
                src.expired,
                src.restored,
                self._expiry_due.get(sid),
                self._forget_due.get(sid),
            )
        elif src.lone is not None:
            self._confirm(sid, src)
        if adm.step_from_s is None:  # (a held batch's seq was counted when it was held)
            self._count_seq(src, adm)
        src.batches += 1
        src.plots += count
        src.ahead_s = None
        src.restored = False
        moved_from = None if src.expired else src.last_time_s  # (back from expiry: it moved)
        clock = max(adm.time_s, src.last_time_s if src.last_time_s is not None else -np.inf)
        src.last_time_s = clock
        src.expired = False
        self._cancel_events(sid)
        if not src.pending:
            heapq.heappush(self._heap, (clock, adm.kind, sid, adm.seq))
        src.pending.append((clock, adm.seq, item))
        if not confirmed:
            return []
        self._count_outage(adm)
        self.newest_s = max(self.newest_s, clock)
        if moved_from is None or clock > moved_from:  # (a stamp that stands still is not heard)
            self._heard(src)
        return self._settle_lone()

    def _heard(self, src: SourceClock) -> None:
        """A source's confirmed clock moved on (a batch at the same stamp, or the same clock said
        again, is no sign of life): the newest clock of all, and when it was heard.  A jump of
        the newest clock by more than ``max_lag_s`` (a source joining ahead, the end of an
        outage) is no progress the others missed: every source counts as heard at it, so they
        get ``max_lag_s`` of its data to report before it leads alone."""
        clock = src.last_time_s
        if clock is not None and clock > self.top_s + self.params.max_lag_s:
            for other in self.sources.values():
                other.heard_at_s = clock
        if clock is not None:
            self.top_s = max(self.top_s, clock)
        src.heard_at_s = self.top_s

    def _confirmed(self, source_id: str, src: SourceClock, time_s: float) -> bool:
        """Whether a batch of the source at ``time_s``, taken, has a confirmed clock (or confirms
        its source's lone run): its own clock of before not far behind, a confirmed clock
        elsewhere (the checks measured it against it), another lone run it falls within
        ``max_step_s`` of (the two agree), or its own lone run going on (not refuted) where it
        is the network's only source, or for ``max_lag_s`` of data time.  While other sources
        are known, a source agreeing with itself for a batch or two proves nothing (a known
        radar that has not reported holds the release back as long, see ``watermark``)."""
        p = self.params
        before = src.confirmed_clock()
        return (
            (src.lone is not None and self._confirms_run(source_id, src, time_s))
            or (before is not None and time_s <= before + p.max_clock_skew_s)
            or any(self._agrees(s, time_s) for o, s in self.sources.items() if o != source_id)
        )

    def _agrees(self, other: SourceClock, time_s: float) -> bool:
        """Whether another source's clock confirms a batch at ``time_s``: a confirmed live clock
        (the checks measured the batch against it), or a lone run (this worker's or, partitioned,
        another's) it falls within ``max_step_s`` of: the two agree."""
        step = self.params.max_step_s
        span = other.foreign_lone
        if span is not None and span[0] - step <= time_s <= span[1] + step:
            return True
        if other.last_time_s is None or other.expired:
            return False
        return other.lone is None or other.lone_time() - step <= time_s <= other.last_time_s + step

    def _confirms_run(self, source_id: str, src: SourceClock, time_s: float) -> bool:
        """Whether the source's next batch at ``time_s`` confirms its lone run by itself: where
        it is the network's only source (no other source, no other site known: a single radar's
        network, whose next batch confirms its first as before), or where the run has gone on
        for ``max_lag_s`` of data time without a jump of more than ``max_lag_s`` (gaps of a
        scan or a few missed batches are no jump; a wrong stamp an hour off is)."""
        lone = src.lone
        assert lone is not None
        if self._alone(source_id):
            return True
        last = src.last_time_s if src.last_time_s is not None else -np.inf
        run_from = time_s if time_s > last + self.params.max_lag_s else lone.run_from_s
        return time_s - run_from >= self.params.max_lag_s

    def _alone(self, source_id: str) -> bool:
        """Whether the source is the network's only one: no other source, no other site known."""
        return self.sites_known <= 1 and all(o == source_id for o in self.sources)

    def _count_outage(self, adm: Admission) -> None:
        """Count the outage a taken, confirmed batch ended.  One judged with no other clock live
        (against ``newest_s``) is judged again: a lone batch back from the same outage may
        have been confirmed, and counted, since."""
        if adm.outage <= 0:
            return
        if adm.time_s <= self.newest_s + self.params.max_clock_skew_s and not self._other_clocks(
            adm.source_id
        ):
            return
        self.outages += 1
        self.last_outage_s = adm.outage
        log.warning(
            "whole-feed outage of %.0f s of data time ended: %s is back at %.3f (%s); the "
            "silent ones expire in data time",
            adm.outage,
            adm.source_id,
            adm.time_s,
            "with a quorum of the sources" if self._other_clocks(adm.source_id) else "none other live",
        )

    def _confirm(self, source_id: str, src: SourceClock) -> None:
        """A lone clock is confirmed: it counts in the network's clocks from now on (and its
        outage, if it ended one no batch counted yet)."""
        lone, src.lone = src.lone, None
        self._lone.discard(source_id)
        assert lone is not None
        a = lone.admission
        if a.outage > 0 and a.time_s > self.newest_s + self.params.max_clock_skew_s:
            self._count_outage(a)
        # the first data time seen is its, for the radars yet to report
        self._first_clock = min(self._first_clock, a.time_s)
        if src.last_time_s is not None:
            self.newest_s = max(self.newest_s, src.last_time_s)
        self._heard(src)

    def settle(self) -> list[Refused]:
        """Settle the lone runs after other workers' clocks came (partitioned), as one of this
        worker's batches would: a run agreeing with another worker's lone run (within
        ``max_step_s``) is confirmed, and the confirmed clocks settle the rest.  Returns the
        batches withdrawn, to be reported rejected."""
        if not self._lone:
            return []
        step = self.params.max_step_s
        spans = [s.foreign_lone for s in self.sources.values() if s.foreign_lone is not None]
        for sid in sorted(self._lone):
            src = self.sources[sid]
            first, newest = src.lone_time(), src.last_time_s if src.last_time_s is not None else -np.inf
            if any(a - step <= newest and first <= b + step for a, b in spans):
                self._confirm(sid, src)
        return self._settle_lone()

    def _settle_lone(self) -> list[Refused]:
        """With a confirmed clock in the network, the lone runs are settled against the
        confirmed consensus: its newest batch more than ``max_clock_skew_s`` ahead, withdrawn
        whole; its first more than ``max_step_s`` ahead, left to its source's next batch (as a
        held step is); else confirmed."""
        if not self._lone:
            return []
        consensus = self.consensus()
        if not np.isfinite(consensus):
            return []
        out = []
        for sid in sorted(self._lone):
            src = self.sources[sid]
            newest = src.last_time_s if src.last_time_s is not None else -np.inf
            if newest - consensus > self.params.max_clock_skew_s:
                why = (
                    f"the confirmed data clock {consensus:.3f} is {newest - consensus:.1f} s behind "
                    f"its batch at {newest:.3f} (max_clock_skew_s {self.params.max_clock_skew_s:g})"
                )
                out += self._withdraw(sid, why)
            elif src.lone_time() - consensus <= self.params.max_step_s:
                self._confirm(sid, src)
        return out

    def _withdraw(self, source_id: str, why: str) -> list[Refused]:
        """Undo a source's lone batches (refuted by data): nothing of them was released, and its
        counts, seq and clock are the source's of before them (each rejected whole)."""
        src = self.sources[source_id]
        lone, src.lone = src.lone, None
        self._lone.discard(source_id)
        assert lone is not None
        for a, count, _ in lone.entries:  # (the newest pending batches are the lone ones)
            src.pending.pop()
            src.batches -= 1
            src.plots -= count
            src.lost_batches -= a.lost
            src.restarts -= a.restart
        refused = lone.rejections(source_id, why)
        held, src.held = src.held, None
        if held is not None:  # a jump inside the run, held after it began: its seq counted
            src.lost_batches -= held.admission.lost
            src.restarts -= held.admission.restart
            refused.append(
                (
                    source_id,
                    held.rejection(source_id, f"the lone run it stepped from was withdrawn ({why})"),
                    held.received_s,
                )
            )
        if not src.pending:  # its heap entry goes with them
            self._heap = [e for e in self._heap if not (e[2] == source_id and e[1] == src.kind)]
            heapq.heapify(self._heap)
        src.last_time_s, src.last_seq = lone.before_s, lone.before_seq
        src.expired, src.restored = lone.expired, lone.restored
        events = ((lone.expiry_due, EXPIRE, self._expiry_due), (lone.forget_due, FORGET, self._forget_due))
        for due, kind, book in events:
            if due is not None:
                book[source_id] = due
                heapq.heappush(self._heap, (due, kind, source_id, 0))
        return refused

    # -- kept across a restart (service.state) -------------------------------------------------
    def export_state(self) -> list[dict[str, Any]]:
        """Each source's kind, latest ``seq`` and data clock: after a restart its numbering goes
        on (a repeated ``seq`` is a duplicate, a gap counts lost batches) and so does its clock.
        Sources that never sent a batch, and other workers' radars, are left out."""
        return [
            {"source_id": sid, "kind": s.kind, "seq": s.confirmed_seq(), "time_s": s.confirmed_clock()}
            for sid, s in sorted(self.sources.items())
            if s.confirmed_seq() is not None and s.confirmed_clock() is not None and not s.foreign
        ]

    @staticmethod
    def read_state(sources: list[dict[str, Any]]) -> list[tuple[float, str, int, int]]:
        """What :meth:`export_state` gave, checked: ``(clock, source id, kind, seq)``, newest
        clock first (``KeyError``, ``TypeError`` or ``ValueError`` if it is not that)."""
        kept = []
        for entry in sources:
            kind, seq, clock = int(entry["kind"]), int(entry["seq"]), float(entry["time_s"])
            if kind not in (REFERENCE, RADAR) or not np.isfinite(clock):
                raise ValueError(f"source {entry['source_id']!r}: kind {kind}, clock {clock}")
            kept.append((clock, str(entry["source_id"]), kind, seq))
        return sorted(kept, reverse=True)

    def restore_state(self, kept: list[tuple[float, str, int, int]]) -> None:
        """Take the sources :meth:`read_state` read, before any batch.  Counters start at zero.

        Each source counts as expired (silent) until its next batch: its ``seq`` and clock still
        judge its own batches (duplicates, lost batches, a publisher's restart), but its clock of
        before the restart takes no part in the consensus or the watermark.  After a service
        down for longer than ``max_clock_skew_s`` every kept clock is that far behind: they
        would reject the first batch of every source as ahead of them, and none would move on.
        At most ``max_sources`` are held (the newest clocks)."""
        for clock, sid, kind, seq in kept:
            src = self.sources.get(sid)
            if src is None:
                if len(self.sources) >= self.params.max_sources:
                    continue
                src = self.sources[sid] = SourceClock(kind)
            if src.kind != kind:
                continue  # an id of another kind now (a site says it is a radar): not this source
            src.last_seq, src.last_time_s, src.released_time_s = seq, clock, clock
            src.expired = src.restored = True
            self.newest_s = max(self.newest_s, clock)

    def count_rejected(self, source_id: str | None) -> None:
        src = self.sources.get(source_id) if source_id is not None else None
        if src is not None:
            src.rejected += 1

    # -- data-time release -------------------------------------------------------------------
    def consensus(self) -> float:
        """The sources' common data clock: the low median of the live clocks (-inf: none yet)."""
        clocks = self._other_clocks(None)
        return _low_median(clocks) if clocks else -np.inf

    def watermark(self) -> float:
        """Data time up to which every live source has reported (see module docstring)."""
        p = self.params
        live = self._live()  # a lone clock releases nothing (module docstring)
        if not live:
            return -np.inf
        clocks = [c for c, _ in live]
        self._first_clock = min(self._first_clock, *clocks)
        newest = self._pace(live)
        # A radar whose site is known but which has not reported yet holds the others back
        # from the first data time seen, within the same lag bound.
        if any(s.last_time_s is None and s.kind == RADAR and not s.foreign for s in self.sources.values()):
            clocks.append(self._first_clock)
        return min(c for c in clocks if newest - p.max_lag_s <= c <= newest)

    def pace_s(self) -> float:
        """The clock the release follows now (:meth:`_pace`; -inf: no live clock): how far
        the outputs are behind counts from it, not from a clock running ahead alone."""
        live = self._live()
        return self._pace(live) if live else -np.inf

    def _live(self) -> list[tuple[float, float]]:
        """The live, confirmed clocks with when each was heard (``heard_at_s``), oldest first."""
        return sorted(
            (s.last_time_s, s.heard_at_s)
            for s in self.sources.values()
            if s.last_time_s is not None and not s.expired and s.lone is None
        )

    def _pace(self, live: list[tuple[float, float]]) -> float:
        """The newest live clock the release follows (``live``: the clocks, oldest first, with
        when each was heard): the newest within ``max_clock_skew_s`` of the consensus, unless
        it runs more than ``max_lag_s`` ahead of every other while at least two others are still
        reporting (heard since it was ``max_lag_s`` behind where it is): then the newest that
        another clock comes within ``max_lag_s`` of.  A radar whose clock runs ahead alone (two
        minutes fast: within the skew, so taken) would otherwise set the pace, and every honest
        radar, lagging it, would stop holding the release back: the picture would follow the
        wrong clock and leave them out.  Others that stopped reporting (an outage) do not hold
        a live radar back longer than ``max_lag_s``, as before; with fewer than three clocks no
        majority can tell a clock ahead from the other stuck behind it, and the newest leads."""
        lag = self.params.max_lag_s
        consensus = live[(len(live) - 1) // 2][0]  # (the low median)
        within = [(c, heard) for c, heard in live if c <= consensus + self.params.max_clock_skew_s]
        top = within[-1][0]
        if len(within) < 3 or top - within[-2][0] <= lag:
            return top
        if sum(heard >= top - lag for _, heard in within[:-1]) < 2:
            return top
        clocks = [c for c, _ in within]
        for upper, lower in zip(reversed(clocks[1:]), reversed(clocks[:-1]), strict=True):
            if upper - lower <= lag:
                return upper
        return top

    def release(self, until: float | None = None) -> Iterator[Release]:
        """Release held batches and expiries up to ``until`` (default: the watermark)."""
        limit = self.watermark() if until is None else until
        if self._lone:  # nothing at or beyond a lone clock (module docstring)
            limit = min(limit, np.nextafter(min(self.sources[s].lone_time() for s in self._lone), -np.inf))
        self.last_limit = max(self.last_limit, limit)
        while self._heap and self._heap[0][0] <= limit:
            clock, kind, source_id, _ = heapq.heappop(self._heap)
            src = self.sources.get(source_id)
            if kind == EXPIRE:
                if src is not None and not src.pending and self._expiry_due.get(source_id) == clock:
                    del self._expiry_due[source_id]
                    src.expired = True
                    self._forget_due[source_id] = due = clock + self.params.forget_after_s
                    heapq.heappush(self._heap, (due, FORGET, source_id, 0))
                    yield Release(src.kind, source_id, clock, None)
                continue
            if kind == FORGET:
                if src is not None and src.expired and self._forget_due.get(source_id) == clock:
                    del self._forget_due[source_id]
                    yield Release(src.kind, source_id, clock, None, forget=True)
                continue
            if src is None:  # evicted with nothing pending: cannot happen, kept for safety
                continue
            clock, _seq, item = src.pending.popleft()
            if src.pending:
                head = src.pending[0]
                heapq.heappush(self._heap, (head[0], kind, source_id, head[1]))
            else:
                due = clock + self.params.source_expiry_s
                self._expiry_due[source_id] = due
                heapq.heappush(self._heap, (due, EXPIRE, source_id, 0))
            src.released_time_s = clock
            yield Release(kind, source_id, clock, item)

    def flush(self) -> Iterator[Release]:
        """Release every held batch regardless of the watermark (end of a replay, shutdown).

        Expiry events beyond the last batch are left alone: the end of the input is not
        silence.
        """
        for sid in sorted(self._lone):  # the end of the input refuted none of them
            self._confirm(sid, self.sources[sid])
        while any(s.pending for s in self.sources.values()):
            last = max(s.pending[-1][0] for s in self.sources.values() if s.pending)
            yield from self.release(until=last)
