"""When a replay into a live service is done: the service's outputs complete through its end.

A replay has published its last message long before the service has processed it: the
messages wait in the service's queue, its sequencer holds each source's batches until every
live source has reported that far (the watermark), and the correlation may run behind in its
own process.  The service says how far its outputs go (contract §5.1: ``Status.outputs_time_s``,
``correlation.pending``); the replay waits until that reaches the recording's end.

The end a service can reach is the watermark the recording allows: every source's last batch
time, the lowest of them (a source that fell silent more than ``lag_s`` before the newest
one does not hold the others back, as in the service's sequencer).  Batches above it wait
for data that never comes (they are released at the service's stop).  A replay counts only
the batches the service takes: each goes through a sequencer of the service's own
(:class:`~service.pipeline.sequencer.Sequencer`, default parameters) as the engine's does,
so a batch it refuses (a time stamp an hour ahead, a repeated ``seq``) moves no end.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import orjson

from service.pipeline.errors import RejectionError
from service.pipeline.sequencer import RADAR, REFERENCE, Sequencer
from service.recording.reader import RecordedMessage
from service.transport.session import json_replies
from service.wire.keys import parse_key
from service.wire.models import MAX_TIME_S

#: Sources more than this far behind the newest source's last batch do not hold back the end
#: (the service's ``sequencer.max_lag_s`` default).
LAG_S = 30.0
#: How often the service's status is asked (s).
POLL_S = 0.2
#: ``service_statuses``: each ``get {prefix}/status`` waits this long for its replies (s) ...
STATUS_QUERY_S = 1.0
#: ... and, when nobody answered, the next is made after this pause (s).
STATUS_RETRY_S = 0.5


def service_statuses(
    session: Any, prefix: str, wait_s: float, stop: threading.Event | None = None
) -> list[dict[str, Any]]:
    """The services' answers to ``get {prefix}/status`` (one per partitioned worker), asking
    again until one answers, ``wait_s`` has passed or ``stop`` is set; [] when none answered.

    A tool that sends a service its inputs (``simulate``, ``replay``, ``asterix`` with
    ``--wait-service``) waits so before its first message: the service declares its input
    subscribers before its status queryable, so once it answers, nothing sent is lost on it.
    """
    deadline = time.monotonic() + wait_s
    while True:
        answers = list(json_replies(session.get(f"{prefix}/status", timeout=STATUS_QUERY_S)))
        if answers:
            return answers
        left = deadline - time.monotonic()
        if left <= 0:
            return []
        pause = min(STATUS_RETRY_S, left)
        if stop is not None:
            if stop.wait(pause):
                return []
        else:
            time.sleep(pause)


@dataclass
class RecordingEnd:
    """Each input source's last data time in what was replayed (fed message by message)."""

    last: dict[str, float] = field(default_factory=dict)
    #: The prefix of the recorded keys; with it (:meth:`add`), only the batches a service's
    #: sequencer takes count (module docstring).  None: every batch with a time counts.
    prefix: str | None = None
    #: The batches the sequencer refused as a repeated ``seq``: the recording's own duplicates
    #: (a source that sent a batch twice), which a fresh service rejects too.
    duplicates: int = 0
    _sequencer: Sequencer = field(default_factory=Sequencer, repr=False)
    _radars: set[str] = field(default_factory=set, repr=False)

    def add(self, message: RecordedMessage) -> None:
        if message.kind == "site" and self.prefix is not None:
            self._site(message)
            return
        if message.kind not in ("plots", "ais", "adsb"):
            return
        try:
            body = orjson.loads(message.payload)
            time_s = float(body["time_s"])
        except (orjson.JSONDecodeError, KeyError, TypeError, ValueError):
            return  # the service rejects it: it moves no clock
        if self.prefix is not None:
            self._sequence(message, body, time_s)
            return
        key = message.key
        self.last[key] = max(time_s, self.last.get(key, time_s))

    def _site(self, message: RecordedMessage) -> None:
        """A radar's site: its plots are taken from now on, and it counts as known (the
        sequencer's ``sites_known``, as the engine keeps it)."""
        radar_id = self._source_id(message)
        if radar_id is not None and radar_id not in self._radars:
            self._radars.add(radar_id)
            self._sequencer.announce(radar_id, RADAR)
            self._sequencer.sites_known = len(self._radars)

    def _sequence(self, message: RecordedMessage, body: object, time_s: float) -> None:
        """The batch through the sequencer, as the engine takes it (module docstring): a batch
        refused, held a step ahead or lone (not confirmed) moves no source's confirmed clock."""
        source_id = self._source_id(message)
        if source_id is None:
            return
        seq = body.get("seq") if isinstance(body, dict) else None
        if not isinstance(seq, int) or isinstance(seq, bool) or not 0 <= seq < 2**63:
            return  # (a schema or range error: rejected whole)
        if not 0.0 <= time_s <= MAX_TIME_S:  # (NaN too)
            return
        if message.kind == "plots" and source_id not in self._radars:
            return  # (unknown_radar)
        sequencer = self._sequencer
        try:
            adm = sequencer.check(source_id, RADAR if message.kind == "plots" else REFERENCE, seq, time_s)
        except RejectionError as exc:
            self.duplicates += exc.reason == "duplicate_seq"
            return
        sequencer.accept(adm, None)
        for _ in sequencer.release():  # (nothing is kept: the items are None)
            pass

    def _source_id(self, message: RecordedMessage) -> str | None:
        """The radar or source id in the message's key (None: a key of no source)."""
        assert self.prefix is not None
        ids = parse_key(message.key, self.prefix)[1]
        return ids[0] if ids else None

    def _clocks(self) -> list[float]:
        """Each source's last batch time: its confirmed clock in the sequencer (with a prefix),
        else the newest time :meth:`add` saw."""
        if self.prefix is None:
            return list(self.last.values())
        clocks = (s.confirmed_clock() for s in self._sequencer.sources.values())
        return [c for c in clocks if c is not None]

    def target_s(self, lag_s: float = LAG_S) -> float | None:
        """The data time through which the service can be complete (module docstring)."""
        clocks = self._clocks()
        if not clocks:
            return None
        newest = max(clocks)
        return min(t for t in clocks if t >= newest - lag_s)


def wait_complete(
    status: Callable[[], dict[str, Any] | None],
    target_s: float,
    timeout_s: float,
    say: Callable[[str], None],
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    no_answer_s: float = 5.0,
) -> tuple[bool, float | None, bool]:
    """Ask ``status()`` until its ``outputs_time_s`` reaches ``target_s`` with nothing pending,
    at most ``timeout_s``: ``(done, outputs_time_s last seen, answered)``.  A None status is no
    answer; none for ``no_answer_s`` means no service listens (nothing to wait for)."""
    start = clock()
    deadline = start + timeout_s
    seen: float | None = None
    answered = False
    said = start
    while True:
        st = status()
        if st is None and not answered and clock() - start >= no_answer_s:
            return False, None, False
        if st is not None:
            answered = True
            seen = st.get("outputs_time_s")
            pending = int((st.get("correlation") or {}).get("pending", 0))
            if seen is not None and seen >= target_s and pending == 0:
                return True, seen, True
        now = clock()
        if now >= deadline:
            return False, seen, answered
        if now - said >= 5.0:
            said = now
            behind = "no answer yet" if seen is None else f"{target_s - seen:.1f} s of data time behind"
            say(f"waiting for the service's outputs: {behind}")
        sleep(POLL_S)


def wait_for_outputs(
    session: Any,
    prefix: str,
    end: RecordingEnd,
    timeout_s: float,
    what: str = "the recording",
    say: Callable[[str], None] | None = None,
) -> bool:
    """Wait until the service's outputs are complete through the end of ``what`` was sent
    (contract §5.1), saying so (``say``: a line to stderr by default); False (with a line saying
    why) when it did not get there in time.  ``replay``, ``simulate`` (``what``: "the run") and
    the ASTERIX bridge writing CAT062 end so.  Partitioned workers each answer: the outputs are
    complete through the lowest of their times, with the sum of their pending answers."""
    target = end.target_s()
    if target is None:
        return True
    if say is None:

        def say(line: str) -> None:
            print(line, file=sys.stderr, flush=True)

    def status() -> dict[str, Any] | None:
        answers = list(json_replies(session.get(f"{prefix}/status", timeout=STATUS_QUERY_S)))
        return merged_status(answers) if answers else None

    t0 = time.monotonic()
    done, seen, answered = wait_complete(status, target, timeout_s, say)
    if not answered:
        say(f"no service answered {prefix}/status: not waiting for its outputs")
        return True
    if done:
        say(
            f"the service's outputs are complete through data time {seen:.3f} "
            f"({what}'s end, {target:.3f}), {time.monotonic() - t0:.1f} s after the last message"
        )
        return True
    got = (
        "the service reports no outputs yet"
        if seen is None
        else f"its outputs are complete through {seen:.3f} only"
    )
    say(
        f"WARNING: {got} after {timeout_s:g} s; {what} ends at data time {target:.3f} "
        f"(a busy service may still be processing it: --wait S to wait longer, 0 not to wait)"
    )
    return False


def merged_status(answers: list[dict[str, Any]]) -> dict[str, Any]:
    """The answers of every worker as one: ``outputs_time_s`` the lowest (None while any has
    none), ``correlation.pending`` the sum (what :func:`wait_complete` reads)."""
    times = [a.get("outputs_time_s") for a in answers]
    known = [float(t) for t in times if t is not None]
    pending = sum(int((a.get("correlation") or {}).get("pending", 0)) for a in answers)
    return {
        "outputs_time_s": min(known) if len(known) == len(times) else None,
        "correlation": {"pending": pending},
    }
