"""The feed in wall time: is data still coming, and which sources have gone quiet.

Everything the service outputs is decided in data time (:mod:`.sequencer`), so a replay at any
speed equals live.  Data time alone cannot tell an operator that the feed has stopped: when
every radar falls silent, or every input is being refused, the data clock stands still and no
source ever expires in data time, while the last picture is still served as if live.  This
module watches the feed on the wall clock, for operations only:

* the outputs are **stale** once the data clock has not moved for ``stale_s`` (``/readyz``
  answers 503 with the reason, ``/status`` ``feed.stale`` is true), counting the inputs refused
  since the last one taken, so "everything is being refused" reads as such;
* a source with no batch taken for ``source_expiry_wall_s``, and none of its input waiting in
  the ingest queue (a worker behind is no silent feed), expires even while the data clock
  stands still (:meth:`FeedWatch.silent`), whichever of that and the sequencer's data-time
  ``source_expiry_s`` comes first.  It is set well above the data-time expiry, so a replay at
  anything above half speed never meets it.

Each refusal is also logged with its source and reason (:class:`RejectionLog`), at most once
per ``REJECTION_LOG_INTERVAL_S`` for each source and reason, with the count of the others, and
at most ``REJECTION_LOG_LINES`` lines of every source together in one such interval.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Collection
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from annotated_types import Gt

from service.pipeline.sequencer import Sequencer

log = logging.getLogger(__name__)

#: A source's refusals of one reason are logged at most this often (s, wall clock).
REJECTION_LOG_INTERVAL_S = 10.0
#: Most (source, reason) keys the log remembers: made-up source ids must not grow it without
#: end; beyond it, the oldest key is forgotten (its next refusal is logged again at once).
REJECTION_LOG_KEYS = 1_024
#: ... and at most this many lines of every source together in one such interval: a sender that
#: makes up a new id for each message must not flood the log line by line; what is left out is
#: counted in one line, written with the first refusal logged after the interval.
REJECTION_LOG_LINES = 20


@dataclass(frozen=True)
class FeedParams:
    """Wall-clock limits of the feed (operations; never part of a result)."""

    #: The outputs are stale, and ``/readyz`` 503, once the data clock has not moved for this
    #: long (s, wall clock) after it first moved.  Two minutes is many scans of the slowest
    #: radar (12 s), and far beyond a queue's or a correlation answer's delay.
    stale_s: Annotated[float, Gt(0)] = 120.0
    #: A source with no batch taken for this long (s, wall clock) expires even if the data
    #: clock stands still (a whole feed gone silent).  Twice the data-time ``source_expiry_s``:
    #: live, the data-time expiry always comes first; a replay slower than half speed may meet it.
    source_expiry_wall_s: float = 600.0


class RejectionLog:
    """One line per source and reason at most every ``interval_s``, with the count since."""

    def __init__(
        self,
        interval_s: float = REJECTION_LOG_INTERVAL_S,
        max_keys: int = REJECTION_LOG_KEYS,
        max_lines: int = REJECTION_LOG_LINES,
    ) -> None:
        self.interval_s = interval_s
        self.max_keys = max_keys
        self.max_lines = max_lines
        #: The interval of the line budget: its start (wall s), lines logged and refusals left out.
        self._budget_s = -np.inf
        self._lines = 0
        self._skipped = 0
        #: (source, reason) -> (wall time of the last line, refusals not logged since)
        self._seen: dict[tuple[str, str], tuple[float, int]] = {}

    def refused(self, source_id: str | None, reason: str, key: str, detail: str) -> None:
        now = time.monotonic()
        k = (source_id or "-", reason)
        last, quiet = self._seen.pop(k, (-np.inf, 0))
        if now - last < self.interval_s:
            self._seen[k] = (last, quiet + 1)  # (re-inserted: the newest keys stay)
            return
        if now - self._budget_s >= self.interval_s:
            if self._skipped:
                log.warning(
                    "rejected %d more inputs in the last %.0f s, not logged one by one "
                    "(at most %d lines an interval; /status counts every rejection)",
                    self._skipped,
                    now - self._budget_s,
                    self.max_lines,
                )
            self._budget_s, self._lines, self._skipped = now, 0, 0
        if self._lines >= self.max_lines:
            self._skipped += 1  # (counted here only: its source's own line comes when one may)
            if np.isfinite(last):
                self._seen[k] = (last, quiet)
            return
        self._lines += 1
        while len(self._seen) >= self.max_keys:
            del self._seen[next(iter(self._seen))]
        self._seen[k] = (now, 0)
        more = f" (+{quiet} more of this source and reason since the last line)" if quiet else ""
        log.warning("rejected %s from %s (%s): %s%s", reason, source_id or "no source", key, detail, more)


class FeedWatch:
    """When the data clock last moved and when each source last had a batch taken (wall s)."""

    def __init__(self, params: FeedParams | None = None) -> None:
        self.params = params or FeedParams()
        self.clock_s = -np.inf
        #: Wall time the data clock last moved (None: it never has).
        self.moved_at: float | None = None
        #: Inputs refused since the last one taken.
        self.refused_since_taken = 0
        #: Sources expired by the wall clock (a count for ``/status``).
        self.expired_by_wall = 0
        self._taken_at: dict[str, float] = {}
        self.log = RejectionLog()

    def taken(self, source_id: str, clock_s: float) -> None:
        """A batch of ``source_id`` was accepted; the data clock is now ``clock_s``.  Wall times
        here are ``time.monotonic()`` when the worker takes the input (a queue's delay is the
        worker's, not the feed's)."""
        wall = time.monotonic()
        self.refused_since_taken = 0
        self._taken_at[source_id] = wall
        if clock_s > self.clock_s:
            self.clock_s = clock_s
            self.moved_at = wall

    def refused(self, source_id: str | None, reason: str, key: str, detail: str) -> None:
        """An input was refused: counted, and logged (:class:`RejectionLog`)."""
        self.refused_since_taken += 1
        self.log.refused(source_id, reason, key, detail)

    def forget(self, source_id: str) -> None:
        self._taken_at.pop(source_id, None)

    def silent(self, now_s: float, waiting: Collection[str] = ()) -> list[str]:
        """The sources with no batch taken for ``source_expiry_wall_s``, forgotten here (each is
        expired once; its next batch makes it live again).  A source in ``waiting`` has input
        queued for the worker: it is not silent, the worker is behind (a stall of the worker's,
        say under a loaded machine, must not expire a feed that is still coming)."""
        limit = now_s - self.params.source_expiry_wall_s
        quiet = [sid for sid, t in self._taken_at.items() if t < limit and sid not in waiting]
        for sid in quiet:
            del self._taken_at[sid]
        self.expired_by_wall += len(quiet)
        return quiet

    def stale_reason(self, now_s: float) -> str:
        """Why the outputs are stale ("" when they are not, or no data came yet)."""
        if self.moved_at is None:
            return ""
        idle = now_s - self.moved_at
        if idle < self.params.stale_s:
            return ""
        n = self.refused_since_taken
        refused = f", {n} inputs refused since the last one taken" if n else ""
        return f"outputs stale: the data clock has not moved for {idle:.0f} s{refused}"

    def status(
        self, now_s: float, sequencer: Sequencer, outputs_time_s: float | None = None
    ) -> dict[str, object]:
        """``/status`` ``feed`` (with the sequencer's count of outages that ended), and how far
        the outputs (``outputs_time_s``) are behind the clock the release follows (the newest
        live one, but a clock running ahead alone: :meth:`Sequencer.pace_s`), in data time:
        what a flooding source or a slow correlation costs the others, which ``/readyz`` does
        not count (the release waits up to ``max_lag_s`` for a lagging source by design)."""
        reason = self.stale_reason(now_s)
        newest = sequencer.pace_s()
        behind = None
        if outputs_time_s is not None and np.isfinite(newest):
            behind = max(0.0, newest - outputs_time_s)
        return {
            "stale": bool(reason),
            "reason": reason,
            "idle_s": None if self.moved_at is None else round(max(0.0, now_s - self.moved_at), 3),
            "refused_since_taken": self.refused_since_taken,
            "outages": sequencer.outages,
            "last_outage_s": sequencer.last_outage_s,
            "expired_by_wall_clock": self.expired_by_wall,
            "behind_s": None if behind is None else round(behind, 3),
        }
