"""The JSON of every output payload, built fast from columns (``TrackBatch``, ``PairSet``, ...).

Rows are built from ``tolist()`` columns and encoded with orjson rather than through the
pydantic models: a national network publishes thousands of tracks a second, and the models
cost ten times as much.  The models (:mod:`service.wire.models`) stay the definition: a test
validates every payload the engine publishes against them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson
from numpy.typing import NDArray

from service.wire.vocabulary import PAIR_BASES


def encode(obj: object) -> bytes:
    """Compact JSON for the wire (orjson: about 10x the standard library on these payloads).

    Every float the service publishes is finite or ``None`` by construction (NaN means "not
    produced" and is mapped to ``None`` where it is built).  Numeric numpy arrays are written
    as nested lists directly (floats in their shortest round-trip form, as Python's own).
    """
    return orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY)


def nullable(x: NDArray[np.float64]) -> list[float | None]:
    """Floats as a list, non-finite entries as ``None`` (JSON has no NaN)."""
    out: list[Any] = np.asarray(x, dtype=float).tolist()
    bad = np.flatnonzero(~np.isfinite(x))
    for i in bad.tolist():
        out[i] = None
    return out


def track_rows(c: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """``TrackBatch.tracks`` from a radar's track columns (``track_id``, ``confirmed``,
    ``time_s``, ``latitude_deg``, ``longitude_deg``, ``altitude_m``, ``position_ecef_m``,
    ``velocity_ecef_mps``, ``plots``, ``truth_id``, ``mode_3a``, ``mode_s``, ``quality``: NaN
    for null)."""
    state = np.where(c["confirmed"], "confirmed", "tentative").tolist()
    return [
        {
            "track_id": tid,
            "status": st,
            "time_s": t,
            "latitude_deg": la,
            "longitude_deg": lo,
            "altitude_m": al,
            "position_ecef_m": p,
            "velocity_ecef_mps": v,
            "plots": n,
            "truth_id": truth,
            "mode_3a": m3a,
            "mode_s": ms,
            "quality": q,
        }
        for tid, st, t, la, lo, al, p, v, n, truth, m3a, ms, q in zip(
            c["track_id"].tolist(),
            state,
            c["time_s"].tolist(),
            c["latitude_deg"].tolist(),
            c["longitude_deg"].tolist(),
            c["altitude_m"].tolist(),
            c["position_ecef_m"].tolist(),
            c["velocity_ecef_mps"].tolist(),
            c["plots"].tolist(),
            c["truth_id"].tolist(),
            c["mode_3a"].tolist(),
            c["mode_s"].tolist(),
            nullable(c["quality"]),
            strict=True,
        )
    ]


def _finite_or_none(v: float | None) -> float | None:
    return float(v) if v is not None and np.isfinite(v) else None


def bias_dict(b: Any) -> dict[str, Any] | None:
    """``BiasEstimate`` of a radar's bias (``RadarBias``); None without a finite estimate."""
    values = (b.range_bias_m, b.azimuth_bias_deg, b.elevation_bias_deg)
    if not all(np.isfinite(v) for v in values):
        return None
    # a 1-sigma that is not finite is null ("not known"), the estimate still stands
    sigma_names = ("range_bias_sigma_m", "azimuth_bias_sigma_deg", "elevation_bias_sigma_deg")
    sigmas = {k: float(v) if np.isfinite(v := getattr(b, k)) else None for k in sigma_names}
    # range gain and time bias: null where not estimated (None) or not finite
    model_names = ("range_gain_ppm", "range_gain_sigma_ppm", "time_bias_s", "time_bias_sigma_s")
    model = {k: _finite_or_none(getattr(b, k, None)) for k in model_names}
    return {
        "radar_id": b.radar_id,
        "range_bias_m": float(b.range_bias_m),
        "azimuth_bias_deg": float(b.azimuth_bias_deg),
        "elevation_bias_deg": float(b.elevation_bias_deg),
        "pairs_used": int(b.pairs_used),
        "time_s": float(b.time_s),
        **sigmas,
        **model,
    }


_PAIR_FLOATS = ("statistic", "rotation_weight", "scale")


#: ``Pair`` fields that are null when the decision did not produce them.
PAIR_NULLABLE = ("statistic", "rotation_weight", "scale")


def pair_rows(c: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """``PairSet.pairs`` from a pair book's columns (``track_a``, ``track_b``, ``confirmed``,
    ``score``, the nullable floats, ``neighbors``, ``hits``, ``first_time_s``, ``last_time_s``,
    ``basis``: the codes of ``PAIR_BASES``, -1 for none; ``held``)."""
    state = np.where(c["confirmed"], "confirmed", "tentative").tolist()
    return [
        {
            "track_a": a,
            "track_b": b,
            "status": st,
            "score": sc,
            "statistic": stat,
            "rotation_weight": rw,
            "scale": scale,
            "neighbors": nb,
            "hits": h,
            "first_time_s": t0,
            "last_time_s": t1,
            "basis": PAIR_BASES[bs] if bs >= 0 else None,
            "held": hd,
        }
        for a, b, st, sc, stat, rw, scale, nb, h, t0, t1, bs, hd in zip(
            c["track_a"].tolist(),
            c["track_b"].tolist(),
            state,
            c["score"].tolist(),
            *(nullable(c[k]) for k in PAIR_NULLABLE),
            c["neighbors"].tolist(),
            c["hits"].tolist(),
            c["first_time_s"].tolist(),
            c["last_time_s"].tolist(),
            c["basis"].tolist(),
            c["held"].tolist(),
            strict=True,
        )
    ]


#: The longest ``Rejection.detail`` (characters): the contract's "a few hundred"; a detail that
#: quotes a hostile input (a 10 000-character id) is cut there and ends with an ellipsis.
MAX_DETAIL_CHARS = 300


def bounded(text: str, most: int = MAX_DETAIL_CHARS) -> str:
    """``text`` cut to ``most`` characters, the last an ellipsis where it was cut."""
    return text if len(text) <= most else text[: most - 1] + "\u2026"


def rejection(key: str, source_id: str | None, reason: str, detail: str, time_s: float) -> dict[str, Any]:
    """The contract's ``Rejection`` (``detail`` at most :data:`MAX_DETAIL_CHARS`)."""
    detail = bounded(detail)
    return {"key": key, "radar_id": source_id, "reason": reason, "detail": detail, "time_s": time_s}
