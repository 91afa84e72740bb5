"""The ``national`` load scenario: its geometry and data rate are what bench_national.py assumes."""

from __future__ import annotations

import json

import numpy as np

from service.geo import enu_rotation, geodetic_to_ecef
from tests.scenario_helpers import scenario_messages
from topofusion_lab.scenarios.catalog import get_scenario


def test_national_geometry() -> None:
    sc = get_scenario("national")
    assert len(sc.radars) == 12
    assert len({r.radar_id for r in sc.radars}) == 12
    centre = geodetic_to_ecef(sc.center_lat_deg, sc.center_lon_deg, 0.0)
    rot = enu_rotation(sc.center_lat_deg, sc.center_lon_deg)
    enu = np.array(
        [rot.T @ (geodetic_to_ecef(r.latitude_deg, r.longitude_deg, 0.0) - centre) for r in sc.radars]
    )
    ring = np.hypot(enu[:, 0], enu[:, 1])
    np.testing.assert_allclose(ring, 125_000.0, rtol=0.01)  # a ring 250 km across
    bearings = np.sort(np.degrees(np.arctan2(enu[:, 0], enu[:, 1])) % 360.0)
    # evenly spread (the catalog places them with a spherical approximation: within a degree)
    np.testing.assert_allclose(np.diff(bearings), 30.0, atol=1.0)
    assert {r.scan_period_s for r in sc.radars} >= {4.0, 5.0, 6.0}
    for component in ("range_bias_m", "azimuth_bias_deg", "elevation_bias_deg"):
        values = np.array([getattr(r, component) for r in sc.radars])
        assert (values > 0).any() and (values < 0).any(), component
    assert all(0.9 <= r.pd <= 0.95 and 20 <= r.clutter_per_scan <= 50 for r in sc.radars)
    assert sc.targets == 1500


def test_national_plot_rate() -> None:
    duration_s = 12.0  # two scans of the slowest radars
    msgs = scenario_messages("national", duration_s=duration_s, seed=1)
    plots = sum(len(json.loads(p)["plots"]["time_s"]) for k, p in msgs if k.endswith("/plots"))
    assert 1_500 <= plots / duration_s <= 2_100  # about 1 750 plots/s
