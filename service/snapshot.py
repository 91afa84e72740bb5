"""Immutable views of the engine's state, and their contract JSON (TrackBatch, PairSet, ...)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.geo import ecef_to_geodetic
from service.tracking.base import TrackTable


def track_batch(radar_id: str, time_s: float, tracks: TrackTable, status: str = "all") -> dict[str, Any]:
    """The contract's ``TrackBatch`` for a radar's tracks (``status``: confirmed, tentative, all)."""
    if status == "confirmed":
        tracks = tracks.take(tracks.confirmed)
    elif status == "tentative":
        tracks = tracks.take(~tracks.confirmed)
    lat, lon, alt = ecef_to_geodetic(tracks.position_ecef_m)
    pos = tracks.position_ecef_m.tolist()
    vel = tracks.velocity_ecef_mps.tolist()
    rows = [
        {
            "track_id": str(tracks.track_id[i]),
            "status": "confirmed" if tracks.confirmed[i] else "tentative",
            "time_s": float(tracks.time_s[i]),
            "latitude_deg": float(lat[i]),
            "longitude_deg": float(lon[i]),
            "altitude_m": float(alt[i]),
            "position_ecef_m": pos[i],
            "velocity_ecef_mps": vel[i],
            "plots": int(tracks.plots[i]),
            "truth_id": tracks.truth_id[i],
        }
        for i in range(len(tracks))
    ]
    return {"radar_id": radar_id, "time_s": time_s, "tracks": rows}


def finite_or_none(x: float) -> float | None:
    """JSON has no NaN: a quantity the decision did not produce is ``null``."""
    return float(x) if np.isfinite(x) else None


def pair_set(
    radar_a: str, radar_b: str, time_s: float, method: str, pairs: Iterable[Any], swap: bool = False
) -> dict[str, Any]:
    """The contract's ``PairSet``; ``swap`` when the correlator's A side is the key's B side."""
    rows = []
    for p in pairs:
        a, b = (p.track_b, p.track_a) if swap else (p.track_a, p.track_b)
        rows.append(
            {
                "track_a": a,
                "track_b": b,
                "status": p.status,
                "score": float(p.score),
                "statistic": finite_or_none(p.statistic),
                "rotation_weight": finite_or_none(p.rotation_weight),
                "scale": finite_or_none(p.scale),
                "neighbors": int(p.neighbors),
                "hits": int(p.hits),
                "first_time_s": float(p.first_time_s),
                "last_time_s": float(p.last_time_s),
            }
        )
    if swap:
        rows.sort(key=lambda r: (r["track_a"], r["track_b"]))
    return {"radar_a": radar_a, "radar_b": radar_b, "time_s": time_s, "method": method, "pairs": rows}


def bias_dict(b: Any) -> dict[str, Any] | None:
    values = (b.range_bias_m, b.azimuth_bias_deg, b.elevation_bias_deg)
    if not all(np.isfinite(v) for v in values):
        return None
    return {
        "radar_id": b.radar_id,
        "range_bias_m": float(b.range_bias_m),
        "azimuth_bias_deg": float(b.azimuth_bias_deg),
        "elevation_bias_deg": float(b.elevation_bias_deg),
        "pairs_used": int(b.pairs_used),
        "time_s": float(b.time_s),
    }


def _filter_status(items: list[dict[str, Any]], status: str) -> list[dict[str, Any]]:
    return items if status == "all" else [p for p in items if p["status"] == status]


@dataclass(frozen=True)
class Snapshot:
    """Immutable state for readers (HTTP handlers, queryables) on other threads."""

    tracks: dict[str, tuple[float, TrackTable]]
    radar_rows: list[dict[str, Any]]
    pair_sets_all: list[dict[str, Any]]
    biases_all: list[dict[str, Any]]
    correlation: dict[str, Any]
    rejected: dict[str, int]
    method: str
    prefix: str

    def radar_ids(self) -> list[str]:
        return [r["radar_id"] for r in self.radar_rows]

    def track_batch(self, radar_id: str, status: str = "confirmed") -> dict[str, Any] | None:
        if radar_id not in self.tracks:
            return None
        time_s, table = self.tracks[radar_id]
        return track_batch(radar_id, time_s, table, status)

    def track_batches(self, status: str = "all") -> list[dict[str, Any]]:
        return [b for rid in self.tracks if (b := self.track_batch(rid, status)) is not None]

    def pair_sets(
        self, radar_a: str | None = None, radar_b: str | None = None, status: str = "confirmed"
    ) -> list[dict[str, Any]]:
        """Pair sets involving both given radars (either order), pairs filtered by ``status``."""
        wanted = {x for x in (radar_a, radar_b) if x is not None}
        return [
            {**ps, "pairs": _filter_status(ps["pairs"], status)}
            for ps in self.pair_sets_all
            if wanted <= {ps["radar_a"], ps["radar_b"]}
        ]

    def biases(self) -> list[dict[str, Any]]:
        return list(self.biases_all)

    def status_core(self) -> dict[str, Any]:
        pairs = [p for ps in self.pair_sets_all for p in ps["pairs"]]
        return {
            "method": self.method,
            "prefix": self.prefix,
            "radars": [{k: v for k, v in r.items() if k != "site"} for r in self.radar_rows],
            "pairs_confirmed": sum(p["status"] == "confirmed" for p in pairs),
            "pairs_tentative": sum(p["status"] == "tentative" for p in pairs),
            "correlation": self.correlation,
            "rejected": self.rejected,
        }

    def status(self) -> dict[str, Any]:
        """Status without process-level fields (the node adds uptime, zenoh and queue)."""
        return {"uptime_s": 0.0, "zenoh": {"mode": "none", "listen": [], "connect": []}, **self.status_core()}

    def radars(self) -> list[dict[str, Any]]:
        keys = ("batches", "plots", "rejected", "lost_batches", "last_time_s")
        return [{**r["site"], **{k: r[k] for k in keys}} for r in self.radar_rows]
