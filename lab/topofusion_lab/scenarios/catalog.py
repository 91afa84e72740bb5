"""Named scenarios for ``topofusion simulate --scenario NAME`` and ``topofusion demo``."""

from __future__ import annotations

import math
from dataclasses import replace

from topofusion_lab.scenarios.simulator import (
    AdsbSpec,
    AisSpec,
    FormationSpec,
    RadarSpec,
    Scenario,
    surface_point,
)

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


def _network_radar(name: str, lat: float, lon: float, row: tuple[float, ...]) -> RadarSpec:
    """An en-route radar of a load scenario at ``lat``/``lon`` with one row of
    :data:`_NATIONAL_RADARS` (scan period, biases, clutter, Pd, height), 300 km range."""
    period, rb, ab, eb, clutter, pd, alt = row
    return RadarSpec(
        name,
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


def _national_radars() -> tuple[RadarSpec, ...]:
    out = []
    cos_lat = math.cos(math.radians(_NATIONAL_LAT))
    for i, row in enumerate(_NATIONAL_RADARS):
        bearing = math.radians(360.0 * i / len(_NATIONAL_RADARS))
        east, north = _NATIONAL_RING_M * math.sin(bearing), _NATIONAL_RING_M * math.cos(bearing)
        # metres to degrees on a sphere: good to well under 1 km at this scale, and the sites
        # are sent with the radars' exact positions anyway
        lat = _NATIONAL_LAT + north / 111_195.0
        lon = _NATIONAL_LON + east / (111_195.0 * cos_lat)
        out.append(_network_radar(f"N{i + 1:02d}", lat, lon, row))
    return tuple(out)


# A continental network, for sizing a partitioned deployment: 45 radars on a 250 km grid
# (7 x 7 without its corners, 1 500 km across), 5 500 aircraft over a square 1 800 km wide on
# the earth's curve, so each aircraft is seen by about 3-4 radars (300 km range, the horizon)
# and each radar overlaps its 8 nearest neighbours and more.  The radars take the national
# radars' scan periods, biases, clutter, Pd and heights in turn.  About 4 000 plots/s, 2.2
# times the national rate.
_CONTINENTAL_LAT, _CONTINENTAL_LON = 48.0, 10.0
_CONTINENTAL_GRID, _CONTINENTAL_STEP_M = 7, 250_000.0


def _continental_radars() -> tuple[RadarSpec, ...]:
    out: list[RadarSpec] = []
    last = _CONTINENTAL_GRID - 1
    for row in range(_CONTINENTAL_GRID):
        for col in range(_CONTINENTAL_GRID):
            if row in (0, last) and col in (0, last):
                continue  # the corners
            east, north = (col - last / 2) * _CONTINENTAL_STEP_M, (last / 2 - row) * _CONTINENTAL_STEP_M
            # as the curved scenario places its aircraft (a grid on the surface, 250 km apart
            # in both directions)
            lat, lon = surface_point(_CONTINENTAL_LAT, _CONTINENTAL_LON, east, north)
            spec = _NATIONAL_RADARS[len(out) % len(_NATIONAL_RADARS)]
            out.append(_network_radar(f"C{len(out) + 1:02d}", float(lat), float(lon), spec))
    return tuple(out)


def _offset(lat0: float, lon0: float, east_m: float, north_m: float) -> tuple[float, float]:
    """The point ``east_m`` / ``north_m`` from ``(lat0, lon0)`` on a sphere (well under 1 km off
    at a few hundred km; the sites are sent with the exact positions anyway)."""
    lat = lat0 + north_m / 111_195.0
    lon = lon0 + east_m / (111_195.0 * math.cos(math.radians(lat0)))
    return round(lat, 5), round(lon, 5)


# A tight formation seen by three en-route radars.  30 aircraft on a jittered 2 km lattice (6 x 5,
# about 10 x 8 km, each moved up to 500 m along and across) fly together at 230 m/s, heading
# 070, across the common coverage: 138 km in 10 min, centred on the scenario centre at half
# time.  The radars stand 110-120 km from the centre on both sides of the track (A north, B
# south, C north-north-east), so the ranges run from about 100 to 160 km.  Plot errors
# 100-200 m / 0.12-0.2 deg (0.25-0.5 km across the line of sight); scans of 6-10 s.  Azimuth
# biases of 0.3-0.4 deg (with range biases of 150-250 m) move each radar's picture 0.6-1 km,
# and the signs make two radars' pictures of the formation 1.1-1.6 km apart (A-B, A-C) and
# 0.5-1.3 km (B-C): about one lattice spacing, where the nearest aircraft of the other radar
# is often the wrong one.  C, an older radar, detects with Pd 0.75.  ``FormationSpec.spacing_m``
# and ``Scenario.targets`` are the knobs of a sweep
# (``topofusion_lab.evaluation.formation_pipeline --spacing-m X --targets N``).
_FORMATION_LAT, _FORMATION_LON = 50.0, 9.0
#: Per radar: id, range from the centre m, bearing from the centre deg, range sigma m, azimuth
#: sigma deg, scan period s, range bias m, azimuth bias deg, elevation bias deg, Pd.
_FORMATION_RADARS = (
    ("A", 110_000.0, 340.0, 100.0, 0.12, 8.0, 150.0, 0.30, 0.05, 0.95),
    ("B", 120_000.0, 160.0, 150.0, 0.15, 10.0, -200.0, 0.40, -0.05, 0.92),
    ("C", 115_000.0, 10.0, 200.0, 0.20, 6.0, 250.0, -0.35, 0.10, 0.75),
)
_FORMATION_HEADING_DEG, _FORMATION_SPEED_MPS, _FORMATION_DURATION_S = 70.0, 230.0, 600.0


def _formation_radars() -> tuple[RadarSpec, ...]:
    out = []
    for rid, dist, bearing, rs, azs, period, rb, ab, eb, pd in _FORMATION_RADARS:
        b = math.radians(bearing)
        lat, lon = _offset(_FORMATION_LAT, _FORMATION_LON, dist * math.sin(b), dist * math.cos(b))
        out.append(
            RadarSpec(
                rid,
                lat,
                lon,
                range_sigma_m=rs,
                azimuth_sigma_deg=azs,
                scan_period_s=period,
                range_bias_m=rb,
                azimuth_bias_deg=ab,
                elevation_bias_deg=eb,
                pd=pd,
                clutter_per_scan=20,
                max_range_m=300_000.0,
            )
        )
    return tuple(out)


def _formation() -> FormationSpec:
    half = _FORMATION_SPEED_MPS * _FORMATION_DURATION_S / 2.0  # centred at half time
    h = math.radians(_FORMATION_HEADING_DEG)
    return FormationSpec(
        spacing_m=2_000.0,
        jitter=0.25,
        heading_deg=_FORMATION_HEADING_DEG,
        speed_mps=_FORMATION_SPEED_MPS,
        start_east_m=-half * math.sin(h),
        start_north_m=-half * math.cos(h),
    )


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
    "thin-traffic": Scenario(
        name="thin-traffic",
        description="2 radars 200 km apart (4 s and 12 s scans), 10 aircraft tens of km apart over 320 km",
        radars=(_A, replace(_B, scan_period_s=12.0)),
        center_lat_deg=_LAT,
        center_lon_deg=119.55,
        half_width_m=160_000.0,
        targets=10,
        duration_s=900.0,
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
    "assessment": Scenario(
        name="assessment",
        description=(
            "3 radars with range gains and time-stamp biases, 60 % of 80 aircraft on ADS-B: "
            "registration and the radar performance assessment"
        ),
        radars=(
            replace(_A, range_bias_m=120.0, range_gain_ppm=800.0, time_bias_s=0.6, pd=0.90, identity=True),
            replace(
                _B,
                range_bias_m=-180.0,
                range_gain_ppm=-600.0,
                time_bias_s=-0.4,
                pd=0.97,
                identity=True,
                mode_3a_error=0.03,
                mode_c_error=0.05,
            ),
            replace(_C, range_bias_m=250.0, range_gain_ppm=400.0, time_bias_s=1.0, pd=0.99, identity=True),
        ),
        adsb=(AdsbSpec("ads-b", identity=True, equipped_share=0.6),),
        center_lat_deg=31.9,
        center_lon_deg=119.55,
        half_width_m=140_000.0,
        targets=80,
        duration_s=900.0,
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
    "continental": Scenario(
        name="continental",
        description="45 radars on a 250 km grid 1 500 km across, 5 500 aircraft on the earth's "
        "curve, 4-6 s scans, per-radar biases and clutter, about 4 000 plots/s",
        radars=_continental_radars(),
        center_lat_deg=_CONTINENTAL_LAT,
        center_lon_deg=_CONTINENTAL_LON,
        half_width_m=900_000.0,
        targets=5500,
        duration_s=600.0,
        curved=True,
    ),
    "formation": Scenario(
        name="formation",
        description="3 en-route radars, 30 aircraft in formation 2 km apart, 0.3-0.4 deg "
        "azimuth biases, one radar with Pd 0.75",
        radars=_formation_radars(),
        center_lat_deg=_FORMATION_LAT,
        center_lon_deg=_FORMATION_LON,
        half_width_m=150_000.0,  # holds the whole flight: no aircraft leaves the formation
        targets=30,
        speed_mps=(_FORMATION_SPEED_MPS, _FORMATION_SPEED_MPS),
        altitude_m=(9_000.0, 10_000.0),
        duration_s=_FORMATION_DURATION_S,
        formation=_formation(),
    ),
}


# Two groups of the formation scenario's aircraft (half each, its radars, lattice, speed and
# duration) in two more shapes, for the formation study (topofusion_lab.evaluation.formation):
#
# * crossing: the groups fly straight through each other, their headings ``crossing_deg``
#   apart on either side of the formation's 070, both centred on the scenario centre at half
#   time (at 40 deg and 230 m/s they close at 157 m/s: groups a few km across pass in under a minute);
# * merging: the groups converge from either side, ``converge_deg`` off 070, and at
#   ``merge_at_s`` each turns to 070 exactly where it makes one lattice with the other (left
#   and right halves of the formation's columns, neighbours one spacing apart), then they fly
#   on as one formation (the formation scenario's track from then on).
def formation_crossing(spacing_m: float = 2_000.0, crossing_deg: float = 40.0, targets: int = 30) -> Scenario:
    """The formation scenario's aircraft as two groups crossing at the centre at half time."""
    base = SCENARIOS["formation"]
    assert base.duration_s is not None
    half = _FORMATION_SPEED_MPS * base.duration_s / 2.0
    groups = []
    for k, heading in enumerate(
        (
            _FORMATION_HEADING_DEG - crossing_deg / 2.0,
            _FORMATION_HEADING_DEG + crossing_deg / 2.0,
        )
    ):
        h = math.radians(heading)
        groups.append(
            FormationSpec(
                spacing_m=spacing_m,
                heading_deg=heading,
                speed_mps=_FORMATION_SPEED_MPS,
                start_east_m=-half * math.sin(h),
                start_north_m=-half * math.cos(h),
                count=targets // 2 if k == 0 else targets - targets // 2,
            )
        )
    return replace(
        base,
        name="formation-crossing",
        description=f"the formation as two groups crossing at {crossing_deg:.0f} deg",
        targets=targets,
        formation=None,
        formations=tuple(groups),
    )


def formation_merging(
    spacing_m: float = 2_000.0, converge_deg: float = 15.0, merge_at_s: float = 240.0, targets: int = 30
) -> Scenario:
    """The formation scenario's aircraft as two groups converging into one lattice."""
    base = SCENARIOS["formation"]
    assert base.duration_s is not None
    cols = math.ceil(math.sqrt(targets))
    cols += cols % 2  # an even count: half the columns each
    h = math.radians(_FORMATION_HEADING_DEG)
    ahead, right = (math.sin(h), math.cos(h)), (math.cos(h), -math.sin(h))
    # the formation scenario's centre at merge_at_s
    along = _FORMATION_SPEED_MPS * (merge_at_s - base.duration_s / 2.0)
    groups = []
    for k, side in enumerate((-1.0, 1.0)):
        across = side * cols / 4.0 * spacing_m  # the centre of this half of the columns
        at_merge = (along * ahead[0] + across * right[0], along * ahead[1] + across * right[1])
        heading = _FORMATION_HEADING_DEG - side * converge_deg  # the left one heads right of 070
        hg = math.radians(heading)
        travel = _FORMATION_SPEED_MPS * merge_at_s
        groups.append(
            FormationSpec(
                spacing_m=spacing_m,
                heading_deg=heading,
                speed_mps=_FORMATION_SPEED_MPS,
                start_east_m=at_merge[0] - travel * math.sin(hg),
                start_north_m=at_merge[1] - travel * math.cos(hg),
                count=targets // 2 if k == 0 else targets - targets // 2,
                columns=cols // 2,
                lattice_heading_deg=_FORMATION_HEADING_DEG,
                turn_at_s=merge_at_s,
                turn_heading_deg=_FORMATION_HEADING_DEG,
            )
        )
    return replace(
        base,
        name="formation-merging",
        description=f"the formation as two groups converging at {converge_deg:.0f} deg, one lattice "
        f"from {merge_at_s:.0f} s",
        targets=targets,
        formation=None,
        formations=tuple(groups),
    )


#: The scenario of ``topofusion demo`` (runs until stopped).
DEMO = replace(SCENARIOS["two-radar"], name="demo", duration_s=None)


def get_scenario(name: str) -> Scenario:
    if name == "demo":
        return DEMO
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose from: demo, {', '.join(SCENARIOS)}") from None
