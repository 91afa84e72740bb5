"""Bias-free reference tracks from cooperative position reports (AIS), pure numpy.

Each MMSI is one vessel; its recent reports (by data time) form a reference track that the
radars are correlated against (method ``cfar``) and registered to (``/biases``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.geo import geodetic_to_ecef
from service.tracking.base import TrackTable


@dataclass(frozen=True)
class ReferenceParams:
    #: Reports older than this (data seconds) before the newest are forgotten; an MMSI with
    #: no report that recent is not offered as a reference track.
    max_age_s: float = 180.0
    #: 1-sigma horizontal position error of a report (m): decoded GNSS positions.
    position_sigma_m: float = 10.0
    #: 1-sigma velocity error from two reports (m/s).
    velocity_sigma_mps: float = 1.0
    #: Two reports further apart than this (s) give no velocity (the vessel is taken as still).
    max_velocity_gap_s: float = 120.0


class ReferenceTracks:
    """One AIS source's reports by MMSI, kept over the last ``max_age_s`` of data time."""

    def __init__(self, params: ReferenceParams | None = None) -> None:
        self.params = params or ReferenceParams()
        self.time_s = np.empty(0)
        self.mmsi = np.empty(0, dtype=str)
        self.ecef = np.empty((0, 3))
        self.newest_time_s = -np.inf

    def __len__(self) -> int:
        return int(self.time_s.size)

    def add(
        self,
        time_s: NDArray[np.float64],
        mmsi: NDArray[np.str_],
        lat_deg: NDArray[np.float64],
        lon_deg: NDArray[np.float64],
        batch_time_s: float,
    ) -> None:
        """Absorb one batch of reports (sea level, WGS-84) and forget the too old ones."""
        self.time_s = np.concatenate([self.time_s, time_s])
        self.mmsi = np.concatenate([self.mmsi.astype(str), mmsi.astype(str)])
        self.ecef = np.concatenate([self.ecef, geodetic_to_ecef(lat_deg, lon_deg, 0.0).reshape(-1, 3)])
        self.newest_time_s = max(self.newest_time_s, batch_time_s)
        keep = self.time_s >= self.newest_time_s - self.params.max_age_s
        self.time_s, self.mmsi, self.ecef = self.time_s[keep], self.mmsi[keep], self.ecef[keep]

    def table(self, time_s: float) -> TrackTable:
        """One confirmed track per MMSI: its latest report, velocity from the one before it."""
        p = self.params
        recent = self.time_s >= time_s - p.max_age_s
        if not recent.any():
            return TrackTable.empty()
        t, ids, pos = self.time_s[recent], self.mmsi[recent], self.ecef[recent]
        order = np.lexsort((t, ids))  # by MMSI, then time
        t, ids, pos = t[order], ids[order], pos[order]
        last = np.flatnonzero(np.r_[ids[1:] != ids[:-1], True])
        prev = last - 1
        has_prev = (prev >= 0) & (ids[np.maximum(prev, 0)] == ids[last])
        dt = np.where(has_prev, t[last] - t[np.maximum(prev, 0)], 0.0)
        usable = has_prev & (dt > 0) & (dt <= p.max_velocity_gap_s)
        vel = np.zeros((last.size, 3))
        vel[usable] = (pos[last[usable]] - pos[prev[usable]]) / dt[usable, None]
        n = last.size
        counts = last - np.r_[0, last[:-1] + 1] + 1
        cov = np.zeros((n, 6, 6))
        cov[:, :3, :3] = np.eye(3) * p.position_sigma_m**2
        cov[:, 3:, 3:] = np.eye(3) * p.velocity_sigma_mps**2
        truth = np.empty(n, dtype=object)
        return TrackTable(
            track_id=ids[last].astype(str),
            confirmed=np.ones(n, dtype=bool),
            time_s=t[last],
            position_ecef_m=pos[last],
            velocity_ecef_mps=vel,
            covariance=cov,
            plots=counts.astype(np.int64),
            truth_id=truth,
        )
