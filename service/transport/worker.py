"""The worker thread: takes the queued samples (:class:`~service.transport.intake.Intake`),
calls ``engine.ingest``, hands what it returns to the publisher thread, then swaps in a new
immutable :class:`~service.engine.Snapshot` for the readers (queryables, HTTP), who take it
without locks.

At a stop it gets ``grace_s`` to finish the queue, then publishes the final outputs (the
engine's flush), and says in one line how many of the queued samples it processed and how many
it left (contract §4.6).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from service.engine import Engine, Snapshot
from service.state import StateKeeper
from service.transport.intake import Intake
from service.transport.network_status import PeerWorkers
from service.transport.publisher import Publisher
from service.wire.outgoing import Outgoing

log = logging.getLogger(__name__)

_STOP = object()
#: Readers' snapshot is rebuilt at most this often (s) while messages keep coming (and when
#: the worker falls idle): a partitioned worker takes a message from the others every few ms.
SNAPSHOT_MIN_S = 0.05
#: How often (s) an idle worker takes the correlation process's late answers.
IDLE_POLL_S = 0.05
#: At a stop, how long (s) past the grace the worker may take to finish the message it is on
#: and flush the engine (the final outputs) before the stop goes on without it.
FINISH_S = 5.0
#: How often (s) the worker looks for sources silent on the wall clock (``pipeline.feed``).
EXPIRY_POLL_S = 1.0


class Worker:
    """The one thread around the engine.  ``peers``: partitioned, the other workers (their
    liveliness sets what the merger waits for) and this worker's status is put for them every
    ``status_interval_s`` (``own_status``); None: a whole network's only worker."""

    def __init__(
        self,
        engine: Engine,
        intake: Intake,
        publisher: Publisher,
        peers: PeerWorkers | None,
        state: StateKeeper | None,
        own_status: Callable[[], dict[str, Any]],
        status_interval_s: float,
    ) -> None:
        self.engine = engine
        self.intake = intake
        self.publisher = publisher
        self.peers = peers
        self.state = state
        self.own_status = own_status
        self.status_interval_s = status_interval_s
        self.snapshot: Snapshot = engine.snapshot()
        self.processed = 0
        #: Of those, plot batches (said at a stop).
        self.processed_plots = 0
        self.thread: threading.Thread | None = None
        #: Set by :meth:`begin_stop`: when the grace ends (monotonic) and what was queued then.
        self.deadline = float("inf")
        self._stop_began = 0.0
        self._queued_at_stop = 0
        self._taken_at_stop = 0

    def start(self) -> None:
        self.thread = threading.Thread(target=self._run, name="topofusion-worker", daemon=True)
        self.thread.start()

    def _publish(self, out: list[Outgoing]) -> None:
        self.publisher.hand(out)

    def _run(self) -> None:
        next_status = next_expiry = 0.0
        last_snapshot = 0.0
        engine, intake = self.engine, self.intake
        while True:
            # Idle with answers of the correlation process still to come: look again soon.
            wait = IDLE_POLL_S if engine.answers_pending else self.status_interval_s
            if time.monotonic() >= self.deadline:
                break  # a stop's grace ran out: what is queued stays there, counted by finish()
            item = intake.next_item(wait)
            if time.monotonic() >= next_expiry:  # sources silent on the wall clock (pipeline.feed)
                next_expiry = time.monotonic() + EXPIRY_POLL_S
                self._publish(engine.expire_silent(time.monotonic(), intake.queue.classes()))
            if item is None:
                out = engine.poll()
                if out:
                    self._publish(out)
                if self.state is not None:  # a write may wait for the correlation process's part
                    self.state.maybe_save(engine)
                self.snapshot = engine.snapshot()  # (cached by the engine when unchanged)
                last_snapshot = time.monotonic()
            if item is _STOP:
                break
            if self.peers is not None:
                waited = self.peers.waited_changed()
                if waited is not None:
                    self._publish(engine.wait_for(waited))
            if item is not None:
                self._handle(*item)
                if self.state is not None:
                    self.state.maybe_save(engine)
                # A fresh snapshot when the inputs run dry, at most every SNAPSHOT_MIN_S (the
                # other workers' messages keep coming in between), and every 64 messages.
                now = time.monotonic()
                if self.processed % 64 == 0 or (
                    intake.queue.empty() and now - last_snapshot >= SNAPSHOT_MIN_S
                ):
                    self.snapshot = engine.snapshot()
                    last_snapshot = now
            if self.peers is not None and time.monotonic() >= next_status:
                next_status = time.monotonic() + self.status_interval_s
                own = self.own_status()
                key = self.peers.keys.worker_status(self.peers.partition.index)
                self._publish([Outgoing(key, lambda own=own: own)])  # type: ignore[misc]
        self._publish(engine.flush())
        self.snapshot = engine.snapshot()

    def _handle(self, key: str, payload: bytes | int, received: float) -> None:
        self.processed += 1
        self.processed_plots += key.endswith("/plots")
        try:
            if isinstance(payload, int):  # the size of a payload too large to take
                out = self.engine.reject_too_large(key, payload, received)
            else:
                out = self.engine.ingest(key, payload, received)
        except Exception:  # engine.ingest never raises on input; this is a last resort
            log.exception("engine failed on %s", key)
            return
        self._publish(out)

    # -- the stop ------------------------------------------------------------------------------
    def begin_stop(self, grace_s: float) -> None:
        """Finish the queue within ``grace_s`` from now (then :meth:`close_queue`)."""
        self._stop_began = time.monotonic()
        self.deadline = self._stop_began + grace_s

    def close_queue(self) -> None:
        """Take no more input: a sample a callback still brings is counted as dropped."""
        self._queued_at_stop, self._taken_at_stop = self.intake.queue.close()

    def finish(self) -> bool:
        """Wait for the worker to finish the queue (until the deadline) and flush the engine
        (``FINISH_S`` more, no longer), and say how it went; False while it is still busy (its
        engine is not to be read then).  A worker never started has nothing to finish."""
        if self.thread is None:
            log.info("stop: no zenoh session was open; nothing was queued")
            return True
        self.intake.put_marker(_STOP)
        self.thread.join(max(0.0, self.deadline - time.monotonic()) + FINISH_S)
        busy = self.thread.is_alive()
        self._log_stop(busy)
        return not busy

    def _log_stop(self, busy: bool) -> None:
        """The one line a stop owes (contract §4.6): how many of the input samples queued at
        the signal it processed, and how many it left, exactly (every sample the worker takes
        during a stop is processed: it looks at the deadline before taking one)."""
        queue = self.intake.queue
        queued = queue.items()
        left = [item for item in queued if item is not _STOP]
        marker_taken = len(left) == len(queued)  # (the stop marker is no sample)
        peers = self.intake.peer_queue.qsize()  # the other workers' messages still waiting (partitioned)
        done = queue.taken - self._taken_at_stop - marker_taken
        plots = sum(1 for key, _, _ in left if key.endswith("/plots"))
        also = f"; {peers} messages of other workers left" if peers else ""
        # (only once the worker thread has ended: a busy worker's engine is not to be read)
        rejected = 0 if busy else self.engine.rejected.total()
        if rejected:  # (processed all the same: checked, refused whole, reported on the errors key)
            also = f" ({rejected} messages rejected in all){also}"
        if busy:
            log.error("stop: the worker is still busy %.0f s after the grace; not waiting", FINISH_S)
        if left or busy:
            log.error(
                "stop: the %.1f s grace ran out: processed %d, %d of %d queued samples left "
                "unprocessed (%d plot batches); %d plot batches processed in all%s",
                self.deadline - self._stop_began,
                done,
                len(left),
                self._queued_at_stop,
                plots,
                self.processed_plots,
                also,
            )
        else:
            log.info(
                "stop: processed all %d queued samples in %.1f s; 0 left unprocessed; "
                "%d plot batches processed in all%s",
                done,
                time.monotonic() - self._stop_began,
                self.processed_plots,
                also,
            )
