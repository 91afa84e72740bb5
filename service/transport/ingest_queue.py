"""The queue behind a Zenoh callback, bounded in samples and in bytes, drops counted by key.

``queue.Queue`` bounds only the count, and a count alone bounds nothing with payloads of up
to 16 MiB (4 096 of them would be 64 GiB).  Here a sample is let in while both the count and
the payload bytes stay within their bounds; one sample is always let into an empty queue,
so a payload larger than the byte bound (the engine rejects it as ``too_large``) cannot block
the queue for good.  A producer finding it full waits at most the time it is given (the
callbacks run on Zenoh's network thread, which must not stall for long: contract §4.6), then
the sample is dropped and counted under its key.

The service's worker takes samples one by one (:meth:`get_nowait`); the recorder's writer
takes everything queued at once (:meth:`take_all`).

Fair intake (``fair_by``)
-------------------------
Given ``fair_by`` (a key's class: the service's is the source id), the worker still takes the
samples in arrival order, which is data-time order for honest sources (the sequencer's
``max_lag_s`` rule makes a source that falls far behind in arrival count as late), with one
exception: after a sample of a class that presses (holds ``PRESSING_SHARE`` of its share,
below: a flood), the next is the oldest of another class, if there is one.  So a source that
floods gets about half the worker at most, and the others' samples wait behind one of its own,
not behind its backlog; each class's samples keep their order (a radar's site before its plots).

A class may hold at most its fair share of the queue (:meth:`BoundedQueue._share`): the bound
divided by two more than the other classes holding ``MIN_SHARE`` samples or more, so a new
source always finds room.  A class at its share while no other class holds ``PRESSING_SHARE`` of its
own is the one flooding: its sample is dropped at once and counted under its key, without
waiting (the callback runs on Zenoh's network thread, which carries the other sources' samples
too).  When other classes press as well (a replay as fast as it goes) a sample waits for room
as above, which pushes back on the publishers instead of losing data.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

#: Keys counted one by one in :attr:`BoundedQueue.dropped`; drops on further keys are summed
#: under ``OTHER_KEYS`` (a flood of made-up keys must not grow the counts without bound).
MAX_DROP_KEYS = 1024
OTHER_KEYS = "(other keys)"
#: Fair intake: a class may always hold this many samples, however many classes share the queue.
MIN_SHARE = 16
#: Fair intake: a class holding this fraction of its share presses; a class at its share is
#: dropped at once while it alone presses, and waits for room (push-back) when others press too.
PRESSING_SHARE = 0.5
#: The class of markers (:meth:`BoundedQueue.put_anyway`): never taken ahead of older samples.
_MARKERS = "\x00markers"


class BoundedQueue:
    """FIFO bounded by ``max_items`` samples and ``max_bytes`` payload bytes; thread-safe."""

    def __init__(self, max_items: int, max_bytes: int, fair_by: Callable[[str], str] | None = None) -> None:
        if max_items < 1 or max_bytes < 1:
            raise ValueError("a bounded queue needs room for at least one sample and one byte")
        self.max_items = max_items
        self.max_bytes = max_bytes
        self.fair_by = fair_by
        #: Each class's FIFO of (arrival number, item, bytes); only classes with samples.
        self._fifo: dict[str, deque[tuple[int, Any, int]]] = {}
        self._arrivals = 0
        #: The class of the last sample taken, if it held its whole share (fair intake).
        self._capped: str | None = None
        self._n = 0
        self._bytes = 0
        self._closed = False
        #: Why the latest drop was (for the log line; with several callers, one of theirs).
        self.last_drop = ""
        self._cond = threading.Condition()
        #: Samples dropped (queue full, or closed), by key.
        self.dropped: dict[str, int] = {}
        #: The most samples and bytes ever held at once.
        self.high_water = 0
        self.high_water_bytes = 0
        #: Samples taken out so far (a consumer's progress, counted where it happens).
        self.taken = 0

    def _full_for(self, size: int) -> bool:
        n = self._n
        return n >= self.max_items or (n > 0 and self._bytes + size > self.max_bytes)

    def _share(self, cls: str) -> int:
        """The most ``cls`` may hold: the bound over two more than the other classes holding
        ``MIN_SHARE`` samples or more (many sources with a sample or two each do not shrink the
        shares, and a source that starts, or comes back, always finds room, even next to a
        flood that began alone), never under ``MIN_SHARE``."""
        heavy = sum(len(f) >= MIN_SHARE for c, f in self._fifo.items() if c != cls)
        return max(MIN_SHARE, self.max_items // (heavy + 2))

    def _over_share(self, cls: str) -> bool:
        """Whether ``cls`` floods alone (see module docstring): it holds its share or more,
        and no other class presses."""
        held = len(self._fifo.get(cls, ()))
        if held < MIN_SHARE:
            return False
        share = self._share(cls)
        pressing = PRESSING_SHARE * share
        return held >= share and not any(len(f) >= pressing for c, f in self._fifo.items() if c != cls)

    def put(self, item: Any, size: int, key: str, timeout_s: float = 0.0) -> bool:
        """Append ``item`` if there is room within ``timeout_s``; otherwise (or once closed, or
        its class over its fair share) count a drop under ``key`` and return False."""
        with self._cond:
            cls = self.fair_by(key) if self.fair_by is not None else ""
            if self.fair_by is not None and self._over_share(cls):
                self._count_drop(key)
                self.last_drop = "its source holds its fair share of the queue already (dropped at once)"
                return False
            if self._full_for(size) and not self._closed:
                deadline = time.monotonic() + timeout_s
                while self._full_for(size) and not self._closed:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
            if self._closed or self._full_for(size):
                self._count_drop(key)
                self.last_drop = "closed" if self._closed else f"no room for {timeout_s:.2f} s"
                return False
            self._append(cls, item, size)
            return True

    def _count_drop(self, key: str) -> None:
        if key not in self.dropped and len(self.dropped) >= MAX_DROP_KEYS:
            key = OTHER_KEYS
        self.dropped[key] = self.dropped.get(key, 0) + 1

    def put_anyway(self, item: Any) -> None:
        """Append a marker (zero bytes) whatever the bounds: a consumer's stop signal (taken
        after everything queued before it)."""
        with self._cond:
            self._append(None, item, 0)

    def _append(self, cls: str | None, item: Any, size: int) -> None:
        if cls is None:  # a marker: numbered after everything queued, taken after it
            cls = _MARKERS
        fifo = self._fifo.get(cls)
        if fifo is None:
            fifo = self._fifo[cls] = deque()
        self._arrivals += 1
        fifo.append((self._arrivals, item, size))
        self._n += 1
        self._bytes += size
        self.high_water = max(self.high_water, self._n)
        self.high_water_bytes = max(self.high_water_bytes, self._bytes)
        self._cond.notify_all()

    def _next_class(self) -> str:
        """The class whose oldest sample is taken next (see module docstring)."""
        if len(self._fifo) == 1:
            return next(iter(self._fifo))
        heads = [(f[0][0], c) for c, f in self._fifo.items()]
        if self._capped is not None:  # the last one taken was a flooder's: another's, if any
            others = [h for h in heads if h[1] != self._capped and h[1] is not _MARKERS]
            if others:
                return min(others)[1]
        return min(heads)[1]

    def get_nowait(self) -> Any:
        """The next item (see module docstring); ``IndexError`` when empty."""
        with self._cond:
            if not self._n:
                raise IndexError("empty queue")
            cls = self._next_class()
            fifo = self._fifo[cls]
            n = len(fifo)  # (a flood bounces at its share: half of it is a flood too)
            capped = self.fair_by is not None and n >= MIN_SHARE and n >= PRESSING_SHARE * self._share(cls)
            self._capped = cls if capped else None
            _, item, size = fifo.popleft()
            if not fifo:
                del self._fifo[cls]
            self._n -= 1
            self._bytes -= size
            self.taken += 1
            self._cond.notify_all()
            return item

    def take_all(self, timeout_s: float) -> list[Any]:
        """Everything queued, waiting up to ``timeout_s`` for something; [] when closed and empty."""
        with self._cond:
            if not self._n and not self._closed:
                self._cond.wait(timeout_s)
            items = self._all()
            self.taken += len(items)
            self._fifo.clear()
            self._n = 0
            self._bytes = 0
            self._cond.notify_all()
            return items

    def _all(self) -> list[Any]:
        """Everything queued, in arrival order."""
        return [item for _, item, _ in sorted(e for f in self._fifo.values() for e in f)]

    def close(self) -> tuple[int, int]:
        """Take nothing more (later puts are dropped and counted); wakes every waiter.  Returns
        what was queued and what had been taken at that moment, read together."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            return self._n, self.taken

    @property
    def closed_and_empty(self) -> bool:
        with self._cond:
            return self._closed and not self._n

    def dropped_counts(self) -> dict[str, int]:
        """A copy of :attr:`dropped` (a reader on another thread must not iterate the live dict)."""
        with self._cond:
            return dict(self.dropped)

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped_counts().values())

    def classes(self) -> set[str]:
        """The classes with samples queued (with ``fair_by``: the sources waiting to be taken)."""
        with self._cond:
            return {c for c in self._fifo if c is not _MARKERS}

    def qsize(self) -> int:
        return self._n

    def __len__(self) -> int:
        return self._n

    def nbytes(self) -> int:
        return self._bytes

    def empty(self) -> bool:
        return not self._n

    def items(self) -> list[Any]:
        """A copy of what is queued, each class oldest first (what a stop leaves, for counting)."""
        with self._cond:
            return self._all()
