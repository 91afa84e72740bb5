"""A radar's figures (contract §5.3 ``RadarPerformance``) from the sums of its window."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.assessment.params import AssessmentParams
from service.assessment.radar import F

FloatArray = NDArray[np.float64]


def _round(x: float | None, digits: int) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), digits)


def _rate(checked: float, correct: float) -> dict[str, Any]:
    c = int(checked)
    return {"checked": c, "correct": int(correct), "rate": _round(correct / c, 4) if c else None}


def _verdict(value: float | None, least: float) -> bool | None:
    return None if value is None else bool(value >= least)


def performance(
    radar_id: str,
    time_s: float | None,
    window_s: float,
    references: list[str],
    aircraft: int,
    sums: FloatArray,
    median_m: float | None,
    params: AssessmentParams,
) -> dict[str, Any]:
    """The ``RadarPerformance`` of one radar: every figure without data is None."""
    expected, detected = int(sums[F["expected"]]), int(sums[F["detected"]])
    pd = detected / expected if expected else None
    pd_sigma = math.sqrt(pd * (1.0 - pd) / expected) if pd is not None else None
    n = int(sums[F["plots"]])
    rms = rms_unc = range_rms = az_rms = None
    if n >= 2:
        rms_unc = math.sqrt((sums[F["s_erho2"]] + sums[F["s_rea2"]]) / n)
        ss_r = sums[F["s_erho2"]] - sums[F["s_kerho"]] ** 2 / sums[F["s_k2"]] if sums[F["s_k2"]] > 0 else 0.0
        ss_a = sums[F["s_rea2"]] - sums[F["s_rea"]] ** 2 / sums[F["s_r2"]] if sums[F["s_r2"]] > 0 else 0.0
        rms = math.sqrt(max(ss_r + ss_a, 0.0) / n)
        range_rms = math.sqrt(max(sums[F["s_er2"]] / n - (sums[F["s_er"]] / n) ** 2, 0.0))
        az_rms = math.degrees(math.sqrt(max(sums[F["s_ea2"]] / n - (sums[F["s_ea"]] / n) ** 2, 0.0)))
    m3a = _rate(sums[F["m3a_checked"]], sums[F["m3a_correct"]])
    mc = _rate(sums[F["mc_checked"]], sums[F["mc_correct"]])
    req = params.requirements
    return {
        "radar_id": radar_id,
        "time_s": time_s,
        "window_s": window_s,
        "references": references,
        "aircraft": aircraft,
        "detection": {
            "pd": _round(pd, 4),
            "pd_sigma": _round(pd_sigma, 4),
            "expected": expected,
            "detected": detected,
        },
        "position": {
            "rms_m": _round(rms, 1),
            "median_m": _round(median_m, 1) if n >= 2 else None,
            "rms_uncorrected_m": _round(rms_unc, 1),
            "range_rms_m": _round(range_rms, 1),
            "azimuth_rms_deg": _round(az_rms, 4),
            "plots": n,
        },
        "mode_3a": m3a,
        "mode_c": mc,
        "requirements": {"pd_min": req.pd_min, "mode_3a_min": req.mode_3a_min, "mode_c_min": req.mode_c_min},
        "verdict": {
            "pd": _verdict(pd, req.pd_min),
            "mode_3a": _verdict(m3a["rate"], req.mode_3a_min),
            "mode_c": _verdict(mc["rate"], req.mode_c_min),
        },
    }
