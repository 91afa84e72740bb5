"""Helpers shared by the correlation tests."""

from __future__ import annotations

import numpy as np

from service.correlation.base import PredictedTracks
from service.geo import Site


def snapshot_of(
    site: Site, truth: np.ndarray, bias: np.ndarray, rng: np.random.Generator, noise: float
) -> PredictedTracks:
    """A radar's picture of ``truth`` (ECEF, n x 3): its polar measurement shifted by ``bias``
    (range m, azimuth rad, elevation rad), plus white noise of ``noise`` m, as a snapshot."""
    r, az, el = site.ecef_to_polar(truth)
    pos = site.polar_to_ecef(r + bias[0], az + np.degrees(bias[1]), el + np.degrees(bias[2]))
    pos = pos + rng.normal(0, noise, pos.shape)
    n = len(pos)
    cov = np.broadcast_to(np.eye(3) * max(noise, 1.0) ** 2, (n, 3, 3)).copy()
    return PredictedTracks(
        np.array([f"{site.site_id}{i}" for i in range(n)]),
        pos,
        np.zeros((n, 3)),
        cov,
        cov.copy(),
        site,
        site.ecef_to_enu(pos),
        np.zeros((n, 3)),
    )
