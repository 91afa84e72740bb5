"""Bring a radar's tracks to the common data time of a correlation update (pure numpy).

Constant-velocity model: ``x(t) = x + v dt``, ``P(t) = F P F^T + Q`` with
``F = [[I, dt I], [0, I]]`` and the continuous white-noise-acceleration ``Q`` of spectral
density ``q`` (m^2/s^3): ``Q = q [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]`` (Bar-Shalom,
Li, Kirubarajan 2001, Section 6.2.2).  ``dt`` may be negative (a track newer than the update
time is brought back); ``Q`` then uses ``|dt|``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from service.correlation.base import FloatArray, PredictedTracks
from service.geo import Site
from service.tracking.base import TrackTable


@dataclass(frozen=True)
class PredictionParams:
    """How tracks are selected and extrapolated before correlation."""

    #: Spectral density of the white-noise acceleration (m^2/s^3) used for ``Q``.
    accel_psd: float = 1.0
    #: Use only confirmed tracks (tentative tracks are too unstable to correlate).
    confirmed_only: bool = True
    #: Tracks older than this (data time, seconds before the update) are left out.
    max_age_s: float = 60.0


def predict_states(
    position: FloatArray, velocity: FloatArray, covariance: FloatArray, dt: FloatArray, accel_psd: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Vectorised CV prediction of ``n`` states by ``dt`` (n,) seconds; returns pos, vel, 6x6 cov."""
    dt = np.asarray(dt, dtype=float)
    pos = position + velocity * dt[:, None]
    # F P F^T by blocks (F = [[I, dt I], [0, I]]; a batched 6x6 product is far slower):
    # [[A, B], [B', D]] -> [[A + dt B' + dt (B + dt D), B + dt D], [B' + dt D, D]].
    p = np.asarray(covariance, dtype=float)
    d3 = dt[:, None, None]
    pv = p[:, :3, 3:] + d3 * p[:, 3:, 3:]
    cov = np.empty(p.shape)
    cov[:, :3, :3] = (p[:, :3, :3] + d3 * p[:, 3:, :3]) + d3 * pv
    cov[:, :3, 3:] = pv
    cov[:, 3:, :3] = p[:, 3:, :3] + d3 * p[:, 3:, 3:]
    cov[:, 3:, 3:] = p[:, 3:, 3:]
    a = np.abs(dt)
    qpp, qpv, qvv = accel_psd * (a**3 / 3.0), accel_psd * (dt * a / 2.0), accel_psd * a
    for k in range(3):
        cov[:, k, k] += qpp
        cov[:, k, k + 3] += qpv
        cov[:, k + 3, k] += qpv
        cov[:, k + 3, k + 3] += qvv
    return pos, velocity.copy(), cov


def predict_blocks(
    position: FloatArray, velocity: FloatArray, covariance: FloatArray, dt: FloatArray, accel_psd: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`predict_states` returning the position and velocity covariance blocks only (what a
    snapshot keeps), in the same arithmetic: ``A + dt B^T + dt (B + dt D) + Q_pp`` and ``D + Q_vv``."""
    dt = np.asarray(dt, dtype=float)
    pos = position + velocity * dt[:, None]
    p = np.asarray(covariance, dtype=float)
    d3 = dt[:, None, None]
    pos_cov = (p[:, :3, :3] + d3 * p[:, 3:, :3]) + d3 * (p[:, :3, 3:] + d3 * p[:, 3:, 3:])
    vel_cov = p[:, 3:, 3:].copy()
    a = np.abs(dt)
    diag = np.arange(3)
    pos_cov[:, diag, diag] += (accel_psd * (a**3 / 3.0))[:, None]
    vel_cov[:, diag, diag] += (accel_psd * a)[:, None]
    return pos, velocity.copy(), pos_cov, vel_cov


def predict_tracks(
    table: TrackTable,
    site: Site | None,
    time_s: float,
    params: PredictionParams | None = None,
    keys: NDArray[np.int64] | None = None,
) -> PredictedTracks:
    """Select usable rows of ``table`` and extrapolate them to ``time_s``.

    ``site`` None marks a bias-free reference source (AIS); its ``enu`` is then the ECEF
    position itself (callers needing a plane use the other side's site).  ``keys``: each row's
    track key (:class:`~.pairkeys.TrackKeys`), carried to the snapshot's ``track_key``.
    """
    p = params or PredictionParams()
    keep = np.ones(len(table), dtype=bool)
    if p.confirmed_only:
        keep &= table.confirmed
    keep &= (time_s - table.time_s) <= p.max_age_s
    keep &= np.all(np.isfinite(table.position_ecef_m), axis=1) & np.all(
        np.isfinite(table.velocity_ecef_mps), axis=1
    )
    # Only the columns a snapshot uses (a table also carries plots, truth labels, ...).
    rows = np.flatnonzero(keep)
    track_id = np.asarray(table.track_id)[rows]
    pos, vel, pos_cov, vel_cov = predict_blocks(
        table.position_ecef_m[rows],
        table.velocity_ecef_mps[rows],
        table.covariance[rows],
        time_s - table.time_s[rows],
        p.accel_psd,
    )
    if site is None:
        enu, enu_v = pos, vel
    else:
        enu = site.ecef_to_enu(pos)
        enu_v = vel @ site.rotation
    return PredictedTracks(
        track_id=track_id.astype(str),
        track_key=None if keys is None else keys[rows],
        position=pos,
        velocity=vel,
        pos_cov=pos_cov,
        vel_cov=vel_cov,
        site=site,
        enu=enu,
        enu_velocity=enu_v,
        mode_s=table.mode_s[rows],
        quality=np.asarray(table.quality, dtype=float)[rows],
    )
