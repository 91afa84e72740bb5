"""The read model's views: immutable state for readers, and their contract JSON built on demand.

A snapshot holds references to immutable columns (a radar's :class:`TrackTable`, a copy of a
pair book's columns), never JSON: a ``TrackBatch`` or ``PairSet`` is built only when somebody
reads it (an HTTP handler, a queryable, a publisher with subscribers) and then kept.  Taking a
snapshot therefore costs in proportion to the number of radars and pairs, not tracks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import orjson
from numpy.typing import NDArray

from service.geo import ecef_to_geodetic
from service.tracking.base import TrackTable


def encode(obj: object) -> bytes:
    """Compact JSON for the wire (orjson: about 10x the standard library on these payloads).

    Every float the service publishes is finite or ``None`` by construction (NaN means "not
    produced" and is mapped to ``None`` where it is built).
    """
    return orjson.dumps(obj)


def _nullable(x: NDArray[np.float64]) -> list[float | None]:
    """Floats as a list, non-finite entries as ``None`` (JSON has no NaN)."""
    out: list[Any] = np.asarray(x, dtype=float).tolist()
    bad = np.flatnonzero(~np.isfinite(x))
    for i in bad.tolist():
        out[i] = None
    return out


def track_batch(radar_id: str, time_s: float, tracks: TrackTable, status: str = "all") -> dict[str, Any]:
    """The contract's ``TrackBatch`` for a radar's tracks (``status``: confirmed, tentative, all)."""
    if status == "confirmed":
        tracks = tracks.take(tracks.confirmed)
    elif status == "tentative":
        tracks = tracks.take(~tracks.confirmed)
    lat, lon, alt = ecef_to_geodetic(tracks.position_ecef_m)
    state = np.where(tracks.confirmed, "confirmed", "tentative").tolist()
    rows = [
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
        }
        for tid, st, t, la, lo, al, p, v, n, truth in zip(
            tracks.track_id.tolist(),
            state,
            tracks.time_s.tolist(),
            np.atleast_1d(lat).tolist(),
            np.atleast_1d(lon).tolist(),
            np.atleast_1d(alt).tolist(),
            tracks.position_ecef_m.tolist(),
            tracks.velocity_ecef_mps.tolist(),
            tracks.plots.tolist(),
            tracks.truth_id.tolist(),
            strict=True,
        )
    ]
    return {"radar_id": radar_id, "time_s": time_s, "tracks": rows}


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


_PAIR_FLOATS = ("statistic", "rotation_weight", "scale")


@dataclass(frozen=True)
class PairSetView:
    """One radar pair's book at one update: copied columns, the ``PairSet`` built when read."""

    radar_a: str
    radar_b: str
    time_s: float
    method: str
    columns: dict[str, np.ndarray]
    confirmed: int
    tentative: int
    _cache: dict[str, dict[str, Any]] = field(default_factory=dict, compare=False, repr=False)

    @staticmethod
    def of(key: tuple[str, str], corr: Any, time_s: float) -> PairSetView:
        """Capture ``corr``'s book (a :class:`~service.correlation.PairCorrelator`) for ``key``."""
        book = corr.book
        swap = corr.site_a.site_id != key[0]
        ta, tb = (book.track_b, book.track_a) if swap else (book.track_a, book.track_b)
        order = np.lexsort((tb, ta))
        cols = {
            "track_a": ta[order],
            "track_b": tb[order],
            "confirmed": book.confirmed[order],
            "score": book.score[order],
            "neighbors": book.neighbors[order],
            "hits": book.hits[order],
            **{k: v[order] for k, v in book.cols.items()},  # fancy indexing copies
        }
        n_conf = int(np.count_nonzero(cols["confirmed"]))
        return PairSetView(key[0], key[1], time_s, corr.method, cols, n_conf, len(order) - n_conf)

    def _rows(self) -> list[dict[str, Any]]:
        c = self.columns
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
            }
            for a, b, st, sc, stat, rw, scale, nb, h, t0, t1 in zip(
                c["track_a"].tolist(),
                c["track_b"].tolist(),
                state,
                c["score"].tolist(),
                *(_nullable(c[k]) for k in _PAIR_FLOATS),
                c["neighbors"].tolist(),
                c["hits"].tolist(),
                c["first_time_s"].tolist(),
                c["last_time_s"].tolist(),
                strict=True,
            )
        ]

    def body(self, status: str = "all") -> dict[str, Any]:
        """The contract's ``PairSet``, pairs filtered by ``status`` (built once per status)."""
        got = self._cache.get(status)
        if got is None:
            if "all" not in self._cache:
                self._cache["all"] = {
                    "radar_a": self.radar_a,
                    "radar_b": self.radar_b,
                    "time_s": self.time_s,
                    "method": self.method,
                    "pairs": self._rows(),
                }
            got = self._cache["all"]
            if status != "all":
                got = {**got, "pairs": [p for p in got["pairs"] if p["status"] == status]}
                self._cache[status] = got
        return got


@dataclass(frozen=True)
class RadarRow:
    """One radar's counters for ``/status`` and ``/radars``."""

    site: dict[str, Any]
    radar_id: str
    batches: int
    plots: int
    rejected: int
    lost_batches: int
    window_plots: int
    tracks_confirmed: int
    tracks_tentative: int
    last_time_s: float | None
    restarts: int = 0
    window_evicted: int = 0
    expired: bool = False

    _STATUS = (
        "radar_id",
        "batches",
        "plots",
        "rejected",
        "lost_batches",
        "window_plots",
        "tracks_confirmed",
        "tracks_tentative",
        "last_time_s",
        "restarts",
        "window_evicted",
        "expired",
    )

    def status(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self._STATUS}


@dataclass(frozen=True)
class Snapshot:
    """Immutable state for readers (HTTP handlers, queryables) on other threads."""

    tracks: dict[str, tuple[float, TrackTable]]
    radar_rows: list[RadarRow]
    pair_views: list[PairSetView]
    biases_all: list[dict[str, Any]]
    correlation: dict[str, Any]
    rejected: dict[str, int]
    method: str
    prefix: str
    _batches: dict[tuple[str, str], dict[str, Any]] = field(default_factory=dict, compare=False, repr=False)

    def track_batch(self, radar_id: str, status: str = "confirmed") -> dict[str, Any] | None:
        if radar_id not in self.tracks:
            return None
        got = self._batches.get((radar_id, status))
        if got is None:
            time_s, table = self.tracks[radar_id]
            got = self._batches[(radar_id, status)] = track_batch(radar_id, time_s, table, status)
        return got

    def track_batches(self, status: str = "all") -> list[dict[str, Any]]:
        return [b for rid in self.tracks if (b := self.track_batch(rid, status)) is not None]

    def pair_sets(
        self, radar_a: str | None = None, radar_b: str | None = None, status: str = "confirmed"
    ) -> list[dict[str, Any]]:
        """Pair sets involving both given radars (either order), pairs filtered by ``status``."""
        wanted = {x for x in (radar_a, radar_b) if x is not None}
        return [v.body(status) for v in self.pair_views if wanted <= {v.radar_a, v.radar_b}]

    def biases(self) -> list[dict[str, Any]]:
        return list(self.biases_all)

    def status_core(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "prefix": self.prefix,
            "radars": [r.status() for r in self.radar_rows],
            "pairs_confirmed": sum(v.confirmed for v in self.pair_views),
            "pairs_tentative": sum(v.tentative for v in self.pair_views),
            "correlation": self.correlation,
            "rejected": self.rejected,
        }

    def status(self) -> dict[str, Any]:
        """Status without process-level fields (the node adds uptime, zenoh and queue)."""
        return {"uptime_s": 0.0, "zenoh": {"mode": "none", "listen": [], "connect": []}, **self.status_core()}

    def radars(self) -> list[dict[str, Any]]:
        keys = ("batches", "plots", "rejected", "lost_batches", "last_time_s")
        return [{**r.site, **{k: getattr(r, k) for k in keys}} for r in self.radar_rows]
