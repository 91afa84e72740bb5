"""WGS-84 geodesy and the radar measurement geometry (service/geo.py)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.geo import (
    WGS84_A,
    WGS84_B,
    Site,
    ecef_to_geodetic,
    enu_rotation,
    enu_to_polar,
    geodetic_to_ecef,
    polar_jacobian,
    polar_to_enu,
)

lat_st = st.floats(-90, 90, allow_nan=False)
lon_st = st.floats(-180, 180, allow_nan=False)
alt_st = st.floats(0, 20_000, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(lat_st, lon_st, alt_st)
def test_geodetic_round_trip_within_a_millimetre(lat: float, lon: float, alt: float) -> None:
    p = geodetic_to_ecef(lat, lon, alt)
    lat2, lon2, alt2 = ecef_to_geodetic(p)
    p2 = geodetic_to_ecef(lat2, lon2, alt2)
    assert np.linalg.norm(p2 - p) < 1e-3
    assert abs(alt2 - alt) < 1e-3


def test_reference_points() -> None:
    np.testing.assert_allclose(geodetic_to_ecef(0, 0, 0), [WGS84_A, 0, 0], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(0, 90, 0), [0, WGS84_A, 0], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(90, 0, 0), [0, 0, WGS84_B], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(-90, 0, 100), [0, 0, -WGS84_B - 100], atol=1e-6)
    # Points at height 0 lie on the ellipsoid; the height is along the surface normal, whose
    # slope in the meridian plane is the geodetic latitude.
    lat = np.linspace(-89.0, 89.0, 37)
    p0 = geodetic_to_ecef(lat, 30.0, 0.0)
    rho = np.hypot(p0[:, 0], p0[:, 1])
    np.testing.assert_allclose(rho**2 / WGS84_A**2 + p0[:, 2] ** 2 / WGS84_B**2, 1.0, atol=1e-12)
    normal = geodetic_to_ecef(lat, 30.0, 1000.0) - p0
    np.testing.assert_allclose(
        np.degrees(np.arctan2(normal[:, 2], np.hypot(normal[:, 0], normal[:, 1]))), lat
    )


def test_enu_rotation_is_orthonormal_with_east_north_up_columns() -> None:
    r = enu_rotation(31.2, 118.5)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) > 0
    up = geodetic_to_ecef(31.2, 118.5, 1.0) - geodetic_to_ecef(31.2, 118.5, 0.0)
    np.testing.assert_allclose(r[:, 2], up, atol=1e-9)
    north = geodetic_to_ecef(31.2001, 118.5, 0.0) - geodetic_to_ecef(31.2, 118.5, 0.0)
    assert np.dot(north / np.linalg.norm(north), r[:, 1]) > 0.999999


def test_axis_correction_azimuth_clockwise_from_north() -> None:
    # Paper Eq. (1) correction: east = r cos(el) sin(az), north = r cos(el) cos(az).
    np.testing.assert_allclose(polar_to_enu(1000.0, 0.0, 0.0), [0, 1000, 0], atol=1e-9)
    np.testing.assert_allclose(polar_to_enu(1000.0, 90.0, 0.0), [1000, 0, 0], atol=1e-9)
    np.testing.assert_allclose(polar_to_enu(1000.0, 0.0, 90.0), [0, 0, 1000], atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(st.floats(100, 400_000), st.floats(0, 359.999), st.floats(-89, 89))
def test_polar_round_trip(r: float, az: float, el: float) -> None:
    r2, az2, el2 = enu_to_polar(polar_to_enu(r, az, el))
    assert abs(r2 - r) < 1e-6
    assert abs((az2 - az + 180) % 360 - 180) < 1e-7
    assert abs(el2 - el) < 1e-7


@settings(max_examples=100, deadline=None)
@given(st.floats(1_000, 400_000), st.floats(0, 359.9), st.floats(-80, 80))
def test_jacobian_matches_finite_differences(r: float, az: float, el: float) -> None:
    jac = polar_jacobian(r, az, el)
    h = np.array([1e-3, 1e-6, 1e-6])
    num = np.empty((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h[k]
        plus = polar_to_enu(r + d[0], az + np.degrees(d[1]), el + np.degrees(d[2]))
        minus = polar_to_enu(r - d[0], az - np.degrees(d[1]), el - np.degrees(d[2]))
        num[:, k] = (plus - minus) / (2 * h[k])
    np.testing.assert_allclose(jac, num, rtol=1e-5, atol=1e-4)


def test_site_frames_and_altitude_inversion() -> None:
    site = Site("A", 31.2, 118.5, 40.0)
    ecef = site.polar_to_ecef([150_000.0, 90_000.0], [41.25, 310.0], [2.1, 1.35])
    r, az, el = site.ecef_to_polar(ecef)
    np.testing.assert_allclose(r, [150_000.0, 90_000.0], atol=1e-6)
    np.testing.assert_allclose(az, [41.25, 310.0], atol=1e-9)
    # a 2-D radar: the elevation that puts a plot at a given altitude
    el = site.elevation_for_altitude([150_000.0, 30_000.0], [9_000.0, 0.0], [41.25, 10.0])
    _, _, h = ecef_to_geodetic(site.polar_to_ecef([150_000.0, 30_000.0], [41.25, 10.0], el))
    np.testing.assert_allclose(h, [9_000.0, 0.0], atol=0.01)


def test_measurement_covariance_is_symmetric_positive_definite() -> None:
    site = Site("A", 31.2, 118.5, 40.0, 200.0, 0.2, 0.2)
    cov = site.measurement_covariance_enu([50_000.0, 200_000.0], [10.0, 200.0], [1.0, 3.0])
    np.testing.assert_allclose(cov, np.swapaxes(cov, -1, -2))
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # cross-range sigma ~ r * sigma_az
    sig = np.sqrt(np.linalg.eigvalsh(cov[1]))
    assert abs(sig.max() - 200_000 * np.radians(0.2)) / sig.max() < 0.05
