"""``/readyz``: why the service is not ready, from its parts (contract §4.6)."""

from __future__ import annotations

import threading
import time

from service.engine import Engine
from service.transport.intake import Intake
from service.transport.session import Connection
from service.transport.worker import Worker

#: ``/readyz`` says a worker of another network (another N or salt, or a K taken twice) holds a
#: K of this one for this long (s, wall clock) after its latest message was refused: such a
#: worker stalls the merge, and it sends while its input moves (a few messages a second).
MISMATCH_HOLD_S = 30.0


class Readiness:
    """The first reason that holds, in this order: a stop, a session Zenoh refused, a router
    not reached yet, no session or worker, a worker that died, a lost connection, input waiting
    ``stall_s`` (wall clock) with the worker taking none, a worker of another network
    (partitioned), a stale feed (``pipeline.feed``)."""

    def __init__(
        self,
        stopping: threading.Event,
        connection: Connection,
        worker: Worker,
        intake: Intake,
        engine: Engine,
        stall_s: float,
    ) -> None:
        self._stopping = stopping
        self._connection = connection
        self._worker = worker
        self._intake = intake
        self._engine = engine
        self.stall_s = stall_s
        #: The peers' count of refused workers' messages last seen, and when it last moved.
        self._mismatches = (0, -float("inf"))

    @property
    def not_ready_reason(self) -> str:
        """Why ``/readyz`` is 503, or "" when ready."""
        if self._stopping.is_set():
            return "shutting down"
        connection = self._connection
        if connection.failure:
            return f"zenoh session failed: {connection.failure}"
        if connection.connecting:
            return "connecting to zenoh"
        if connection.session is None or self._worker.thread is None:
            return "not started"
        if not self._worker.thread.is_alive():
            return "worker not running"
        if not connection.linked:
            return "no zenoh connection"
        if self.stalled:
            return "worker stalled"
        now = time.monotonic()
        return self._mismatch_reason(now) or self._engine.feed.stale_reason(now)

    def _mismatch_reason(self, now: float) -> str:
        """A worker of another network refused within ``MISMATCH_HOLD_S``, and why."""
        peers = self._engine.peers
        if peers.mismatches != self._mismatches[0]:
            self._mismatches = (peers.mismatches, now)
        if now - self._mismatches[1] > MISMATCH_HOLD_S:
            return ""
        return f"partition mismatch: {peers.mismatch}"

    @property
    def stalled(self) -> bool:
        """Input has waited ``stall_s`` with the worker taking none of it."""
        return self._intake.stalled(self.stall_s)
