"""Bias-free reference tracks from cooperative position reports (AIS, ADS-B), pure numpy.

A reference source reports the positions its targets determine themselves (GNSS): an AIS
receiver's vessels by MMSI, an ADS-B receiver's aircraft by ICAO 24-bit address.  Each id is
one target; its recent reports (by data time) form a reference track that the radars are
correlated against (method ``cfar``) and registered to (``/biases``), which makes their bias
estimates absolute.  The two kinds share this one path and differ only in their parameters
(:class:`ReferenceKindParams`): vessels are at sea level and report every few seconds to
minutes, aircraft report their geometric height (when they do) about twice a second.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from service.geo import ecef_to_geodetic, geodetic_to_ecef
from service.tracking.base import TrackTable

#: The kinds of reference source (the contract's ``ais`` and ``adsb`` inputs).
ReferenceKind = Literal["ais", "adsb"]


@dataclass(frozen=True)
class ReferenceKindParams:
    """How one kind of report becomes a reference track."""

    #: 1-sigma horizontal position error of a report (m).
    position_sigma_m: float
    #: 1-sigma vertical position error of a report (m).
    height_sigma_m: float
    #: 1-sigma error of the velocity taken between two reports (m/s).
    velocity_sigma_mps: float
    #: The velocity is taken between the latest report and the oldest one at most this long
    #: before it (s), or the one just before when there is none that recent: over one report
    #: interval of ADS-B (0.5 s) a 15 m position error is a 40 m/s velocity error.
    velocity_baseline_s: float
    #: Two reports further apart than this (s) give no velocity (the target is taken as still).
    max_velocity_gap_s: float


@dataclass(frozen=True)
class ReferenceParams:
    #: Reports older than this (data seconds) before the newest are forgotten; an id with no
    #: report that recent is not offered as a reference track.
    max_age_s: float = 180.0
    #: AIS: decoded GNSS positions of vessels at sea level, reported every 2 s to 3 min.
    ais: ReferenceKindParams = field(
        default_factory=lambda: ReferenceKindParams(
            position_sigma_m=10.0,
            height_sigma_m=10.0,
            velocity_sigma_mps=1.0,
            velocity_baseline_s=0.0,
            max_velocity_gap_s=120.0,
        )
    )
    #: ADS-B: GNSS positions (NACp 8 or better: 95 % within 93 m, typically far better) and
    #: geometric heights, about two reports a second.
    adsb: ReferenceKindParams = field(
        default_factory=lambda: ReferenceKindParams(
            position_sigma_m=20.0,
            height_sigma_m=30.0,
            velocity_sigma_mps=4.0,
            velocity_baseline_s=10.0,
            max_velocity_gap_s=30.0,
        )
    )

    def of(self, kind: ReferenceKind) -> ReferenceKindParams:
        return self.ais if kind == "ais" else self.adsb


class ReferenceTracks:
    """One reference source's reports by id, kept over the last ``max_age_s`` of data time."""

    def __init__(self, params: ReferenceParams | None = None, kind: ReferenceKind = "ais") -> None:
        self.params = params or ReferenceParams()
        self.kind = kind
        self.time_s = np.empty(0)
        self.ids = np.empty(0, dtype=str)
        self.ecef = np.empty((0, 3))
        self.newest_time_s = -np.inf

    def __len__(self) -> int:
        return int(self.time_s.size)

    def add(
        self,
        time_s: NDArray[np.float64],
        ids: NDArray[np.str_],
        lat_deg: NDArray[np.float64],
        lon_deg: NDArray[np.float64],
        altitude_m: NDArray[np.float64],
        batch_time_s: float,
    ) -> None:
        """Absorb one batch of reports and forget the too old ones.

        ``altitude_m`` is the height above the WGS-84 ellipsoid, NaN where a report gave none:
        such a report takes the latest height its id reported (before it, here or in an
        earlier batch); an id with no height yet is left out, since a radar sees an aircraft at
        a slant range its height is part of.
        """
        ids = np.asarray(ids).astype(str)
        altitude_m = np.asarray(altitude_m, dtype=float)
        if np.isnan(altitude_m).any():
            altitude_m = self._fill_heights(time_s, ids, altitude_m)
            known = ~np.isnan(altitude_m)
            time_s, ids, altitude_m = np.asarray(time_s)[known], ids[known], altitude_m[known]
            lat_deg, lon_deg = np.asarray(lat_deg)[known], np.asarray(lon_deg)[known]
        ecef = geodetic_to_ecef(lat_deg, lon_deg, altitude_m).reshape(-1, 3)
        self.time_s = np.concatenate([self.time_s, time_s])
        self.ids = np.concatenate([self.ids.astype(str), ids])
        self.ecef = np.concatenate([self.ecef, ecef])
        self.newest_time_s = max(self.newest_time_s, batch_time_s)
        keep = self.time_s >= self.newest_time_s - self.params.max_age_s
        self.time_s, self.ids, self.ecef = self.time_s[keep], self.ids[keep], self.ecef[keep]

    def _fill_heights(
        self, time_s: NDArray[np.float64], ids: NDArray[np.str_], altitude_m: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Each NaN height replaced by the latest earlier height of the same id (the kept
        reports' heights first, then this batch's in time order), NaN where there is none."""
        old_alt = ecef_to_geodetic(self.ecef)[2] if len(self) else np.empty(0)
        t = np.concatenate([self.time_s, np.asarray(time_s, dtype=float)])
        who = np.concatenate([self.ids.astype(str), ids])
        alt = np.concatenate([np.atleast_1d(old_alt), altitude_m])
        is_old = np.r_[np.ones(len(self), dtype=bool), np.zeros(ids.shape[0], dtype=bool)]
        order = np.lexsort((~is_old, t, who))  # by id, then time (kept reports before new)
        w, a = who[order], alt[order]
        idx = np.where(~np.isnan(a), np.arange(a.shape[0]), -1)
        np.maximum.accumulate(idx, out=idx)  # the latest known height at or before each row
        start = np.r_[True, w[1:] != w[:-1]]
        group_start = np.maximum.accumulate(np.where(start, np.arange(w.shape[0]), 0))
        ok = idx >= group_start  # the height is this id's own
        filled = np.full(a.shape[0], np.nan)
        filled[ok] = a[idx[ok]]
        out = np.empty_like(filled)
        out[order] = filled
        return out[len(self) :]

    def table(self, time_s: float) -> TrackTable:
        """One confirmed track per id: its latest report, velocity over the kind's baseline."""
        p, k = self.params, self.params.of(self.kind)
        recent = self.time_s >= time_s - p.max_age_s
        if not recent.any():
            return TrackTable.empty()
        t, ids, pos = self.time_s[recent], self.ids[recent], self.ecef[recent]
        order = np.lexsort((t, ids))  # by id, then time
        t, ids, pos = t[order], ids[order], pos[order]
        last = np.flatnonzero(np.r_[ids[1:] != ids[:-1], True])
        first = np.r_[0, last[:-1] + 1]
        # The oldest report within the baseline of the latest, else the one just before it.
        code = np.repeat(np.arange(last.size), last - first + 1)
        span = float(t[-1] - t.min()) + 1.0 if t.size else 1.0
        key = code * (2.0 * span) + (t - t.min())  # one sorted axis: id blocks, time inside
        base = np.maximum(np.searchsorted(key, key[last] - k.velocity_baseline_s), first)
        prev = np.maximum(np.minimum(base, last - 1), 0)
        has_prev = last > first
        dt = np.where(has_prev, t[last] - t[prev], 0.0)
        usable = has_prev & (dt > 0) & (dt <= k.max_velocity_gap_s)
        vel = np.zeros((last.size, 3))
        vel[usable] = (pos[last[usable]] - pos[prev[usable]]) / dt[usable, None]
        n = last.size
        counts = last - first + 1
        cov = np.zeros((n, 6, 6))
        up = pos[last] / np.linalg.norm(pos[last], axis=1, keepdims=True)  # geocentric up, near enough
        horizontal = np.eye(3) - up[:, :, None] * up[:, None, :]
        cov[:, :3, :3] = k.position_sigma_m**2 * horizontal + k.height_sigma_m**2 * (
            up[:, :, None] * up[:, None, :]
        )
        cov[:, 3:, 3:] = np.eye(3) * k.velocity_sigma_mps**2
        return TrackTable(
            track_id=ids[last].astype(str),
            confirmed=np.ones(n, dtype=bool),
            time_s=t[last],
            position_ecef_m=pos[last],
            velocity_ecef_mps=vel,
            covariance=cov,
            plots=counts.astype(np.int64),
            truth_id=np.empty(n, dtype=object),
            mode_s=ids[last].astype(object) if self.kind == "adsb" else None,  # type: ignore[arg-type]
        )
