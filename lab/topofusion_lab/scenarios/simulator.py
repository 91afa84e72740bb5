"""A scanning multi-radar simulator with biased, noisy sensors (data time, seeded).

Targets fly straight at constant velocity in a local east-north-up frame around the
scenario centre; a target leaving the area is replaced by a new one entering it (new
``truth_id``; ``Scenario.respawn`` says where), so a scenario can run for ever.  Each radar's
antenna turns clockwise from north once per ``scan_period_s``; a target at azimuth ``az`` is
seen at ``scan_start + az / 360 * period`` with probability ``pd``.  Its plot is the true polar
position plus the radar's systematic bias (range offset and gain, azimuth and elevation
offsets) plus Gaussian noise (the sigmas of its site), stamped by the radar's clock (true time
plus its ``time_bias_s``).
Uniform clutter is added per sector.  The scan is reported in ``sectors`` batches.

A scenario with a ``formation`` (:class:`FormationSpec`) starts its targets together instead:
on a jittered lattice around one point, all with one heading and speed (see there); one with
``formations`` starts them as several such groups (crossing or merging formations), each of
which may turn once.

``generate(..., observe=f)`` calls ``f(t, ids, pos, vel)`` with every target's true state at
the start of each simulation step (evaluation only: the truth of a run).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from service.geo import Site, ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from service.pipeline.tracking_stage import to_geometry
from service.wire.keys import Keys
from service.wire.models import RadarSite


@dataclass(frozen=True)
class RadarSpec:
    radar_id: str
    latitude_deg: float
    longitude_deg: float
    altitude_m: float = 30.0
    range_sigma_m: float = 200.0
    azimuth_sigma_deg: float = 0.2
    elevation_sigma_deg: float = 0.2
    scan_period_s: float = 4.0
    #: Systematic errors (unknown to the service): added to every plot.
    range_bias_m: float = 0.0
    azimuth_bias_deg: float = 0.0
    elevation_bias_deg: float = 0.0
    #: Range gain (ppm): the reported range is the true range x (1 + range_gain_ppm 1e-6), plus
    #: ``range_bias_m`` and noise.
    range_gain_ppm: float = 0.0
    #: Time-stamp bias (s): the radar's clock runs this far ahead of true time, so a plot seen
    #: at true time ``T`` is stamped ``T + time_bias_s`` (and so is each batch's ``time_s``).
    time_bias_s: float = 0.0
    pd: float = 0.95
    clutter_per_scan: float = 0.0
    max_range_m: float = 350_000.0
    sectors: int = 8
    two_d: bool = False  # a 2-D radar sends altitude_m (e.g. Mode C) instead of elevation
    #: ASTERIX data source identifier (sent with the site; the ASTERIX bridge maps by it).
    sac: int | None = None
    sic: int | None = None
    #: A secondary (Mode S) radar: each target's plots carry its Mode 3/A code, Mode S address
    #: and flight level (:func:`identity_of`); clutter carries none.
    identity: bool = False
    #: Identity errors of a secondary radar (performance assessment): the share of plots whose
    #: Mode 3/A code is another one, and whose flight level is off by 3 to 20 FL.
    mode_3a_error: float = 0.0
    mode_c_error: float = 0.0

    def wire_site(self) -> RadarSite:
        """The radar's ``RadarSite`` (the fields of the same names; biases stay unknown)."""
        return RadarSite(**{name: getattr(self, name) for name in RadarSite.model_fields})

    def site(self) -> Site:
        """The numerics' view of :meth:`wire_site`, as the service builds it."""
        return to_geometry(self.wire_site())

    def site_message(self) -> dict[str, Any]:
        return self.wire_site().model_dump(exclude_none=True)  # sac/sic only when set


@dataclass(frozen=True)
class AisSpec:
    """An AIS receiver reporting the true position of every ``stride``-th target."""

    source_id: str
    report_period_s: float = 10.0
    batch_period_s: float = 10.0
    stride: int = 1


@dataclass(frozen=True)
class AdsbSpec:
    """An ADS-B receiver: every ``stride``-th target reports its GNSS position and geometric
    height (errors ``position_sigma_m`` / ``height_sigma_m``, 1-sigma) every
    ``report_period_s``; one batch per ``batch_period_s``.  A share ``no_height`` of reports
    leaves the height out (null)."""

    source_id: str
    report_period_s: float = 1.0
    batch_period_s: float = 2.0
    stride: int = 1
    position_sigma_m: float = 10.0
    height_sigma_m: float = 15.0
    no_height: float = 0.0
    #: Of the targets ``stride`` picks, this share is equipped (chosen by the aircraft's name,
    #: :func:`equipped`, as equipage belongs to the aircraft); 1: all of them.
    equipped_share: float = 1.0
    #: Reports also carry the target's Mode 3/A code and barometric flight level
    #: (``mode_3a``, ``flight_level``: the true height as a flight level, 1/4 FL steps).
    identity: bool = False


def equipped(name: str, share: float) -> bool:
    """Whether the aircraft ``name`` carries ADS-B when a ``share`` of all do: its number times
    the golden ratio, modulo 1, below ``share`` (evenly spread over the numbers, fixed per
    aircraft)."""
    return share >= 1.0 or (int(name[1:]) * 0.6180339887498949) % 1.0 < share


def identity_of(name: str) -> tuple[str, str]:
    """A simulated target's Mode 3/A code and Mode S address (a function of its name, the way
    a transponder's codes belong to the aircraft): what the target transmits, not truth labels."""
    number = int(name[1:])
    return f"{(number * 37) % 4096:04o}", f"{(0x3C0000 + number * 7919) % 0x1000000:06x}"


def mmsi_of(name: str) -> str:
    """A simulated target's AIS MMSI (a function of its name, as :func:`identity_of`)."""
    return f"{412000000 + int(name[1:]):09d}"


@dataclass(frozen=True)
class FormationSpec:
    """All of a scenario's targets start as one formation: ``Scenario.targets`` aircraft on a
    square lattice of ``spacing_m`` (rows of ``ceil(sqrt(N))`` abreast, across the heading, one
    behind the other, the last row partly filled; the lattice centred on the formation's
    centre), each moved by a uniform jitter of up to ``jitter`` x ``spacing_m`` along and
    across; all fly
    ``heading_deg`` (clockwise from north) at ``speed_mps``, at altitudes drawn from
    ``Scenario.altitude_m``.  The formation's centre starts ``start_east_m`` / ``start_north_m``
    from the scenario centre.  A target that leaves the area is replaced as ``Scenario.respawn``
    says (no longer in formation): make the area hold the formation's whole flight.
    """

    spacing_m: float = 2_000.0
    jitter: float = 0.25
    heading_deg: float = 0.0
    speed_mps: float = 230.0
    start_east_m: float = 0.0
    start_north_m: float = 0.0
    #: Of ``Scenario.formations`` (several groups): the aircraft of this group (``None``: all of
    #: ``Scenario.targets``, the one formation of ``Scenario.formation``).
    count: int | None = None
    #: Aircraft abreast (``None``: ``ceil(sqrt(N))``).
    columns: int | None = None
    #: The lattice's orientation (its rows across this heading; ``None``: ``heading_deg``).
    lattice_heading_deg: float | None = None
    #: At this data time (s since the start) the whole group turns, at once, to
    #: ``turn_heading_deg`` at ``turn_speed_mps`` (``None``: the heading and speed it has).
    turn_at_s: float | None = None
    turn_heading_deg: float | None = None
    turn_speed_mps: float | None = None

    def __post_init__(self) -> None:
        if not (self.spacing_m > 0 and 0 <= self.jitter < 0.5):
            raise ValueError(f"formation: spacing_m must be > 0 and jitter in [0, 0.5), not {self}")
        if (self.count is not None and self.count < 0) or (self.columns is not None and self.columns < 1):
            raise ValueError(f"formation: count must be >= 0 and columns >= 1, not {self}")

    def turn_velocity(self) -> tuple[float, float]:
        """East and north velocity after the turn (m/s)."""
        h = np.radians(self.heading_deg if self.turn_heading_deg is None else self.turn_heading_deg)
        v = self.speed_mps if self.turn_speed_mps is None else self.turn_speed_mps
        return float(v * np.sin(h)), float(v * np.cos(h))


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    radars: tuple[RadarSpec, ...]
    center_lat_deg: float
    center_lon_deg: float
    #: Half-width of the square area targets fly in (m, east and north of the centre).
    half_width_m: float = 150_000.0
    targets: int = 40
    speed_mps: tuple[float, float] = (150.0, 260.0)
    altitude_m: tuple[float, float] = (3_000.0, 11_000.0)
    #: Duration in data seconds; ``None`` runs until stopped.
    duration_s: float | None = 600.0
    start_time_s: float = 1_763_769_600.0  # 2025-11-22T00:00:00Z
    #: Cooperative reporters (AIS) of the targets' true positions.
    ais: tuple[AisSpec, ...] = ()
    #: ADS-B receivers of the targets' own positions and heights.
    adsb: tuple[AdsbSpec, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)
    #: Where a target that left the area is replaced.  ``"edge"`` (every catalog scenario):
    #: on the circle inscribed in the area, heading for its centre within +-34 deg, so the
    #: traffic converges and the targets gather towards the centre over the first crossing
    #: times (national: after the first hour the inner quarter of the area holds about 1.75
    #: times as many as at the start, and the radars see a third more).  ``"uniform"``: the
    #: targets stay uniformly spread with isotropic headings and the initial speeds, in
    #: expectation at every moment (a stationary load, for soak tests): the new target enters
    #: at a uniformly random point of the square's boundary with the heading and speed of the
    #: flow a uniform population sends across it (angle to the inward normal with density
    #: ~cos, speed with density ~speed: faster targets cross more often).  A new target at a
    #: random point inside the area would not do: targets born inside and not yet gone pile
    #: up towards the centre (national: +17 % in the inner quarter).
    respawn: Literal["edge", "uniform"] = "edge"
    #: The targets start as one formation (``None``: each where and how ``_Targets`` draws it).
    formation: FormationSpec | None = None
    #: ... or as several groups, each a formation of its ``count`` aircraft (the counts add up
    #: to ``targets``; ``formation`` then ``None``): crossing or merging formations.
    formations: tuple[FormationSpec, ...] = ()
    #: The area lies on the earth's curve: a target's east and north offsets are distances
    #: along the surface from the centre and its height is above the ellipsoid.  ``False``
    #: (every scenario a few hundred km across): on the centre's tangent plane, whose height
    #: grows by d^2 / 2R off the centre (11 km at 370 km, 64 km at 900 km), too much for an
    #: area a continent wide.
    curved: bool = False

    def __post_init__(self) -> None:
        if self.respawn not in ("edge", "uniform"):
            raise ValueError(f"respawn must be 'edge' or 'uniform', not {self.respawn!r}")
        if self.formations:
            counts = [f.count for f in self.formations]
            if self.formation is not None or None in counts or sum(c or 0 for c in counts) != self.targets:
                raise ValueError(
                    "formations: each group needs its count, the counts must add up to targets, "
                    "and formation must be None"
                )


@dataclass(frozen=True)
class SimMessage:
    """One message to publish: ``kind`` is ``site``, ``plots``, ``ais`` or ``adsb``."""

    time_s: float
    kind: str
    radar_id: str
    body: dict[str, Any]


class _Targets:
    def __init__(self, sc: Scenario, rng: np.random.Generator) -> None:
        self.sc = sc
        self.rng = rng
        self.count = 0
        n = sc.targets
        self.pos = np.zeros((n, 3))
        self.vel = np.zeros((n, 3))
        self.ids = np.empty(n, dtype=object)
        #: Data time of the targets' state (s since the start), and each target's turn (time,
        #: inf: none; east/north velocity after it): groups of ``Scenario.formations`` only.
        self.t = 0.0
        self.turn_at = np.full(n, np.inf)
        self.turn_vel = np.zeros((n, 2))
        if sc.formations:
            first = 0
            for f in sc.formations:
                assert f.count is not None
                self._spawn_formation(f, np.arange(first, first + f.count))
                first += f.count
        elif sc.formation is None:
            self._spawn(np.arange(n), inside=True)
        else:
            self._spawn_formation(sc.formation, np.arange(n))

    def _spawn_formation(self, f: FormationSpec, idx: np.ndarray) -> None:
        """The targets ``idx`` in formation ``f`` (see :class:`FormationSpec`)."""
        sc, rng, n = self.sc, self.rng, len(idx)
        if n == 0:
            return
        cols = int(np.ceil(np.sqrt(n))) if f.columns is None else f.columns
        rows = int(np.ceil(n / cols))
        k = np.arange(n)
        across = (k % cols - (cols - 1) / 2.0) * f.spacing_m
        along = ((rows - 1) / 2.0 - k // cols) * f.spacing_m  # first row in front
        along = along + rng.uniform(-f.jitter, f.jitter, n) * f.spacing_m
        across = across + rng.uniform(-f.jitter, f.jitter, n) * f.spacing_m
        h = np.radians(f.heading_deg)
        ahead, right = np.array([np.sin(h), np.cos(h)]), np.array([np.cos(h), -np.sin(h)])
        if f.lattice_heading_deg is None:
            l_ahead, l_right = ahead, right
        else:
            hl = np.radians(f.lattice_heading_deg)
            l_ahead, l_right = np.array([np.sin(hl), np.cos(hl)]), np.array([np.cos(hl), -np.sin(hl)])
        xy = (
            np.array([f.start_east_m, f.start_north_m]) + along[:, None] * l_ahead + across[:, None] * l_right
        )
        self.pos[idx, :2] = xy
        self.pos[idx, 2] = rng.uniform(*sc.altitude_m, n)
        self.vel[idx] = [f.speed_mps * ahead[0], f.speed_mps * ahead[1], 0.0]
        if f.turn_at_s is not None:
            self.turn_at[idx] = f.turn_at_s
            self.turn_vel[idx] = f.turn_velocity()
        for j in idx:
            self.count += 1
            self.ids[j] = f"T{self.count}"

    def _spawn(self, idx: np.ndarray, inside: bool) -> None:
        sc, rng, k = self.sc, self.rng, len(idx)
        if k == 0:
            return
        w = sc.half_width_m
        if not inside and sc.respawn == "uniform":
            xy, heading, speed = self._enter_uniform(k)
        else:
            heading = rng.uniform(0, 2 * np.pi, k)
            speed = rng.uniform(*sc.speed_mps, k)
            if inside:
                xy = rng.uniform(-w, w, (k, 2))
            else:  # enter on the inscribed circle, heading inwards (the heading drawn above is
                # replaced, and still drawn so that the random stream stays what it has been)
                edge_angle = rng.uniform(0, 2 * np.pi, k)
                xy = 0.98 * w * np.stack([np.sin(edge_angle), np.cos(edge_angle)], axis=1)
                heading = edge_angle + np.pi + rng.uniform(-0.6, 0.6, k)
        self.pos[idx, :2] = xy
        self.pos[idx, 2] = rng.uniform(*sc.altitude_m, k)
        self.vel[idx] = np.stack([speed * np.sin(heading), speed * np.cos(heading), np.zeros(k)], axis=1)
        self.turn_at[idx] = np.inf  # a new target flies straight
        for j in idx:
            self.count += 1
            self.ids[j] = f"T{self.count}"

    def _enter_uniform(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, headings and speeds of ``k`` targets crossing into the area as a uniform,
        isotropic population with the scenario's speed distribution does (``respawn="uniform"``).

        Through a piece of boundary, targets of speed ``v`` whose heading makes an angle ``a``
        with the inward normal cross at a rate ~ ``v cos(a)``: points uniform along the
        boundary (the four sides are equally long), ``sin(a)`` uniform in (-1, 1), ``v``
        drawn from the speed range with density ~ ``v``.  Each target then flies the chord
        such a population's targets fly, so the population keeps the initial distribution.
        """
        rng, w = self.rng, self.sc.half_width_m
        lo, hi = self.sc.speed_mps
        side = rng.integers(0, 4, k)  # east, north, west, south
        along = rng.uniform(-w, w, k)
        normal = np.array([1.5, 1.0, 0.5, 0.0])[side] * np.pi  # inward, clockwise from north
        heading = normal + np.arcsin(rng.uniform(-1.0, 1.0, k))
        speed = np.sqrt(lo**2 + rng.uniform(0.0, 1.0, k) * (hi**2 - lo**2))
        # on the boundary itself (a target is out only beyond it), already heading inwards
        x = np.select([side == 0, side == 2], [w, -w], along)
        y = np.select([side == 1, side == 3], [w, -w], along)
        return np.stack([x, y], axis=1), heading, speed

    def advance(self, dt: float) -> None:
        turning = np.flatnonzero(self.turn_at <= self.t + dt)
        if turning.size:  # fly to the turn at the old velocity, then on at the new one
            before = np.clip(self.turn_at[turning] - self.t, 0.0, dt)[:, None]
            old = self.vel[turning].copy()
            self.vel[turning, :2] = self.turn_vel[turning]
            self.pos[turning] += (old - self.vel[turning]) * before
            self.turn_at[turning] = np.inf
        self.pos += self.vel * dt
        self.t += dt
        out = np.any(np.abs(self.pos[:, :2]) > self.sc.half_width_m, axis=1)
        self._spawn(np.flatnonzero(out), inside=False)


#: Metres of the earth's surface per degree of latitude (a sphere; the sites are exact anyway).
_M_PER_DEG = 111_195.0


def surface_point(lat0: float, lon0: float, east_m: Any, north_m: Any) -> tuple[Any, Any]:
    """Latitude and longitude (deg) ``north_m`` along the meridian from ``(lat0, lon0)``, then
    ``east_m`` along that parallel (a sphere; broadcasts): where a curved scenario puts a target
    of those offsets."""
    lat = lat0 + np.asarray(north_m) / _M_PER_DEG
    return lat, lon0 + np.asarray(east_m) / (_M_PER_DEG * np.cos(np.radians(lat)))


def _ecef(sc: Scenario, enu: np.ndarray, center: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """ECEF of targets at east-north-up ``enu`` of the scenario's centre (:attr:`Scenario.curved`)."""
    if not sc.curved:
        return np.asarray(enu @ rot.T + center)
    lat, lon = surface_point(sc.center_lat_deg, sc.center_lon_deg, enu[..., 0], enu[..., 1])
    return geodetic_to_ecef(lat, lon, enu[..., 2])


#: ``observe(t, ids, pos, vel)`` of :func:`generate`: data seconds since the start, each target's
#: name, east-north-up position and velocity (m, m/s; copies) at ``t``.
Observer = Callable[[float, np.ndarray, np.ndarray, np.ndarray], None]


def generate(sc: Scenario, seed: int = 0, observe: Observer | None = None) -> Iterator[SimMessage]:
    """Site messages, then plot batches in data-time order (deterministic for ``seed``).

    ``observe``: called with the targets' true state at the start of every step, before the
    step's batches are yielded (evaluation only; it changes nothing of the stream)."""
    rng = np.random.default_rng(seed)
    targets = _Targets(sc, rng)
    center = geodetic_to_ecef(sc.center_lat_deg, sc.center_lon_deg, 0.0)
    rot = enu_rotation(sc.center_lat_deg, sc.center_lon_deg)
    sites = {r.radar_id: r.site() for r in sc.radars}
    seqs = {r.radar_id: 0 for r in sc.radars}
    for r in sc.radars:
        yield SimMessage(sc.start_time_s, "site", r.radar_id, r.site_message())
    # All radars share one base step: the shortest sector duration.
    step = min(r.scan_period_s / r.sectors for r in sc.radars)
    t = 0.0
    while sc.duration_s is None or t < sc.duration_s:
        t_next = t + step
        if observe is not None:
            observe(t, targets.ids.copy(), targets.pos.copy(), targets.vel.copy())
        batches = []
        for r in sc.radars:
            sector_len = r.scan_period_s / r.sectors
            # sectors of this radar that end within (t, t_next]
            k0 = int(np.floor(t / sector_len + 1e-9))
            k1 = int(np.floor(t_next / sector_len + 1e-9))
            for k in range(k0, k1):
                batches.append((round((k + 1) * sector_len, 9), r, k))
        batches.sort(key=lambda b: (b[0], b[1].radar_id))
        for end_time, r, k in batches:
            body = _sector_batch(r, sites[r.radar_id], k, targets, center, rot, t, rng, sc.start_time_s)
            seqs[r.radar_id] += 1
            body["seq"] = seqs[r.radar_id]
            yield SimMessage(sc.start_time_s + end_time, "plots", r.radar_id, body)
        for a in sc.ais:
            k0 = int(np.floor(t / a.batch_period_s + 1e-9))
            k1 = int(np.floor(t_next / a.batch_period_s + 1e-9))
            for k in range(k0, k1):
                seqs[a.source_id] = seqs.get(a.source_id, 0) + 1
                body = _ais_batch(a, targets, center, rot, t, (k + 1) * a.batch_period_s, sc.start_time_s)
                body["seq"] = seqs[a.source_id]
                yield SimMessage(body["time_s"], "ais", a.source_id, body)
        for b in sc.adsb:
            k0 = int(np.floor(t / b.batch_period_s + 1e-9))
            k1 = int(np.floor(t_next / b.batch_period_s + 1e-9))
            for k in range(k0, k1):
                seqs[b.source_id] = seqs.get(b.source_id, 0) + 1
                body = _adsb_batch(
                    b, targets, center, rot, t, (k + 1) * b.batch_period_s, sc.start_time_s, rng
                )
                body["seq"] = seqs[b.source_id]
                yield SimMessage(body["time_s"], "adsb", b.source_id, body)
        targets.advance(t_next - t)
        t = t_next


def generate_looped(sc: Scenario, seed: int = 0) -> Iterator[SimMessage]:
    """The scenario again and again, without end (``topofusion simulate --loop``).

    Each pass is :func:`generate` of the same scenario and seed (the same traffic), started
    ``duration_s`` of data time after the one before, so data time runs on; every source's
    ``seq`` goes on from the last pass's, so a service takes the passes as one stream (a ``seq``
    back at 1 would be a publisher's restart, and a repeated data time a duplicate).  The sites
    come once, at the start: they do not change from pass to pass.  A scenario without a
    duration runs for ever already (and one of no duration has nothing to repeat): it is
    :func:`generate` itself.
    """
    if sc.duration_s is None or sc.duration_s <= 0:
        yield from generate(sc, seed)
        return
    offset: dict[str, int] = {}
    k = 0
    while True:
        last: dict[str, int] = {}
        shifted = replace(sc, start_time_s=sc.start_time_s + k * sc.duration_s)
        for m in generate(shifted, seed):
            if m.kind == "site":
                if k == 0:
                    yield m
                continue
            seq = int(m.body["seq"]) + offset.get(m.radar_id, 0)
            last[m.radar_id] = seq
            yield SimMessage(m.time_s, m.kind, m.radar_id, {**m.body, "seq": seq})
        offset.update(last)
        k += 1


def wire_messages(sc: Scenario, seed: int, prefix: str = "fusion") -> Iterator[tuple[str, bytes]]:
    """``(key, JSON payload)`` of a scenario's messages in data-time order, as published."""
    keys = Keys(prefix)
    for m in generate(sc, seed):
        yield keys.input(m.kind, m.radar_id), json.dumps(m.body).encode()


def in_coverage(r: RadarSpec, range_m: np.ndarray, altitude_m: np.ndarray) -> np.ndarray:
    """Whether targets at ``range_m`` from radar ``r`` at ``altitude_m`` are within its reach:
    its maximum range and the radio horizon (4/3 earth: ``d_km = 4.12 (sqrt(h_radar_m) +
    sqrt(h_target_m))``); such a target is detected with probability ``r.pd`` a scan."""
    h_target = np.maximum(altitude_m, 0.0)
    horizon_m = 4120.0 * (np.sqrt(max(r.altitude_m, 0.0)) + np.sqrt(h_target))
    return np.asarray((range_m <= r.max_range_m) & (range_m <= horizon_m))


def _sector_batch(
    r: RadarSpec,
    site: Site,
    k: int,
    targets: _Targets,
    center: np.ndarray,
    rot: np.ndarray,
    t_now: float,
    rng: np.random.Generator,
    t0: float,
) -> dict[str, Any]:
    period, sectors = r.scan_period_s, r.sectors
    scan = k // sectors
    j = k % sectors
    az_lo, az_hi = 360.0 * j / sectors, 360.0 * (j + 1) / sectors
    scan_start = scan * period
    # true positions at the current step; refine each target to its detection time
    ecef_now = _ecef(targets.sc, targets.pos, center, rot)
    rng_true, az_true, _ = site.ecef_to_polar(ecef_now)
    t_det = scan_start + az_true / 360.0 * period
    pos_det = targets.pos + targets.vel * (t_det - t_now)[:, None]
    ecef = _ecef(targets.sc, pos_det, center, rot)
    rng_true, az_true, el_true = site.ecef_to_polar(ecef)
    in_sector = (az_true >= az_lo) & (az_true < az_hi)
    visible = in_coverage(r, rng_true, targets.pos[:, 2])
    seen = in_sector & visible & (rng.random(len(az_true)) < r.pd)
    idx = np.flatnonzero(seen)
    n = len(idx)
    rr = rng_true[idx] * (1.0 + r.range_gain_ppm * 1e-6) + r.range_bias_m + rng.normal(0, r.range_sigma_m, n)
    aa = az_true[idx] + r.azimuth_bias_deg + rng.normal(0, r.azimuth_sigma_deg, n)
    ee = el_true[idx] + r.elevation_bias_deg + rng.normal(0, r.elevation_sigma_deg, n)
    tt = scan_start + az_true[idx] / 360.0 * period + r.time_bias_s  # the radar's clock
    truth: list[str | None] = [str(x) for x in targets.ids[idx]]
    alt = ecef_to_geodetic(ecef[idx])[2]
    nc = rng.poisson(r.clutter_per_scan / sectors) if r.clutter_per_scan > 0 else 0
    if nc:
        ca = rng.uniform(az_lo, az_hi, nc)
        rr = np.concatenate([rr, rng.uniform(5_000.0, r.max_range_m, nc)])
        aa = np.concatenate([aa, ca])
        ee = np.concatenate([ee, rng.uniform(0.2, 6.0, nc)])
        tt = np.concatenate([tt, scan_start + ca / 360.0 * period + r.time_bias_s])
        alt = np.concatenate([alt, rng.uniform(0.0, 12_000.0, nc)])
        truth += [None] * nc
    order = rng.permutation(len(rr))  # plots inside a batch need not be sorted
    plots: dict[str, Any] = {
        "time_s": [round(t0 + float(x), 4) for x in tt[order]],
        "range_m": [round(float(x), 2) for x in rr[order]],
        "azimuth_deg": [round(float(x) % 360.0, 5) for x in aa[order]],
    }
    if r.two_d:
        plots["altitude_m"] = [round(float(x), 1) for x in alt[order]]
    else:
        plots["elevation_deg"] = [round(float(np.clip(x, -90, 90)), 5) for x in ee[order]]
    plots["truth_id"] = [truth[i] for i in order]
    if r.identity:
        codes = [identity_of(x) if x is not None else (None, None) for x in truth]
        fl = np.round(np.r_[alt[: len(idx)] / 30.48, np.full(nc, np.nan)] * 4.0) / 4.0  # ISA: FL = ft / 100
        if r.mode_3a_error > 0:
            wrong = rng.random(len(codes)) < r.mode_3a_error
            codes = [
                (f"{(int(c[0], 8) + 1 + int(rng.integers(4095))) % 4096:04o}", c[1]) if w and c[0] else c
                for c, w in zip(codes, wrong, strict=True)
            ]
        plots["mode_3a"] = [codes[i][0] for i in order]
        plots["mode_s"] = [codes[i][1] for i in order]
        if r.mode_c_error > 0:
            off = (rng.random(fl.size) < r.mode_c_error) * rng.choice([-1.0, 1.0], fl.size)
            fl = fl + off * rng.uniform(3.0, 20.0, fl.size)
        plots["flight_level"] = [None if np.isnan(fl[i]) else float(fl[i]) for i in order]
    return {
        "radar_id": r.radar_id,
        "seq": 0,
        "time_s": round(t0 + (k + 1) * period / sectors + r.time_bias_s, 6),
        "plots": plots,
    }


def _adsb_batch(
    b: AdsbSpec,
    targets: _Targets,
    center: np.ndarray,
    rot: np.ndarray,
    t_now: float,
    t_end: float,
    t0: float,
    rng: np.random.Generator,
) -> dict[str, Any]:
    """Reports of every ``stride``-th target at each report time in the batch period."""
    idx = np.arange(0, len(targets.ids), b.stride)
    if b.equipped_share < 1.0:
        idx = idx[np.array([equipped(str(targets.ids[i]), b.equipped_share) for i in idx], dtype=bool)]
    times = np.arange(t_end - b.batch_period_s + b.report_period_s, t_end + 1e-9, b.report_period_s)
    rows_t: list[float] = []
    rows_id: list[str] = []
    rows_lat: list[float] = []
    rows_lon: list[float] = []
    rows_alt: list[float | None] = []
    rows_m3a: list[str] = []
    rows_fl: list[float] = []
    for tr in times:
        enu = targets.pos[idx] + targets.vel[idx] * (tr - t_now)
        if b.identity:
            true_alt = np.atleast_1d(ecef_to_geodetic(_ecef(targets.sc, enu, center, rot))[2])
            rows_fl += [round(float(a) / 30.48 * 4.0) / 4.0 for a in true_alt]
            rows_m3a += [identity_of(str(targets.ids[i]))[0] for i in idx]
        enu = enu + rng.normal(0.0, 1.0, enu.shape) * [
            b.position_sigma_m,
            b.position_sigma_m,
            b.height_sigma_m,
        ]
        lat, lon, alt = ecef_to_geodetic(_ecef(targets.sc, enu, center, rot))
        dropped = rng.random(len(idx)) < b.no_height
        rows_t += [round(t0 + float(tr), 3)] * len(idx)
        rows_id += [identity_of(str(targets.ids[i]))[1] for i in idx]
        rows_lat += [round(float(x), 7) for x in lat]
        rows_lon += [round(float(x), 7) for x in lon]
        rows_alt += [
            None if d else round(float(a), 1) for a, d in zip(np.atleast_1d(alt), dropped, strict=True)
        ]
    reports: dict[str, Any] = {
        "time_s": rows_t,
        "icao24": rows_id,
        "latitude_deg": rows_lat,
        "longitude_deg": rows_lon,
        "altitude_m": rows_alt,
    }
    if b.identity:
        reports["mode_3a"], reports["flight_level"] = rows_m3a, rows_fl
    return {"source_id": b.source_id, "seq": 0, "time_s": round(t0 + t_end, 6), "reports": reports}


def _ais_batch(
    a: AisSpec, targets: _Targets, center: np.ndarray, rot: np.ndarray, t_now: float, t_end: float, t0: float
) -> dict[str, Any]:
    """Reports of every ``stride``-th target at each report time in the batch period."""
    idx = np.arange(0, len(targets.ids), a.stride)
    times = np.arange(t_end - a.batch_period_s + a.report_period_s, t_end + 1e-9, a.report_period_s)
    rows_t, rows_id, rows_lat, rows_lon = [], [], [], []
    for tr in times:
        enu = targets.pos[idx] + targets.vel[idx] * (tr - t_now)
        lat, lon, _ = ecef_to_geodetic(_ecef(targets.sc, enu, center, rot))
        rows_t += [round(t0 + float(tr), 3)] * len(idx)
        rows_id += [mmsi_of(str(targets.ids[i])) for i in idx]
        rows_lat += [round(float(x), 7) for x in lat]
        rows_lon += [round(float(x), 7) for x in lon]
    return {
        "source_id": a.source_id,
        "seq": 0,
        "time_s": round(t0 + t_end, 6),
        "reports": {"time_s": rows_t, "mmsi": rows_id, "latitude_deg": rows_lat, "longitude_deg": rows_lon},
    }
