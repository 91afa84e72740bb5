"""The ``continental`` sizing scenario (bench_partition.py --scenario continental): a grid of 45
radars, and aircraft that stay at their flight levels over 1 800 km (the earth's curve)."""

from __future__ import annotations

import json
from collections import defaultdict

import numpy as np

from service.geo import ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from tests.scenario_helpers import scenario_messages
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import _ecef


def test_continental_geometry() -> None:
    sc = get_scenario("continental")
    assert len({r.radar_id for r in sc.radars}) == len(sc.radars) == 45
    assert sc.curved and sc.targets == 5500
    centre = geodetic_to_ecef(sc.center_lat_deg, sc.center_lon_deg, 0.0)
    rot = enu_rotation(sc.center_lat_deg, sc.center_lon_deg)
    sites = np.array([geodetic_to_ecef(r.latitude_deg, r.longitude_deg, 0.0) for r in sc.radars])
    # nearest neighbour 250 km away (a grid), within 1 % on the sphere approximation
    d = np.linalg.norm(sites[:, None] - sites[None], axis=2) + np.eye(len(sites)) * 1e9
    np.testing.assert_allclose(d.min(axis=1), 250_000.0, rtol=0.01)
    east_north = (sites - centre) @ rot
    assert np.abs(east_north[:, :2]).max() < sc.half_width_m


def test_curved_targets_keep_their_height_far_from_the_centre() -> None:
    """On the tangent plane a target 900 km out would be 64 km up; curved, it flies at its height."""
    sc = get_scenario("continental")
    centre = geodetic_to_ecef(sc.center_lat_deg, sc.center_lon_deg, 0.0)
    rot = enu_rotation(sc.center_lat_deg, sc.center_lon_deg)
    enu = np.array([[880_000.0, -870_000.0, 9_000.0], [0.0, 0.0, 3_000.0], [-600_000.0, 850_000.0, 11_000.0]])
    _, _, height = ecef_to_geodetic(_ecef(sc, enu, centre, rot))
    np.testing.assert_allclose(height, enu[:, 2], atol=1e-3)
    # distances along the surface from the centre: the east and north offsets
    lat, _, _ = ecef_to_geodetic(_ecef(sc, enu, centre, rot))
    np.testing.assert_allclose((lat - sc.center_lat_deg) * 111_195.0, enu[:, 1], atol=1e-3)


def test_continental_plot_rate_and_overlap() -> None:
    duration_s = 6.0  # a scan of the slowest radars
    msgs = scenario_messages("continental", duration_s=duration_s, seed=1)
    sc = get_scenario("continental")
    seen_by: dict[str, set[str]] = defaultdict(set)
    plots = 0
    for key, payload in msgs:
        if not key.endswith("/plots"):
            continue
        body = json.loads(payload)
        plots += len(body["plots"]["time_s"])
        for truth in body["plots"]["truth_id"]:
            if truth is not None:
                seen_by[truth].add(body["radar_id"])
    assert {r.radar_id for r in sc.radars} == {
        json.loads(p)["radar_id"] for k, p in msgs if k.endswith("/plots")
    }
    assert 3_200 <= plots / duration_s <= 4_800  # about 4 000 plots/s
    radars_per_aircraft = np.mean([len(v) for v in seen_by.values()])
    assert 2.5 <= radars_per_aircraft <= 5.0  # each aircraft in several radars' cover
    assert len(seen_by) >= 0.9 * sc.targets  # nearly every aircraft is seen
