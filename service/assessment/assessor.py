"""The live performance assessment of every radar against the references (contract §5.3).

:class:`Assessment` is fed what the pipeline already has, in release (data-time) order: each
radar's plot batches, each reference source's reports, and the confirmed pairs of radar tracks
with reference tracks (which aircraft are a radar's *reference trajectories*).  It does its work
on a data-time schedule: step ``k`` assesses the plots up to ``k * step_s - lag_s`` once data
time has reached ``k * step_s`` and the correlation has answered up to that time too, so the
figures of step ``k`` are the same live and in a replay, whatever the correlation's speed.
Without a reference source nothing is held or computed.  Cost per step: one indexing of the
reference reports, and per radar one gating of the step's plots against its aircraft.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.assessment.figures import performance
from service.assessment.params import AssessmentParams
from service.assessment.radar import FIELDS, RadarAssessment
from service.assessment.references import ReferenceHistory
from service.geo import Site, geodetic_to_ecef

FloatArray = NDArray[np.float64]
#: The contract's names of the reference kinds.
REFERENCE_NAMES = {"adsb": "ads-b", "ais": "ais"}


@dataclass(frozen=True)
class PerformanceView:
    """The figures of the latest step, for readers on other threads (never changed)."""

    params: AssessmentParams
    figures: Mapping[str, dict[str, Any]]

    def of(self, radar_id: str) -> dict[str, Any]:
        """The radar's figures (all None before its first assessed plot)."""
        got = self.figures.get(radar_id)
        if got is not None:
            return got
        return performance(
            radar_id, None, self.params.window_s, [], 0, np.zeros(len(FIELDS)), None, self.params
        )


class Assessment:
    """Every radar's :class:`RadarAssessment`, the reference history and the schedule."""

    def __init__(self, params: AssessmentParams | None = None) -> None:
        self.params = p = params or AssessmentParams()
        self.references = ReferenceHistory(p.history_s, p.max_report_gap_s)
        self.kinds: dict[str, str] = {}  # reference source -> kind
        self.assessments: dict[str, RadarAssessment] = {}
        self.sites: dict[str, Site] = {}
        #: radar -> reference id -> (data time it was first and last paired, reference kind)
        self.paired: dict[str, dict[str, tuple[float, float, str]]] = {}
        self.clock_s = -math.inf
        self.next_step: int | None = None
        self.view = PerformanceView(p, {})

    @property
    def active(self) -> bool:
        return bool(self.kinds)

    # -- input, in release order ---------------------------------------------------------
    def plots(
        self,
        radar_id: str,
        site: Site,
        time_s: FloatArray,
        range_m: FloatArray,
        azimuth_deg: FloatArray,
        mode_3a: NDArray[np.object_],
        flight_level: FloatArray,
        clock_s: float,
    ) -> None:
        """A radar's released batch (held once there is a reference source, for ``lag_s +
        step_s`` at most: whether the radar has reference aircraft is known at the step)."""
        self._clock(clock_s)
        if not self.active:
            return
        self.sites[radar_id] = site
        radar = self.assessments.get(radar_id)
        if radar is None:
            radar = self.assessments[radar_id] = RadarAssessment(radar_id, self.params)
        good = np.isfinite(time_s) & np.isfinite(range_m) & np.isfinite(azimuth_deg)
        radar.add_plots((time_s[good], range_m[good], azimuth_deg[good], mode_3a[good], flight_level[good]))

    def reference(
        self,
        source_id: str,
        kind: str,
        time_s: FloatArray,
        ids: NDArray[np.str_],
        latitude_deg: FloatArray,
        longitude_deg: FloatArray,
        altitude_m: FloatArray,
        mode_3a: NDArray[np.object_],
        flight_level: FloatArray,
        clock_s: float,
    ) -> None:
        """A reference source's released batch (reports without a height are left out: a
        radar sees an aircraft at a slant range its height is part of)."""
        self._clock(clock_s)
        self.kinds[source_id] = kind
        has = np.isfinite(altitude_m)
        ecef = geodetic_to_ecef(latitude_deg[has], longitude_deg[has], altitude_m[has]).reshape(-1, 3)
        self.references.add(time_s[has], ids[has], ecef, flight_level[has], mode_3a[has])

    def pairs(self, radar_id: str, source_id: str, reference_ids: list[str], time_s: float) -> None:
        """The reference tracks confirmed in pairs with ``radar_id``'s tracks at ``time_s``."""
        kind = self.kinds.get(source_id)
        if kind is None or not reference_ids:
            return
        book = self.paired.setdefault(radar_id, {})
        for rid in reference_ids:
            held = book.get(rid)
            book[rid] = (time_s if held is None else min(held[0], time_s), time_s, kind)

    def forget(self, source_id: str) -> None:
        self.assessments.pop(source_id, None)
        self.sites.pop(source_id, None)
        self.paired.pop(source_id, None)
        self.kinds.pop(source_id, None)
        if source_id in self.view.figures:
            self.view = PerformanceView(
                self.params, {k: v for k, v in self.view.figures.items() if k != source_id}
            )

    # -- the schedule --------------------------------------------------------------------
    def _clock(self, clock_s: float) -> None:
        if math.isfinite(clock_s):
            self.clock_s = max(self.clock_s, clock_s)

    def advance(self, answered_s: float | None) -> bool:
        """Run every step whose time data time and the correlation (``answered_s``: the data
        time through which the pairs are known) have both reached.  True if figures changed."""
        if not self.active or not math.isfinite(self.clock_s):
            return False
        p = self.params
        # (answered_s None: the caller has no correlation to wait for, e.g. at the end)
        through = self.clock_s if answered_s is None else min(self.clock_s, answered_s)
        if not math.isfinite(through):
            return False
        last = math.floor(through / p.step_s)
        if self.next_step is None:
            self.next_step = last
        if last - self.next_step > (p.window_s + p.history_s) / p.step_s:  # a jump in data time
            self.next_step = last - math.ceil((p.window_s + p.history_s) / p.step_s)
        ran = False
        while self.next_step <= last:
            self._step(self.next_step)
            self.next_step += 1
            ran = True
        if ran:
            self._publish(self.next_step - 1)
        return ran

    def finish(self) -> bool:
        """The end of the input (a replay's end): assess everything held."""
        if not self.active or not math.isfinite(self.clock_s):
            return False
        self.clock_s += self.params.lag_s + self.params.step_s
        return self.advance(None)

    def _step(self, step: int) -> None:
        p = self.params
        cutoff = step * p.step_s - p.lag_s
        self.references.index(step * p.step_s)
        for radar_id, radar in self.assessments.items():
            book = self.paired.get(radar_id, {})
            stale = [a for a, (_, last, _) in book.items() if last < cutoff - p.window_s]
            for a in stale:
                del book[a]
            # the aircraft paired by the step's data time: the same whenever the answers came
            aircraft = sorted(a for a, (first, _, _) in book.items() if first <= step * p.step_s)
            radar.step(step, cutoff, self.sites[radar_id], self.references, aircraft)
            radar.forget_before(cutoff)

    def _publish(self, step: int) -> None:
        p = self.params
        cutoff = step * p.step_s - p.lag_s
        figures = {}
        for radar_id, radar in sorted(self.assessments.items()):
            sums = radar.window_sums(step)
            kinds = sorted({REFERENCE_NAMES.get(k, k) for _, _, k in self.paired.get(radar_id, {}).values()})
            aircraft = sum(1 for t in radar.last_seen.values() if t >= cutoff - p.window_s)
            median = radar.median_m(cutoff - p.window_s, sums)
            figures[radar_id] = performance(radar_id, cutoff, p.window_s, kinds, aircraft, sums, median, p)
        self.view = PerformanceView(p, figures)

    def whole_run(self, radar_id: str, time_s: float | None, span_s: float) -> dict[str, Any]:
        """The radar's figures over everything assessed (``topofusion assess``); the median from
        the whole run's histogram of compensated errors."""
        from service.assessment.radar import HORIZONTAL_ERROR_EDGES

        radar = self.assessments[radar_id]
        hist = radar.hist_horizontal
        n = int(hist.sum()) + radar.hist_horizontal_over
        median = None
        if n:
            cum = np.cumsum(hist)
            k = int(np.searchsorted(cum, n / 2.0))
            median = float(HORIZONTAL_ERROR_EDGES[min(k, hist.size - 1)] + 2.5) if k < hist.size else None
        kinds = sorted({REFERENCE_NAMES.get(k, k) for k in self.kinds.values()})
        aircraft = len(radar.all_aircraft)
        return performance(radar_id, time_s, span_s, kinds, aircraft, radar.total, median, self.params)
