"""Pair books' links (their confirmed pairs) as they were after an update, read back at a
release's place in one worker's order.

A correlating worker keeps the links of its own pairs and those other workers send it
(``{prefix}/links/{a}/{b}``) at the releases that cross a multiple of the links' grid
(:mod:`.system_stage`); worker 1 draws the system tracks from them, every worker takes the
cycle step's chains from them (:mod:`.cycle_links`) and, with the aid of association on, its
trackers' partners with the pair's registration (:mod:`.partner_aid`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.fusion.members import Links

Key = tuple[str, str]
#: A release's place in one worker's order: its data time, then the radar released.
Position = tuple[float, str]


@dataclass(frozen=True)
class PairRegistration:
    """A pair correlator's own registration as it stood at its links (the aid of association,
    :mod:`.partner_aid`): its radars, their five terms ``(n, 5)`` and their relative covariance
    ``(5 n, 5 n)`` (:class:`~service.correlation.registration.BiasSolution`)."""

    radar_ids: tuple[str, ...]
    terms: np.ndarray
    covariance: np.ndarray

    @staticmethod
    def of(corr: Any) -> PairRegistration | None:
        """``corr``'s registration (a :class:`~service.correlation.PairCorrelator`); None while it
        is not registered, its solution has no relative covariance, or a number of it is not
        finite (the wire takes finite numbers only: such links go without it)."""
        sol = corr.solution
        if sol is None or sol.terms is None or sol.relative_covariance is None or not corr.registered:
            return None
        if not (np.all(np.isfinite(sol.terms)) and np.all(np.isfinite(sol.relative_covariance))):
            return None
        return PairRegistration(tuple(sol.radar_ids), sol.terms, sol.relative_covariance)


@dataclass(frozen=True)
class SharedLinks:
    """A pair's links after one of its updates (``PairLinks`` on the wire)."""

    key: Key
    time_s: float  # the data time of the release the update followed ...
    release: str  # ... and the radar released
    links: Links
    #: The pair's registration then (None: not registered, or not asked for: the aid is off).
    registration: PairRegistration | None = None

    @property
    def position(self) -> Position:
        return (self.time_s, self.release)


@dataclass(frozen=True)
class Crossing:
    """A release that crossed a multiple of the links' grid (:mod:`.system_stage`), and the
    links of the owned pairs updated since the crossing before, as they were then."""

    position: Position
    own: tuple[SharedLinks, ...]


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
        return {key: shared.links for key, shared in self.shared_at(position).items()}

    def shared_at(self, position: Position) -> dict[Key, SharedLinks]:
        """As :meth:`at`, each pair's whole message (its registration with its links)."""
        out = {}
        for key, queue in self._queues.items():
            latest = None
            while queue and queue[0].position <= position:
                latest = queue.popleft()
            if latest is not None:
                queue.appendleft(latest)  # the base of the reads to come
                out[key] = latest
        return out

    def forget(self, source_id: str) -> None:
        for key in [k for k in self._queues if source_id in k]:
            del self._queues[key]
