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
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

#: Keys counted one by one in :attr:`BoundedQueue.dropped`; drops on further keys are summed
#: under ``OTHER_KEYS`` (a flood of made-up keys must not grow the counts without bound).
MAX_DROP_KEYS = 1024
OTHER_KEYS = "(other keys)"


class BoundedQueue:
    """FIFO bounded by ``max_items`` samples and ``max_bytes`` payload bytes; thread-safe."""

    def __init__(self, max_items: int, max_bytes: int) -> None:
        if max_items < 1 or max_bytes < 1:
            raise ValueError("a bounded queue needs room for at least one sample and one byte")
        self.max_items = max_items
        self.max_bytes = max_bytes
        self._items: deque[tuple[Any, int]] = deque()
        self._bytes = 0
        self._closed = False
        self._cond = threading.Condition()
        #: Samples dropped (queue full, or closed), by key.
        self.dropped: dict[str, int] = {}
        #: The most samples and bytes ever held at once.
        self.high_water = 0
        self.high_water_bytes = 0
        #: Samples taken out so far (a consumer's progress, counted where it happens).
        self.taken = 0

    def _full_for(self, size: int) -> bool:
        n = len(self._items)
        return n >= self.max_items or (n > 0 and self._bytes + size > self.max_bytes)

    def put(self, item: Any, size: int, key: str, timeout_s: float = 0.0) -> bool:
        """Append ``item`` if there is room within ``timeout_s``; otherwise (or once closed)
        count a drop under ``key`` and return False."""
        with self._cond:
            if self._full_for(size) and not self._closed:
                deadline = time.monotonic() + timeout_s
                while self._full_for(size) and not self._closed:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
            if self._closed or self._full_for(size):
                if key not in self.dropped and len(self.dropped) >= MAX_DROP_KEYS:
                    key = OTHER_KEYS
                self.dropped[key] = self.dropped.get(key, 0) + 1
                return False
            self._append(item, size)
            return True

    def put_anyway(self, item: Any) -> None:
        """Append a marker (zero bytes) whatever the bounds: a consumer's stop signal."""
        with self._cond:
            self._append(item, 0)

    def _append(self, item: Any, size: int) -> None:
        self._items.append((item, size))
        self._bytes += size
        self.high_water = max(self.high_water, len(self._items))
        self.high_water_bytes = max(self.high_water_bytes, self._bytes)
        self._cond.notify_all()

    def get_nowait(self) -> Any:
        """The oldest item; ``IndexError`` when empty."""
        with self._cond:
            item, size = self._items.popleft()
            self._bytes -= size
            self.taken += 1
            self._cond.notify_all()
            return item

    def take_all(self, timeout_s: float) -> list[Any]:
        """Everything queued, waiting up to ``timeout_s`` for something; [] when closed and empty."""
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait(timeout_s)
            items = [item for item, _ in self._items]
            self.taken += len(items)
            self._items.clear()
            self._bytes = 0
            self._cond.notify_all()
            return items

    def close(self) -> tuple[int, int]:
        """Take nothing more (later puts are dropped and counted); wakes every waiter.  Returns
        what was queued and what had been taken at that moment, read together."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            return len(self._items), self.taken

    @property
    def closed_and_empty(self) -> bool:
        with self._cond:
            return self._closed and not self._items

    def dropped_counts(self) -> dict[str, int]:
        """A copy of :attr:`dropped` (a reader on another thread must not iterate the live dict)."""
        with self._cond:
            return dict(self.dropped)

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped_counts().values())

    def qsize(self) -> int:
        return len(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def nbytes(self) -> int:
        return self._bytes

    def empty(self) -> bool:
        return not self._items

    def items(self) -> list[Any]:
        """A copy of what is queued, oldest first (what a stop leaves, for counting)."""
        with self._cond:
            return [item for item, _ in self._items]
