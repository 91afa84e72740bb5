"""Named scenarios for ``topofusion simulate --scenario NAME`` and ``topofusion demo``."""

from __future__ import annotations

import math
from dataclasses import replace

from topofusion_lab.scenarios.simulator import AisSpec, RadarSpec, Scenario

# Two radars ~200 km apart (SVD paper, Section 3: random errors 200 m / 0.2 deg, systematic
# errors 100 m / 0.1 deg); targets over the common area between them.
_LAT = 31.20
_A = RadarSpec("A", _LAT, 118.50, range_bias_m=100.0, azimuth_bias_deg=0.1, elevation_bias_deg=0.1)
_B = RadarSpec("B", _LAT, 120.60, range_bias_m=-100.0, azimuth_bias_deg=-0.1, elevation_bias_deg=-0.1)
_C = RadarSpec("C", 32.80, 119.55, range_bias_m=150.0, azimuth_bias_deg=0.15, scan_period_s=5.0, sectors=10)


# A national network: 12 radars evenly spread on a ring 250 km across, 1 500 aircraft over a
# square 740 km wide, so each radar (300 km range, radio horizon of its altitude) sees about
# half of them.  Scan periods 4-6 s mixed, each radar with its own bias of varied sign and
# its own clutter and Pd.  About 1 750 plots/s in total: a load scenario for the engine.
_NATIONAL_LAT, _NATIONAL_LON = 46.5, 2.5
_NATIONAL_RING_M = 125_000.0
#: Per radar: scan period s, range bias m, azimuth bias deg, elevation bias deg, clutter per
#: scan, Pd, antenna altitude m.
_NATIONAL_RADARS = (
    (4.0, 250.0, 0.25, 0.05, 30, 0.93, 60.0),
    (5.0, -300.0, 0.15, -0.10, 45, 0.90, 120.0),
    (6.0, 400.0, -0.30, 0.10, 20, 0.95, 40.0),
    (4.5, -150.0, -0.20, 0.05, 35, 0.92, 200.0),
    (5.0, 350.0, 0.35, -0.05, 50, 0.91, 80.0),
    (4.0, -450.0, 0.10, 0.15, 25, 0.94, 30.0),
    (6.0, 200.0, -0.40, -0.10, 40, 0.90, 150.0),
    (5.5, -250.0, 0.30, 0.05, 30, 0.95, 100.0),
    (4.0, 300.0, -0.15, -0.15, 20, 0.92, 50.0),
    (5.0, -400.0, -0.25, 0.10, 45, 0.93, 250.0),
    (6.0, 150.0, 0.20, -0.05, 35, 0.91, 70.0),
    (4.5, -200.0, -0.35, 0.05, 50, 0.94, 110.0),
)


def _national_radars() -> tuple[RadarSpec, ...]:
    out = []
    cos_lat = math.cos(math.radians(_NATIONAL_LAT))
    for i, (period, rb, ab, eb, clutter, pd, alt) in enumerate(_NATIONAL_RADARS):
        bearing = math.radians(360.0 * i / len(_NATIONAL_RADARS))
        east, north = _NATIONAL_RING_M * math.sin(bearing), _NATIONAL_RING_M * math.cos(bearing)
        # metres to degrees on a sphere: good to well under 1 km at this scale, and the sites
        # are sent with the radars' exact positions anyway
        lat = _NATIONAL_LAT + north / 111_195.0
        lon = _NATIONAL_LON + east / (111_195.0 * cos_lat)
        out.append(
            RadarSpec(
                f"N{i + 1:02d}",
                round(lat, 5),
                round(lon, 5),
                altitude_m=alt,
                scan_period_s=period,
                range_bias_m=rb,
                azimuth_bias_deg=ab,
                elevation_bias_deg=eb,
                pd=pd,
                clutter_per_scan=clutter,
                max_range_m=300_000.0,
                sectors=8,
            )
        )
    return tuple(out)


SCENARIOS: dict[str, Scenario] = {
    "two-radar": Scenario(
        name="two-radar",
        description="2 radars 200 km apart, 40 aircraft, the SVD paper's noise and bias levels",
        radars=(_A, _B),
        center_lat_deg=_LAT,
        center_lon_deg=119.55,
        half_width_m=120_000.0,
        targets=40,
        duration_s=600.0,
    ),
    "three-radar": Scenario(
        name="three-radar",
        description="3 radars, 80 aircraft, light clutter, one radar with a 5 s scan",
        radars=(replace(_A, clutter_per_scan=20), replace(_B, clutter_per_scan=20), _C),
        center_lat_deg=31.9,
        center_lon_deg=119.55,
        half_width_m=140_000.0,
        targets=80,
        duration_s=600.0,
    ),
    "large-bias": Scenario(
        name="large-bias",
        description="2 radars with 1 km / 1 deg biases, where nearest-neighbour association fails",
        radars=(
            replace(_A, range_bias_m=1000.0, azimuth_bias_deg=1.0),
            replace(_B, range_bias_m=-800.0, azimuth_bias_deg=-0.8),
        ),
        center_lat_deg=_LAT,
        center_lon_deg=119.55,
        half_width_m=120_000.0,
        targets=40,
        duration_s=600.0,
    ),
    "coastal": Scenario(
        name="coastal",
        description="a coastal radar with 500 m / 0.5 deg bias and an AIS receiver, 30 vessels",
        radars=(
            RadarSpec(
                "coast",
                30.60,
                122.00,
                altitude_m=100.0,
                range_sigma_m=50.0,
                azimuth_sigma_deg=0.1,
                elevation_sigma_deg=0.1,
                range_bias_m=500.0,
                azimuth_bias_deg=0.5,
                max_range_m=60_000.0,
            ),
        ),
        ais=(AisSpec("ais-1", report_period_s=10.0, batch_period_s=10.0),),
        center_lat_deg=30.60,
        center_lon_deg=122.17,
        half_width_m=20_000.0,
        targets=30,
        speed_mps=(3.0, 12.0),
        altitude_m=(0.0, 0.0),
        duration_s=900.0,
    ),
    "national": Scenario(
        name="national",
        description="12 radars on a 250 km ring, 1 500 aircraft, 4-6 s scans, per-radar biases "
        "and clutter, about 1 750 plots/s",
        radars=_national_radars(),
        center_lat_deg=_NATIONAL_LAT,
        center_lon_deg=_NATIONAL_LON,
        half_width_m=370_000.0,
        targets=1500,
        duration_s=600.0,
    ),
}
#: The scenario of ``topofusion demo`` (runs until stopped).
DEMO = replace(SCENARIOS["two-radar"], name="demo", duration_s=None)


def get_scenario(name: str) -> Scenario:
    if name == "demo":
        return DEMO
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose from: demo, {', '.join(SCENARIOS)}") from None
