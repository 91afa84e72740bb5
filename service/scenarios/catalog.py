"""Named scenarios for ``topofusion simulate --scenario NAME`` and ``topofusion demo``."""

from __future__ import annotations

from dataclasses import replace

from service.scenarios.simulator import AisSpec, RadarSpec, Scenario

# Two radars ~200 km apart (SVD paper, Section 3: random errors 200 m / 0.2 deg, systematic
# errors 100 m / 0.1 deg); targets over the common area between them.
_LAT = 31.20
_A = RadarSpec("A", _LAT, 118.50, range_bias_m=100.0, azimuth_bias_deg=0.1, elevation_bias_deg=0.1)
_B = RadarSpec("B", _LAT, 120.60, range_bias_m=-100.0, azimuth_bias_deg=-0.1, elevation_bias_deg=-0.1)
_C = RadarSpec("C", 32.80, 119.55, range_bias_m=150.0, azimuth_bias_deg=0.15, scan_period_s=5.0, sectors=10)

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
