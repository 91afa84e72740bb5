"""Pacing a simulated feed by data time, with a periodic chore (the sites put again).

Every output of ``topofusion simulate`` (Zenoh payloads, ASTERIX to a file or over UDP) sends
its messages at their data time divided by ``speed`` after the first one, and between them
does something every ``every_s`` wall seconds: a late joiner learns the sites from it, so the
chore must run during long waits too (a slow ``--speed``), not only between messages.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class Pacer:
    """Waits until a message's data time is due; runs ``chore`` every ``every_s`` wall seconds.

    ``speed`` scales data time to wall time (0: no waiting).  ``every_s`` None or 0: no chore.
    """

    def __init__(
        self,
        speed: float,
        stop: threading.Event,
        every_s: float | None = None,
        chore: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if speed < 0:
            raise ValueError("speed must be >= 0")
        self.speed = speed
        self.stop = stop
        self.every_s = every_s if every_s and chore is not None else None
        self.chore = chore
        self.clock = clock
        self._wall0: float | None = None
        self._data0 = 0.0
        self._next_chore = clock() + self.every_s if self.every_s is not None else None

    def due(self, data_time_s: float) -> bool:
        """Wait until ``data_time_s`` is due (the first call anchors the schedule); False when
        stopped meanwhile.  The chore runs whenever its time comes, while waiting too."""
        if self._wall0 is None:
            self._wall0, self._data0 = self.clock(), data_time_s
        due = self._wall0 + (data_time_s - self._data0) / self.speed if self.speed > 0 else None
        while True:
            self.tick()
            now = self.clock()
            if due is None or due <= now:
                return not self.stop.is_set()
            wait = due - now
            if self._next_chore is not None:
                wait = min(wait, max(self._next_chore - now, 0.0))
            if self.stop.wait(wait):
                return False

    def tick(self) -> None:
        """Run the chore if its time has come."""
        if self._next_chore is None or self.chore is None:
            return
        now = self.clock()
        if now >= self._next_chore:
            assert self.every_s is not None
            self._next_chore = now + self.every_s
            self.chore()
