"""Measurement model: polar plots to local ENU positions with first-order covariance.

SVD paper Section 1.1 / Eq. (1) (corrected axes, see ``service/geo.py``):
``east = r cos(el) sin(az)``, ``north = r cos(el) cos(az)``, ``up = r sin(el)``.
The covariance of a plot is ``J diag(s_r^2, s_az^2, s_el^2) J^T`` with ``J`` the Jacobian of
that map at the plot (:func:`service.geo.polar_jacobian`).  Each plot keeps its own time: a
rotating antenna sees targets at different times within one scan.

2-D radars (``elevation_deg`` NaN): the elevation is solved from ``altitude_m`` (0 when that is
NaN too) with :meth:`Site.elevation_for_altitude`, and its sigma is the altitude sigma mapped
through ``d(up)/d(el) ~ r cos(el)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.columns import concat_rows, take_rows
from service.geo import FloatArray, Site, polar_jacobian, polar_to_enu
from service.tracking.base import PlotColumns
from service.tracking.params import MeasurementParams


@dataclass(frozen=True)
class Measurements:
    """Plots as positions in the site's ENU frame, row ``i`` is plot ``i``."""

    time_s: FloatArray  # (n,)
    enu_m: FloatArray  # (n, 3)
    covariance: FloatArray  # (n, 3, 3)

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    def take(self, index: np.ndarray) -> Measurements:
        return take_rows(self, index)

    @staticmethod
    def empty() -> Measurements:
        return Measurements(np.empty(0), np.empty((0, 3)), np.empty((0, 3, 3)))

    @staticmethod
    def concat(parts: list[Measurements]) -> Measurements:
        return concat_rows(Measurements, parts) if parts else Measurements.empty()


def polar_covariance_enu(
    range_m: FloatArray,
    azimuth_deg: FloatArray,
    elevation_deg: FloatArray,
    range_sigma_m: FloatArray | float,
    azimuth_sigma_rad: FloatArray | float,
    elevation_sigma_rad: FloatArray | float,
) -> FloatArray:
    """``J diag(s_r^2, s_az^2, s_el^2) J^T`` per plot, shape ``(n, 3, 3)``; sigmas broadcast."""
    jac = polar_jacobian(range_m, azimuth_deg, elevation_deg)
    d = np.empty(jac.shape[:-1])  # the variances, broadcast to every plot
    d[..., 0] = np.square(range_sigma_m)
    d[..., 1] = np.square(azimuth_sigma_rad)
    d[..., 2] = np.square(elevation_sigma_rad)
    cov = (jac * d[..., None, :]) @ np.swapaxes(jac, -1, -2)
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))


def plot_elevation(
    site: Site, plots: PlotColumns, params: MeasurementParams
) -> tuple[FloatArray, FloatArray]:
    """Elevation (deg) and elevation sigma (rad) of every plot (see module docstring)."""
    el = np.array(plots.elevation_deg, dtype=float, copy=True)
    sigma = np.full(el.shape, np.radians(site.elevation_sigma_deg))
    missing = np.isnan(el)
    if np.any(missing):
        r = plots.range_m[missing]
        alt = plots.altitude_m[missing]
        alt = np.where(np.isnan(alt), 0.0, alt)
        el_m = site.elevation_for_altitude(r, alt, plots.azimuth_deg[missing])
        el[missing] = el_m
        sigma[missing] = params.altitude_sigma_m / np.maximum(r * np.cos(np.radians(el_m)), 1.0)
    return el, sigma


def plots_to_measurements(site: Site, plots: PlotColumns, params: MeasurementParams) -> Measurements:
    """Polar plots to ENU positions and covariances."""
    if len(plots) == 0:
        return Measurements.empty()
    el, el_sigma = plot_elevation(site, plots, params)
    enu = polar_to_enu(plots.range_m, plots.azimuth_deg, el)
    cov = polar_covariance_enu(
        plots.range_m,
        plots.azimuth_deg,
        el,
        site.range_sigma_m,
        np.radians(site.azimuth_sigma_deg),
        el_sigma,
    )
    return Measurements(np.asarray(plots.time_s, dtype=float), enu, cov)
