"""Pair books' links (their confirmed pairs) as they were after an update, read back at a
release's place in one worker's order.

A correlating worker keeps the links of its own pairs and those other workers send it
(``{prefix}/links/{a}/{b}``) at the releases that cross a multiple of the links' grid
(:mod:`.system_stage`); worker 1 draws the system tracks from them and every worker takes the
cycle step's chains from them (:mod:`.cycle_links`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from service.fusion.members import Links

Key = tuple[str, str]
#: A release's place in one worker's order: its data time, then the radar released.
Position = tuple[float, str]


@dataclass(frozen=True)
class SharedLinks:
    """A pair's links after one of its updates (``PairLinks`` on the wire)."""

    key: Key
    time_s: float  # the data time of the release the update followed ...
    release: str  # ... and the radar released
    links: Links

    @property
    def position(self) -> Position:
        return (self.time_s, self.release)


class LinksHistory:
    """Each pair's links after its updates, oldest first (a pair's owner sends them in the
    order it updated it), read at positions that only move on."""

    def __init__(self) -> None:
        self._queues: dict[Key, deque[SharedLinks]] = {}

    def record(self, shared: SharedLinks) -> None:
        self._queues.setdefault(shared.key, deque()).append(shared)

    def at(self, position: Position) -> dict[Key, Links]:
        """Every pair's latest links at or before ``position`` (none yet: left out); the older
        ones are dropped, as no later read needs them."""
        out = {}
        for key, queue in self._queues.items():
            latest = None
            while queue and queue[0].position <= position:
                latest = queue.popleft()
            if latest is not None:
                queue.appendleft(latest)  # the base of the reads to come
                out[key] = latest.links
        return out

    def forget(self, source_id: str) -> None:
        for key in [k for k in self._queues if source_id in k]:
            del self._queues[key]
