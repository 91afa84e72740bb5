"""Intake: the Zenoh input callbacks put ``(key, bytes, time)`` on the bounded queues; the
worker takes from them (:meth:`Intake.next_item`).

The callbacks run on Zenoh's network thread and do no work: a plot batch of a radar another
partitioned worker owns is dropped there, a payload above the contract's bound is queued as its
size only, and a sample waits at most ``queue_wait_s`` for room (then it is dropped, counted by
key and logged).  The inputs' queue is fair by source (``ingest_queue``, "Fair intake"); the
other workers' messages have a queue of their own, taken first.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zenoh

from service.pipeline.partition import Partition
from service.transport.ingest_queue import MAX_DROP_KEYS, OTHER_KEYS, BoundedQueue
from service.wire.keys import PRIORITY_KINDS, Keys, parse_key
from service.wire.models import MAX_PAYLOAD_BYTES

log = logging.getLogger(__name__)

#: A drop on a full queue is logged at most this often per key (s), with the count since.
DROP_LOG_INTERVAL_S = 10.0


class RateLimitedLog:
    """Logs ``what (reason): message`` at most once per ``interval_s`` and reason, with a count
    of the rest."""

    def __init__(
        self, interval_s: float = 10.0, what: str = "rejected", level: int = logging.WARNING
    ) -> None:
        self.interval_s = interval_s
        self.what = what
        self.level = level
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warn(self, reason: str, message: str) -> None:
        if reason not in self._last and len(self._last) >= MAX_DROP_KEYS:
            reason = OTHER_KEYS  # (made-up keys must not grow the table without end)
        now = time.monotonic()
        if now - self._last.get(reason, -1e9) >= self.interval_s:
            extra = self._suppressed.pop(reason, 0)
            suffix = f" (+{extra} more since last report)" if extra else ""
            log.log(self.level, "%s (%s): %s%s", self.what, reason, message, suffix)
            self._last[reason] = now
        else:
            self._suppressed[reason] = self._suppressed.get(reason, 0) + 1


class Intake:
    """The input subscribers' keys and callback, and the two queues behind it."""

    def __init__(
        self,
        keys: Keys,
        partition: Partition,
        radars: tuple[str, ...],
        queue_size: int,
        queue_bytes: int,
        queue_wait_s: float,
        stopping: threading.Event,
    ) -> None:
        self.keys = keys
        self.partition = partition
        #: ``--radars``: the only radars subscribed to (empty: every radar under the prefix).
        self.radars = radars
        self.queue_wait_s = queue_wait_s
        self._stopping = stopping
        #: Fair by source (``ingest_queue``): a flooding source drops its own excess, not others'.
        self.queue = BoundedQueue(queue_size, queue_bytes, fair_by=self.source_of)
        #: Partitioned: the other workers' messages, taken before inputs (see :meth:`next_item`);
        #: bounded like the inputs' (anyone who may put on their keys could flood it; a lost
        #: track-states change costs that radar until its owner's next full table).
        self.peer_queue = BoundedQueue(queue_size, queue_bytes)
        self._items = threading.Semaphore(0)  # one release per item put on either queue
        self._drop_log = RateLimitedLog(DROP_LOG_INTERVAL_S, "dropped on a full ingest queue", logging.ERROR)
        #: When the worker last took a sample or found none (monotonic): progress, for /readyz.
        self.last_take = time.monotonic()

    def input_keys(self) -> list[str]:
        """Every radar's inputs (or only those of ``--radars``), and what partitioned workers
        send each other (the registration rows: to the bias worker only)."""
        ids = self.radars or ("*",)
        radar_keys = [k for rid in ids for k in (self.keys.site(rid), self.keys.plots(rid))]
        peer = [] if self.partition.whole else list(self.keys.peer_inputs)
        if not self.partition.solves_biases:  # (the rows are the bias worker's alone: unsent here)
            peer.remove(self.keys.registration_inputs)
        return [*radar_keys, self.keys.ais_inputs, self.keys.adsb_inputs, *peer]

    def on_sample(self, sample: zenoh.Sample) -> None:
        """The input subscribers' callback (Zenoh's network thread; no work here)."""
        key = str(sample.key_expr)
        if not self.partition.whole and key.endswith("/plots"):
            kind, ids = parse_key(key, self.keys.prefix)
            if kind == "plots" and not self.partition.owns(ids[0]):
                return  # another worker's radar
        size = len(sample.payload)
        # A payload above the contract's bound is rejected unread: not copied, not queued whole.
        item = (key, sample.payload.to_bytes() if size <= MAX_PAYLOAD_BYTES else size, time.time())
        peer = self.keys.classify_peer(key) if not self.partition.whole else None
        into = self.peer_queue if peer is not None and peer[0] in PRIORITY_KINDS else self.queue
        if into.put(item, size if size <= MAX_PAYLOAD_BYTES else 0, key, self.queue_wait_s):
            self._items.release()
        elif not self._stopping.is_set():
            self._drop_log.warn(key, into.last_drop)

    def source_of(self, key: str) -> str:
        """The ingest queue's class of a key: its source (a radar's site and plots together)."""
        kind = self.keys.classify(key)
        return kind[1] if kind is not None else key

    def next_item(self, wait: float) -> Any:
        """The next message, the other workers' tables, rows and progress first: they only move
        the correlation along (in data-time order whatever the order they are taken in), while
        inputs queued before them would otherwise keep the merger waiting and the tables piling
        up.  None: nothing came for ``wait`` s."""
        took = self._items.acquire(timeout=wait)
        self.last_take = time.monotonic()
        if not took:
            return None
        try:
            return self.peer_queue.get_nowait()
        except IndexError:  # (one release per item put: the item is on the inputs' queue)
            return self.queue.get_nowait()

    def put_marker(self, marker: object) -> None:
        """Queue ``marker`` behind every input (the worker's stop)."""
        self.queue.put_anyway(marker)
        self._items.release()

    def stalled(self, stall_s: float) -> bool:
        """Input has waited ``stall_s`` with the worker taking none of it."""
        waiting = not self.queue.empty() or not self.peer_queue.empty()
        return waiting and time.monotonic() - self.last_take > stall_s

    def status(self) -> dict[str, Any]:
        """``/status`` ``queue``: depth and bounds, and the drops by key (contract §4.6)."""
        dropped = self.queue.dropped_counts() | self.peer_queue.dropped_counts()  # (distinct keys)
        return {
            "depth": self.queue.qsize(),
            "capacity": self.queue.max_items,
            "high_water": self.queue.high_water,
            "dropped": sum(dropped.values()),
            "bytes": self.queue.nbytes(),
            "capacity_bytes": self.queue.max_bytes,
            "dropped_by_key": dropped,
        }
