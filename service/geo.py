"""WGS-84 geodesy and radar measurement geometry (pure numpy, vectorised).

Frames
------
* geodetic: latitude/longitude in degrees, height above the WGS-84 ellipsoid in metres;
* ECEF: earth-centred, earth-fixed Cartesian metres;
* ENU: local east-north-up tangent frame at a site;
* radar polar: slant range (m), azimuth (deg, clockwise from true north), elevation
  (deg, up from the local tangent plane).

SVD paper, Section 1.1, Eq. (1): ``y = R x + L`` with ``L`` the radar's ECEF position and
``R`` the local-to-ECEF rotation whose columns are east, north and up.  The paper prints
``x = r cos(phi) cos(theta), y = r cos(phi) sin(theta)``; with its east-north-up ``R`` and
azimuth clockwise from north the consistent form is used here (docs/references.md §1):
``east = r cos(phi) sin(theta)``, ``north = r cos(phi) cos(theta)``, ``up = r sin(phi)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: WGS-84 semi-major axis (m).
WGS84_A = 6_378_137.0
#: WGS-84 flattening.
WGS84_F = 1.0 / 298.257223563
#: WGS-84 semi-minor axis (m).
WGS84_B = WGS84_A * (1.0 - WGS84_F)
#: First eccentricity squared.
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
#: Second eccentricity squared.
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)


def geodetic_to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike) -> FloatArray:
    """Geodetic (deg, deg, m) to ECEF metres; broadcasts, returns shape ``(..., 3)``."""
    lat = np.radians(np.asarray(lat_deg, dtype=float))
    lon = np.radians(np.asarray(lon_deg, dtype=float))
    h = np.asarray(alt_m, dtype=float)
    sin_lat = np.sin(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)  # prime-vertical radius
    x = (n + h) * np.cos(lat) * np.cos(lon)
    y = (n + h) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sin_lat
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(ecef: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """ECEF metres ``(..., 3)`` to geodetic (lat deg, lon deg, alt m).

    Bowring's parametric-latitude start followed by two Newton-style refinements: better
    than 1e-6 m for heights from -10 km to 1000 km, which covers every radar target.
    """
    p = np.asarray(ecef, dtype=float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lon = np.arctan2(y, x)
    rho = np.hypot(x, y)
    beta = np.arctan2(z * WGS84_A, rho * WGS84_B)  # parametric latitude, Bowring (1976)
    lat = np.arctan2(
        z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3,
        rho - WGS84_E2 * WGS84_A * np.cos(beta) ** 3,
    )
    for _ in range(2):
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
        lat = np.arctan2(
            z + WGS84_EP2 * WGS84_B * np.sin(beta) ** 3,
            rho - WGS84_E2 * WGS84_A * np.cos(beta) ** 3,
        )
    sin_lat = np.sin(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    # Height along the normal, stable at all latitudes.
    alt = rho * np.cos(lat) + (z + WGS84_E2 * n * sin_lat) * sin_lat - n
    return np.degrees(lat), np.degrees(lon), alt


def enu_rotation(lat_deg: float, lon_deg: float) -> FloatArray:
    """The 3x3 matrix ``R`` of Eq. (1): columns are the east, north, up unit vectors in ECEF.

    ``ecef = R @ enu + L`` and ``enu = R.T @ (ecef - L)``.
    """
    lat = np.radians(lat_deg)
    lon = np.radians(lon_deg)
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    return np.array(
        [
            [-so, -sl * co, cl * co],
            [co, -sl * so, cl * so],
            [0.0, cl, sl],
        ]
    )


def polar_to_enu(range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike) -> FloatArray:
    """Radar polar to local ENU, corrected axes of Section 1.1 (see module docstring)."""
    r = np.asarray(range_m, dtype=float)
    az = np.radians(np.asarray(azimuth_deg, dtype=float))
    el = np.radians(np.asarray(elevation_deg, dtype=float))
    horiz = r * np.cos(el)
    return np.stack(np.broadcast_arrays(horiz * np.sin(az), horiz * np.cos(az), r * np.sin(el)), axis=-1)


def enu_to_polar(enu: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Local ENU ``(..., 3)`` to (range m, azimuth deg in [0, 360), elevation deg)."""
    v = np.asarray(enu, dtype=float)
    e, n, u = v[..., 0], v[..., 1], v[..., 2]
    r = np.sqrt(e * e + n * n + u * u)
    az = np.mod(np.degrees(np.arctan2(e, n)), 360.0)
    el = np.degrees(np.arctan2(u, np.hypot(e, n)))
    return r, az, el


def polar_jacobian(range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike) -> FloatArray:
    """d(east, north, up) / d(range, azimuth_rad, elevation_rad), shape ``(..., 3, 3)``.

    First-order Jacobian of :func:`polar_to_enu`, used to map the site's random-error sigmas
    into an ENU covariance ``J diag(s_r^2, s_az^2, s_el^2) J^T``.
    """
    r = np.asarray(range_m, dtype=float)
    az = np.radians(np.asarray(azimuth_deg, dtype=float))
    el = np.radians(np.asarray(elevation_deg, dtype=float))
    r, az, el = np.broadcast_arrays(r, az, el)
    sa, ca, se, ce = np.sin(az), np.cos(az), np.sin(el), np.cos(el)
    jac = np.empty((*r.shape, 3, 3))
    jac[..., 0, 0] = ce * sa
    jac[..., 0, 1] = r * ce * ca
    jac[..., 0, 2] = -r * se * sa
    jac[..., 1, 0] = ce * ca
    jac[..., 1, 1] = -r * ce * sa
    jac[..., 1, 2] = -r * se * ca
    jac[..., 2, 0] = se
    jac[..., 2, 1] = 0.0
    jac[..., 2, 2] = r * ce
    return jac


@dataclass(frozen=True)
class Site:
    """A sensor's position and random-error model, the numerics' view of ``RadarSite``."""

    site_id: str
    latitude_deg: float
    longitude_deg: float
    altitude_m: float = 0.0
    range_sigma_m: float = 200.0
    azimuth_sigma_deg: float = 0.2
    elevation_sigma_deg: float = 0.2
    scan_period_s: float = 4.0
    origin_ecef: FloatArray = field(init=False, repr=False, compare=False)
    rotation: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "origin_ecef", geodetic_to_ecef(self.latitude_deg, self.longitude_deg, self.altitude_m)
        )
        object.__setattr__(self, "rotation", enu_rotation(self.latitude_deg, self.longitude_deg))

    # -- frames -------------------------------------------------------------------------
    def enu_to_ecef(self, enu: ArrayLike) -> FloatArray:
        """Eq. (1): ``y = R x + L`` for points of shape ``(..., 3)``."""
        return np.asarray(enu, dtype=float) @ self.rotation.T + self.origin_ecef

    def ecef_to_enu(self, ecef: ArrayLike) -> FloatArray:
        """Inverse of Eq. (1): ``x = R^T (y - L)``."""
        return (np.asarray(ecef, dtype=float) - self.origin_ecef) @ self.rotation

    def polar_to_ecef(
        self, range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike
    ) -> FloatArray:
        return self.enu_to_ecef(polar_to_enu(range_m, azimuth_deg, elevation_deg))

    def ecef_to_polar(self, ecef: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        return enu_to_polar(self.ecef_to_enu(ecef))

    def elevation_for_altitude(
        self, range_m: ArrayLike, altitude_m: ArrayLike, azimuth_deg: ArrayLike
    ) -> FloatArray:
        """Elevation (deg) at which a plot at ``range_m`` lies at ``altitude_m`` (WGS-84).

        For 2-D radars (contract: ``plots.altitude_m`` or altitude 0).  Starts from the
        spherical-earth law of cosines with the site's Gaussian mean radius, then corrects
        with two Newton steps on the exact ellipsoidal height (``dh/d(el) ~ r cos(el)``).
        Ranges shorter than the height difference are clipped to +-90 deg.
        """
        r = np.asarray(range_m, dtype=float)
        h = np.asarray(altitude_m, dtype=float)
        az = np.asarray(azimuth_deg, dtype=float)
        lat = np.radians(self.latitude_deg)
        sin2 = np.sin(lat) ** 2
        # Gaussian mean radius of curvature at the site.
        radius = WGS84_A * np.sqrt(1.0 - WGS84_E2) / (1.0 - WGS84_E2 * sin2)
        r0 = radius + self.altitude_m
        sin_el = ((radius + h) ** 2 - r0**2 - r**2) / (2.0 * r * r0)
        el = np.arcsin(np.clip(sin_el, -1.0, 1.0))
        for _ in range(2):
            _, _, h_est = ecef_to_geodetic(self.polar_to_ecef(r, az, np.degrees(el)))
            step = (h - h_est) / np.maximum(r * np.cos(el), 1.0)
            el = np.clip(el + step, -np.pi / 2, np.pi / 2)
        return np.degrees(el)

    def measurement_covariance_enu(
        self, range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike
    ) -> FloatArray:
        """ENU covariance ``J diag(s_r^2, s_az^2, s_el^2) J^T`` of each plot, ``(..., 3, 3)``."""
        jac = polar_jacobian(range_m, azimuth_deg, elevation_deg)
        d = np.array(
            [
                self.range_sigma_m**2,
                np.radians(self.azimuth_sigma_deg) ** 2,
                np.radians(self.elevation_sigma_deg) ** 2,
            ]
        )
        return (jac * d) @ np.swapaxes(jac, -1, -2)
