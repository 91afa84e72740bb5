"""The engine's correlation stage: one ``PairCorrelator`` per pair of sources, on a data-time schedule.

Radar pairs use the configured method.  An AIS source is a bias-free reference: each radar is
correlated with it by ``cfar`` (the method built for cooperative references) and the pairs
feed the joint bias estimate, which then is absolute rather than relative.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.correlation import PairCorrelator, estimate_biases
from service.geo import Site
from service.snapshot import bias_dict, pair_set
from service.tracking.base import TrackTable

#: Method used between a radar and an AIS reference source.
REFERENCE_METHOD = "cfar"


@dataclass(frozen=True)
class Source:
    """What the stage needs of one source at an update."""

    source_id: str
    geometry: Site | None  # None: a bias-free reference (AIS)
    tracks: Callable[[float], TrackTable]


class CorrelationStage:
    def __init__(self, method: str, interval_s: float, max_site_distance_m: float) -> None:
        self.method = method
        self.interval_s = interval_s
        self.max_site_distance_m = max_site_distance_m
        self.correlators: dict[tuple[str, str], PairCorrelator] = {}
        self.next_due: dict[tuple[str, str], float] = {}
        self.last_time: dict[tuple[str, str], float] = {}
        self.timings_ms: deque[float] = deque(maxlen=2048)
        self.updates = 0
        self.last_ms = 0.0
        self._bias_time = 0.0
        self._bias_cache: tuple[int, list[dict[str, Any]]] = (0, [])

    def forget(self, source_id: str) -> None:
        """A source's geometry changed: its pairs start afresh."""
        for key in [k for k in self.correlators if source_id in k]:
            del self.correlators[key]
            self.next_due.pop(key, None)
            self.last_time.pop(key, None)

    def _overlaps(self, a: Site, b: Site | None) -> bool:
        if b is None:
            return True
        return bool(np.linalg.norm(a.origin_ecef - b.origin_ecef) <= self.max_site_distance_m)

    def update(self, radar: Source, others: list[Source], time_s: float) -> list[dict[str, Any]]:
        """Correlate ``radar`` with every overlapping source due for an update; PairSets out."""
        assert radar.geometry is not None
        results = []
        for other in others:
            if not self._overlaps(radar.geometry, other.geometry):
                continue
            key = (min(radar.source_id, other.source_id), max(radar.source_id, other.source_id))
            if time_s < self.next_due.get(key, -np.inf):
                continue
            self.next_due[key] = time_s + self.interval_s
            # The correlator's A side is a radar; for AIS the reference is always its B side.
            first, second = (
                (radar, other) if other.geometry is None or key[0] == radar.source_id else (other, radar)
            )
            corr = self.correlators.get(key)
            if corr is None:
                method = self.method if second.geometry is not None else REFERENCE_METHOD
                assert first.geometry is not None
                corr = self.correlators[key] = PairCorrelator(method, first.geometry, second.geometry)
            corr.update(first.tracks(time_s), second.tracks(time_s), time_s)
            self.last_time[key] = time_s
            self.updates += 1
            self.last_ms = float(corr.last_update_ms)
            self.timings_ms.append(self.last_ms)
            results.append(self._pair_set(key, corr))
        if results:
            self._bias_time = time_s
        return results

    def biases(self) -> list[dict[str, Any]]:
        """Joint bias estimate over every pair, solved when asked (once per correlation update)."""
        if self._bias_cache[0] != self.updates:
            estimates = estimate_biases(list(self.correlators.values()), self._bias_time)
            self._bias_cache = (self.updates, [b for b in map(bias_dict, estimates) if b is not None])
        return self._bias_cache[1]

    def _pair_set(self, key: tuple[str, str], corr: PairCorrelator) -> dict[str, Any]:
        swap = corr.site_a.site_id != key[0]
        return pair_set(key[0], key[1], self.last_time.get(key, 0.0), corr.method, corr.pairs(), swap=swap)

    def pair_sets(self) -> list[dict[str, Any]]:
        return [self._pair_set(key, corr) for key, corr in sorted(self.correlators.items())]

    def timings(self) -> dict[str, Any]:
        t = np.asarray(self.timings_ms) if self.timings_ms else np.zeros(1)
        return {
            "updates": self.updates,
            "last_ms": round(self.last_ms, 3),
            "p50_ms": round(float(np.percentile(t, 50)), 3),
            "p99_ms": round(float(np.percentile(t, 99)), 3),
        }
