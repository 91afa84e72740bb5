"""Live radar performance against bias-free references (contract §5.3): numpy only, no I/O.

:class:`Assessment` takes each radar's plots, the references' reports and the radar-reference
pairs in release order and keeps, per radar, a sliding window of detection, position and
Mode 3/A / Mode C figures (:mod:`.radar` says how each is measured), brought up to date on a
data-time schedule.  docs/assessment.md describes the method and its bounds.
"""

from service.assessment.assessor import Assessment, PerformanceView
from service.assessment.params import AssessmentParams, Requirements

__all__ = ["Assessment", "AssessmentParams", "PerformanceView", "Requirements"]
