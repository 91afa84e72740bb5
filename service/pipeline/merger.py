"""The correlation input of a partitioned worker: every radar's tables in data-time order.

Each worker tracks its own radars and releases their batches in data-time order (its
:class:`~.sequencer.Sequencer`, which also hears the other workers' radar clocks, so its
watermark is the network's).  The tables it releases go to the other workers
(:mod:`.track_exchange`); the tables every worker released reach each correlating worker in
arrival order.  The merger puts them back into the order one worker would have released them
in, ``(time_s, kind, source_id, seq)``, without ever waiting on wall time:

* every worker says how far it has released (``released_s``: all its tables up to that data
  time are published before the message that says so, ``{prefix}/workers/{K}/clock``);
* an item is released once every live worker that owns a radar has released that far.

Since each worker publishes in release order and a session's messages arrive in the order they
were put, everything at or below that limit has arrived: the release order is one worker's,
whatever the interleaving on arrival.  A worker that is gone (its liveliness token left) is
not waited for; its radars are missing until it is back.  What it published meanwhile and
arrives after the merge has released a later item (a link down for longer than the grace) is
released at once, out of the one-worker order: each such item is counted (:attr:`reordered`,
``/status`` ``partition.progress.reordered``), never hidden.

A radar whose owner is gone is silent to the others, and its tracks coast out as a silent
radar's do: the others arm an expiry of it (:meth:`TableMerger.expire`, ``Peers``), an empty
table released in data-time order like any other, which a table of the radar or its owner's
return calls off.  Nothing else of the radar is dropped: its pairs' books and registration
memory wait for the owner's return.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from service.pipeline.sequencer import EXPIRE, RADAR, Release


class TableMerger:
    """A heap of released items of every worker, released up to the slowest live owner."""

    def __init__(self) -> None:
        #: Data time up to which each worker has published everything it released.
        self.released: dict[int, float] = {}
        self._heap: list[tuple[float, int, str, int, int, int, Any]] = []
        self._tie = itertools.count()
        #: Everything up to this data time has been released.
        self.last_limit = -np.inf
        #: Items that arrived after the merge had released a later one (from a worker not
        #: waited for any more): released at the next release, out of the one-worker order.
        self.reordered = 0
        #: The order key of the last item released.
        self._last: tuple[float, int, str, int] | None = None
        #: Each radar's armed expiry (:meth:`expire`): the tie number of its heap entry ...
        self._expiring: dict[str, int] = {}
        #: ... and those of every armed expiry still in the heap (called off or not).
        self._armed: set[int] = set()

    def __len__(self) -> int:
        """The tables held (armed expiries are not)."""
        return len(self._heap) - len(self._armed)

    def push(
        self, kind: int, source_id: str, seq: int, time_s: float, item: Any, expiry: bool = False
    ) -> None:
        """A released item: a radar's table (``kind`` RADAR) or a reference batch; ``expiry``:
        the source expired (ordered after every batch of the same data time, as released)."""
        order_kind = EXPIRE if expiry else kind
        if self._last is not None and (time_s, order_kind, source_id, seq) < self._last:
            self.reordered += 1
        heapq.heappush(self._heap, (time_s, order_kind, source_id, seq, next(self._tie), kind, item))

    def expire(self, source_id: str, time_s: float, table: Any) -> None:
        """Release ``table`` (an empty one) as radar ``source_id``'s expiry at ``time_s``, after
        every table of that data time, unless :meth:`call_off` comes first; an expiry armed
        again replaces the one before."""
        tie = self._expiring[source_id] = next(self._tie)
        self._armed.add(tie)
        heapq.heappush(self._heap, (time_s, EXPIRE, source_id, 0, tie, RADAR, table))

    def call_off(self, source_id: str) -> None:
        """The radar's armed expiry does not happen (its entry is dropped when it comes up)."""
        self._expiring.pop(source_id, None)

    def expiring(self, source_id: str) -> bool:
        return source_id in self._expiring

    def _called_off(self, entry: tuple[float, int, str, int, int, int, Any]) -> bool:
        """A heap entry of an expiry called off, or armed again since."""
        return entry[4] in self._armed and self._expiring.get(entry[2]) != entry[4]

    def progress(self, worker: int, released_s: float) -> None:
        """Worker ``worker`` has published every table up to ``released_s`` (a restarted worker
        starts again from its own clock)."""
        self.released[worker] = released_s

    def limit(self, owners: Iterable[int]) -> float:
        """Data time up to which every one of ``owners`` (the live workers owning radars) has
        published."""
        return min((self.released.get(k, -np.inf) for k in owners), default=np.inf)

    def through(self, owners: Iterable[int]) -> float:
        """Data time up to which everything has been released: the last limit, or further,
        just short of the oldest item held back by a cap, where every owner has published:
        everything below has arrived and none of it is held."""
        limit = self.limit(owners)
        while self._heap and self._called_off(self._heap[0]):
            self._armed.discard(heapq.heappop(self._heap)[4])
        if self._heap:
            limit = min(limit, float(np.nextafter(self._heap[0][0], -np.inf)))
        return max(self.last_limit, limit)

    def release(self, owners: Iterable[int], cap: float = np.inf) -> Iterator[Release]:
        """Release what every live owner has published; at most up to ``cap`` (a worker's
        correlation stays close behind every other worker's, ``Peers.cap``)."""
        yield from self._until(min(self.limit(owners), cap))

    def flush(self) -> Iterator[Release]:
        """Every table held (shutdown), and the armed expiries due by the last of them (the end
        of the input is not silence, as the sequencer's ``flush`` has it)."""
        yield from self._until(max((e[0] for e in self._heap if e[4] not in self._armed), default=-np.inf))

    def _until(self, limit: float) -> Iterator[Release]:
        self.last_limit = max(self.last_limit, limit)
        while self._heap and self._heap[0][0] <= limit:
            entry = heapq.heappop(self._heap)
            time_s, order, source_id, seq, tie, kind, item = entry
            if tie in self._armed:  # an armed expiry (:meth:`expire`)
                called_off = self._called_off(entry)
                self._armed.discard(tie)
                if called_off:
                    continue
                del self._expiring[source_id]
            self._last = (time_s, order, source_id, seq)
            yield Release(kind, source_id, time_s, item)
