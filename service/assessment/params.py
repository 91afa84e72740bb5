"""The parameters of the live radar performance assessment (contract §5.3), all in data time."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Requirements:
    """What a radar must reach (defaults: EUROCONTROL's, as COMPASS checks them)."""

    #: Detection probability at least this.
    pd_min: float = 0.97
    #: Share of correct Mode 3/A codes at least this.
    mode_3a_min: float = 0.98
    #: Share of correct Mode C (flight level within ``mode_c_tolerance_fl`` of the reference).
    mode_c_min: float = 0.96


@dataclass(frozen=True)
class AssessmentParams:
    """How each radar's plots are measured against the bias-free references paired with it."""

    #: The figures cover this much data time (s): the sliding window.
    window_s: float = 600.0
    #: The figures are brought up to date once per this much data time (s); also the width of
    #: one bin of the window (the window holds ``ceil(window_s / step_s)`` bins).
    step_s: float = 5.0
    #: A plot is assessed once data time is this far past it (s), so that the references have
    #: reported on both sides of it (ADS-B every 0.5-2 s in batches of a few seconds; AIS
    #: every 2-10 s under way): as long as ``max_report_gap_s``.
    lag_s: float = 12.0
    #: Reference reports are kept this long (s): at least ``max_gap_s + lag_s + step_s``.
    history_s: float = 80.0
    #: Two detections of an aircraft further apart than this (s) open a new stretch: the
    #: scans in between are not counted (it may have left the coverage).
    max_gap_s: float = 60.0
    #: Reference reports further apart than this (s) are not interpolated between.
    max_report_gap_s: float = 12.0
    #: A plot is an aircraft's when within this many sigmas of its reference position (radar
    #: random error, reference error and the uncertainty of the bias estimate).
    gate_sigma: float = 5.0
    #: 1-sigma of the bias before the window has estimated it (range m, azimuth deg).
    prior_range_bias_m: float = 1000.0
    prior_azimuth_bias_deg: float = 1.0
    #: Mode C is correct within this many flight levels of the reference's (2 FL = 200 ft).
    mode_c_tolerance_fl: float = 2.0
    #: Coverage cells (where the radar has detected a reference aircraft): range, azimuth and
    #: height steps, and the largest range and height held.
    coverage_range_m: float = 10_000.0
    coverage_azimuth_deg: float = 5.0
    coverage_height_m: float = 2_000.0
    coverage_max_range_m: float = 600_000.0
    coverage_max_height_m: float = 20_000.0
    #: The median error is taken over at most this many of the radar's latest plots.
    median_plots: int = 4096
    #: The requirements the verdict checks.
    requirements: Requirements = field(default_factory=Requirements)

    def __post_init__(self) -> None:
        if not (self.window_s > 0 and self.step_s > 0 and self.lag_s >= 0):
            raise ValueError("assessment: window_s and step_s must be > 0, lag_s >= 0")
        if self.history_s < self.max_gap_s + self.lag_s + self.step_s:
            raise ValueError("assessment: history_s must be at least max_gap_s + lag_s + step_s")
        if self.median_plots < 1:
            raise ValueError("assessment: median_plots must be >= 1")
