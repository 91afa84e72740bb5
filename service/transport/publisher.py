"""The publisher thread: puts the outputs the worker hands over (:meth:`Publisher.hand`).

The worker never waits on the network: partitioned workers publish to each other, and a worker
blocked on a put to a peer whose queue is full while that peer is blocked on a put to it would
stall both.  The outbox is bounded by count (``outbox_size``); beyond it the worker waits.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

import zenoh

from service.wire.frames import is_frame
from service.wire.keys import Keys
from service.wire.outgoing import Outgoing

log = logging.getLogger(__name__)

_STOP = object()
#: Puts a new publisher makes before trusting its matching status (see :meth:`Publisher._put`).
UNCONDITIONAL_PUTS = 8
#: ... and for how long (wall s) after it is declared, however many: a backlog taken at start
#: puts dozens of outputs on a new key within milliseconds, before its matching status has
#: heard of the subscribers that were there all along.
UNCONDITIONAL_S = 2.0
#: Most output publishers held; the least recently used beyond goes (``_bound_publishers``).
#: A national network's worker puts on about a hundred keys (tracks, pairs, system tracks).
MAX_PUBLISHERS = 1_024
_OCTETS = zenoh.Encoding.APPLICATION_OCTET_STREAM


class Publisher:
    """One thread putting outputs on ``session`` (set at :meth:`start`; None: put nothing)."""

    def __init__(self, keys: Keys, outbox_size: int, max_publishers: int = MAX_PUBLISHERS) -> None:
        self.keys = keys
        self.max_publishers = max_publishers
        self.outbox: queue.Queue[Any] = queue.Queue(maxsize=outbox_size)
        self.session: zenoh.Session | None = None
        self.publishers: dict[str, list[Any]] = {}  # key -> [publisher, unconditional puts left, until]
        self._thread: threading.Thread | None = None

    def start(self, session: zenoh.Session) -> None:
        self.session = session
        self._thread = threading.Thread(target=self._send_outputs, name="topofusion-publisher", daemon=True)
        self._thread.start()

    def hand(self, out: list[Outgoing]) -> None:
        """Hand outputs to the publisher thread (waits only when its outbox is full)."""
        if out:
            self.outbox.put(out)

    def stop(self, timeout_s: float) -> None:
        """Put whatever was handed over, waiting at most ``timeout_s`` for room in the outbox
        and as long again for the thread; then undeclare every publisher."""
        if self._thread is not None:
            try:
                self.outbox.put(_STOP, timeout=timeout_s)
            except queue.Full:
                log.error("stop: the publisher is %d outputs behind; not waiting", self.outbox.qsize())
            self._thread.join(timeout_s)
        for pub, *_ in self.publishers.values():
            try:
                pub.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        self.publishers = {}

    def _send_outputs(self) -> None:
        while True:
            out = self.outbox.get()
            if out is _STOP:
                break
            self._put(out)

    def _put(self, out: list[Outgoing]) -> None:
        """Put each output whose key has a subscriber (an output nobody hears is never encoded).

        A new publisher learns of the subscribers that already exist a round trip after it is
        declared, so its first ``UNCONDITIONAL_PUTS`` outputs, and every output of its first
        ``UNCONDITIONAL_S`` seconds, are put whatever its matching status says; errors are
        always put.
        """
        session = self.session
        if session is None:
            return
        for msg in out:
            errors = msg.key == self.keys.errors  # (logged by the engine, each source and reason)
            try:
                entry = self.publishers.pop(msg.key, None)  # (re-inserted: newest last)
                if entry is None:
                    self._bound_publishers()
                    # What partitioned workers send each other must not be dropped under load
                    # (a lost track-states message costs that radar until its next full table).
                    peer = self.keys.classify_peer(msg.key) is not None
                    pub = session.declare_publisher(
                        msg.key,
                        encoding=zenoh.Encoding.APPLICATION_JSON,
                        congestion_control=zenoh.CongestionControl.BLOCK
                        if peer
                        else zenoh.CongestionControl.DROP,
                    )
                    entry = [pub, UNCONDITIONAL_PUTS, time.monotonic() + UNCONDITIONAL_S]
                self.publishers[msg.key] = entry
                pub, fresh, until = entry
                if errors or fresh > 0 or time.monotonic() < until or pub.matching_status.matching:
                    entry[1] = fresh - 1
                    payload = msg.payload
                    # (a frame is no JSON: its numbers are raw bytes, docs/contract.md "Scale-out")
                    pub.put(payload, encoding=_OCTETS if is_frame(payload) else None)
            except Exception:
                log.exception("publish failed on %s", msg.key)

    def _bound_publishers(self) -> None:
        """Room for one more publisher: output keys come and go with radar ids (a retired
        radar's tracks and pairs), so the least recently used beyond ``max_publishers`` goes."""
        while len(self.publishers) >= self.max_publishers:
            oldest = next(iter(self.publishers))
            try:
                self.publishers.pop(oldest)[0].undeclare()
            except Exception:  # (a session closing under it: nothing left to free)
                log.debug("undeclaring the publisher of %s failed", oldest, exc_info=True)
