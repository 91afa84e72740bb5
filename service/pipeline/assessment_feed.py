"""What the pipeline has, handed to the performance assessment (:mod:`service.assessment`).

The engine calls this at three points of the one path, in release order: a radar's released
plot batch (after tracking), a reference source's released batch (before correlation), and
each pair set the correlation answered (its confirmed radar-reference pairs).  After each
round of answers :meth:`AssessmentFeed.advance` runs the assessment steps that data time and
the correlation have both reached.  A failure here costs the assessment, never the engine: it
is counted (``failures``) and the input goes on.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from service.assessment import Assessment, AssessmentParams, PerformanceView
from service.geo import Site
from service.pipeline.decode import reference_identity
from service.wire.models import AdsbBatch, AisBatch

log = logging.getLogger(__name__)


class AssessmentFeed:
    def __init__(self, params: AssessmentParams | None = None) -> None:
        self.assessment = Assessment(params)
        self.failures = 0

    @property
    def view(self) -> PerformanceView:
        return self.assessment.view

    def _failed(self, exc: Exception) -> None:
        self.failures += 1
        if self.failures == 1 or self.failures % 1000 == 0:
            log.warning(
                "performance assessment failed (%d so far): %s: %s", self.failures, type(exc).__name__, exc
            )

    def plots(self, radar_id: str, site: Site, plots: Any, clock_s: float) -> None:
        if not self.assessment.active:
            return  # no reference source: nothing to do
        try:
            n = len(plots)
            fl = getattr(plots, "flight_level", None)
            self.assessment.plots(
                radar_id,
                site,
                plots.time_s,
                plots.range_m,
                plots.azimuth_deg,
                plots.mode_3a,
                np.full(n, np.nan) if fl is None else fl,
                clock_s,
            )
        except Exception as exc:  # the assessment must never cost the engine a batch
            self._failed(exc)

    def reference(
        self,
        source_id: str,
        kind: str,
        columns: tuple[np.ndarray, ...],
        batch: AisBatch | AdsbBatch,
        clock_s: float,
    ) -> None:
        """A reference batch: its ``kind`` (``ais``, ``adsb``) and ``columns`` as the engine
        decoded them for the correlation (``decode.reference_columns``), and its identity."""
        try:
            t, ids, lat, lon, alt = columns
            m3a, fl = reference_identity(batch)
            self.assessment.reference(source_id, kind, t, ids, lat, lon, alt, m3a, fl, clock_s)
        except Exception as exc:
            self._failed(exc)

    def pairs(
        self, updated: Iterable[tuple[tuple[str, str], Any]], reference_kinds: Mapping[str, str]
    ) -> None:
        """The confirmed radar-reference pairs of updated pair sets (``(key, view)``; the
        others are not the assessment's)."""
        for key, view in updated:
            side = 1 if key[1] in reference_kinds else 0 if key[0] in reference_kinds else None
            if side is None or key[1 - side] in reference_kinds or not self.assessment.active:
                continue
            try:
                cols = view.columns
                ids = cols["track_b" if side == 1 else "track_a"][cols["confirmed"]]
                self.assessment.pairs(key[1 - side], key[side], [str(i) for i in ids], float(view.time_s))
            except Exception as exc:
                self._failed(exc)

    def advance(self, answered_s: float | None) -> bool:
        """``answered_s``: the data time through which the correlation has answered (None:
        nothing yet).  True if the figures changed."""
        try:
            return self.assessment.advance(-math.inf if answered_s is None else answered_s)
        except Exception as exc:
            self._failed(exc)
            return False

    def finish(self) -> None:
        try:
            self.assessment.finish()
        except Exception as exc:
            self._failed(exc)

    def forget(self, source_id: str) -> None:
        self.assessment.forget(source_id)
