"""Pydantic models of every payload of the contract (docs/contract.md): the only wire definitions.

Input models (``RadarSite``, ``PlotBatch``, ``AisBatch``, ``AdsbBatch``) carry all of the contract's
validation rules; :func:`rejection_reason` maps a pydantic error onto the contract's
``Rejection.reason`` vocabulary so that one model gives both the JSON Schema and the checks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    ValidationError,
    model_validator,
)
from pydantic_core import PydanticCustomError

from service.wire.packed import PACKED_PATTERN, unpack_floats
from service.wire.vocabulary import ID_PATTERN, PairBasis, RejectionReason

#: At most this many plots (or AIS reports) per batch.
MAX_BATCH_ITEMS = 100_000
#: Payloads above this many bytes are rejected (``too_large``) before parsing.  A full batch
#: of 100 000 plots with truth ids is about 9 MB of JSON.
MAX_PAYLOAD_BYTES = 16 * 1024 * 1024

SourceId = Annotated[str, Field(pattern=ID_PATTERN, description="matches [A-Za-z0-9_-]{1,64}")]
#: Plausibility bounds that keep hostile but finite numbers out of the numerics (a range of
#: 1e156 m overflows the covariance maths; a time of 1e300 s would stop every radar's clock).
#: Latest accepted time: 2286-11-20, the end of 10-digit Unix seconds.
MAX_TIME_S = 1e10
#: Accepted slant ranges: 1 m (no radar measures closer; a denormal range overflows the
#: geometry) to 10 000 km (far beyond any radar horizon).
MIN_RANGE_M, MAX_RANGE_M = 1.0, 1e7
#: Accepted heights above the ellipsoid (plots and sites): deepest ocean to 1 000 km.
MIN_ALTITUDE_M, MAX_ALTITUDE_M = -12_000.0, 1_000_000.0
#: A plot may be stamped at most this long after its batch's ``time_s`` (clock jitter).
PLOT_TIME_TOLERANCE_S = 1.0

TimeS = Annotated[
    StrictFloat,
    Field(ge=0, le=MAX_TIME_S, allow_inf_nan=False, description="seconds since the Unix epoch, UTC"),
]
Range = Annotated[StrictFloat, Field(ge=MIN_RANGE_M, le=MAX_RANGE_M, allow_inf_nan=False)]
Altitude = Annotated[StrictFloat, Field(ge=MIN_ALTITUDE_M, le=MAX_ALTITUDE_M, allow_inf_nan=False)]
Azimuth = Annotated[StrictFloat, Field(ge=0, lt=360, allow_inf_nan=False)]
Elevation = Annotated[StrictFloat, Field(ge=-90, le=90, allow_inf_nan=False)]
Latitude = Annotated[StrictFloat, Field(ge=-90, le=90, allow_inf_nan=False)]
Longitude = Annotated[StrictFloat, Field(ge=-180, le=180, allow_inf_nan=False)]
#: Plausible 1-sigma measurement errors and scan periods of a radar (sites): wide enough for any
#: real radar (a range sigma of tens to hundreds of metres, angles of hundredths to tenths of a
#: degree, scans of 1 to 20 s), narrow enough to keep the numerics sane: a sigma of 1e308
#: overflows a plot's covariance (every track of the radar NaN), a denormal one takes every
#: plot as exact (the radar's tracks break up), a scan period of a nanosecond deletes every track
#: at once.
MIN_RANGE_SIGMA_M, MAX_RANGE_SIGMA_M = 0.1, 10_000.0
MIN_ANGLE_SIGMA_DEG, MAX_ANGLE_SIGMA_DEG = 1e-4, 10.0
MIN_SCAN_PERIOD_S, MAX_SCAN_PERIOD_S = 0.1, 600.0
RangeSigma = Annotated[StrictFloat, Field(ge=MIN_RANGE_SIGMA_M, le=MAX_RANGE_SIGMA_M, allow_inf_nan=False)]
AngleSigma = Annotated[
    StrictFloat, Field(ge=MIN_ANGLE_SIGMA_DEG, le=MAX_ANGLE_SIGMA_DEG, allow_inf_nan=False)
]
ScanPeriod = Annotated[StrictFloat, Field(ge=MIN_SCAN_PERIOD_S, le=MAX_SCAN_PERIOD_S, allow_inf_nan=False)]
#: Largest accepted ``seq``: a signed 64-bit integer (what every publisher's counter fits in).
MAX_SEQ = 2**63 - 1
Seq = Annotated[StrictInt, Field(ge=0, le=MAX_SEQ)]
#: An ASTERIX data source identifier octet (SAC or SIC, I048/010, I034/010).
SourceOctet = Annotated[StrictInt, Field(ge=0, le=255)]
#: Mode 3/A code: 4 octal digits (contract §4.1).
Mode3A = Annotated[str, Field(pattern=r"^[0-7]{4}$")]
#: ICAO 24-bit aircraft address: 6 lower-case hex digits (Mode S, ADS-B ``icao24``).
Icao24 = Annotated[str, Field(pattern=r"^[0-9a-f]{6}$")]
#: The longest ``plots.truth_id`` (characters): a simulator's aircraft name; without a bound a
#: batch of 300 000-character names held hundreds of MB in the plot window.
MAX_TRUTH_ID_CHARS = 64
TruthId = Annotated[str, Field(max_length=MAX_TRUTH_ID_CHARS)]
#: Barometric flight level (FL = 100 ft): the valid ranges of ASTERIX I048/090 (-12 to 1270)
#: and I021/145 (-15 to 1500), with a little room below.
MIN_FLIGHT_LEVEL, MAX_FLIGHT_LEVEL = -20.0, 1500.0
FlightLevel = Annotated[StrictFloat, Field(ge=MIN_FLIGHT_LEVEL, le=MAX_FLIGHT_LEVEL, allow_inf_nan=False)]


class WireModel(BaseModel):
    """Base of input models: unknown fields are ignored (the contract may grow)."""

    model_config = ConfigDict(extra="ignore", frozen=True)


class ColumnsModel(WireModel):
    """Base of columnar models: every column present has the length of the others."""

    @model_validator(mode="after")
    def _check_lengths(self) -> ColumnsModel:
        return _equal_lengths(self)


class RadarSite(WireModel):
    """A radar's position and random (not systematic) 1-sigma errors."""

    radar_id: SourceId
    latitude_deg: Latitude
    longitude_deg: Longitude
    altitude_m: Altitude = 0.0
    range_sigma_m: RangeSigma = 200.0
    azimuth_sigma_deg: AngleSigma = 0.2
    elevation_sigma_deg: AngleSigma = 0.2
    scan_period_s: ScanPeriod = 4.0
    sac: SourceOctet | None = Field(default=None, description="ASTERIX system area code (I048/010)")
    sic: SourceOctet | None = Field(default=None, description="ASTERIX system identification code")


_Columns = TypeVar("_Columns", bound=BaseModel)


def _equal_lengths(model: _Columns, names: Sequence[str] | None = None) -> _Columns:
    """A columnar model's columns (``names``, default every field; absent optional ones aside)
    have one length."""
    fields = type(model).model_fields if names is None else names
    columns: dict[str, Sequence[object] | None] = {n: getattr(model, n) for n in fields}
    lengths = {name: len(col) for name, col in columns.items() if col is not None}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"columns must have equal lengths, got {lengths}")
    return model


class PlotColumnsModel(ColumnsModel):
    """Columnar plots: one array per field, all of equal length."""

    time_s: Annotated[list[TimeS], Field(max_length=MAX_BATCH_ITEMS)]
    range_m: Annotated[list[Range], Field(max_length=MAX_BATCH_ITEMS)]
    azimuth_deg: Annotated[list[Azimuth], Field(max_length=MAX_BATCH_ITEMS)]
    elevation_deg: Annotated[list[Elevation], Field(max_length=MAX_BATCH_ITEMS)] | None = None
    altitude_m: Annotated[list[Altitude | None], Field(max_length=MAX_BATCH_ITEMS)] | None = Field(
        default=None, description="height above the WGS-84 ellipsoid per plot (null: not known)"
    )
    truth_id: Annotated[list[TruthId | None], Field(max_length=MAX_BATCH_ITEMS)] | None = Field(
        default=None,
        description="simulation only: carried to tracks for evaluation, never read by algorithms "
        "(at most 64 characters each)",
    )
    mode_3a: Annotated[list[Mode3A | None], Field(max_length=MAX_BATCH_ITEMS)] | None = Field(
        default=None, description="Mode 3/A code per plot, 4 octal digits (null: none)"
    )
    mode_s: Annotated[list[Icao24 | None], Field(max_length=MAX_BATCH_ITEMS)] | None = Field(
        default=None, description="Mode S address per plot, 6 lower-case hex digits (null: none)"
    )
    flight_level: Annotated[list[FlightLevel | None], Field(max_length=MAX_BATCH_ITEMS)] | None = Field(
        default=None, description="barometric flight level per plot (FL = 100 ft; null: none)"
    )


class PlotBatch(WireModel):
    radar_id: SourceId
    seq: Seq
    time_s: TimeS
    plots: PlotColumnsModel

    @model_validator(mode="after")
    def _plots_not_after_batch(self) -> PlotBatch:
        """``time_s`` is the time up to which the radar has reported: no plot is later."""
        latest = max(self.plots.time_s, default=self.time_s)
        if latest > self.time_s + PLOT_TIME_TOLERANCE_S:
            raise PydanticCustomError(
                "out_of_range",
                "plot time {latest} is after the batch time_s {time_s} (+{tol} s)",
                {"latest": latest, "time_s": self.time_s, "tol": PLOT_TIME_TOLERANCE_S},
            )
        return self


class AisReportsModel(ColumnsModel):
    time_s: Annotated[list[TimeS], Field(max_length=MAX_BATCH_ITEMS)]
    mmsi: Annotated[list[Annotated[str, Field(pattern=r"^[0-9]{1,9}$")]], Field(max_length=MAX_BATCH_ITEMS)]
    latitude_deg: Annotated[list[Latitude], Field(max_length=MAX_BATCH_ITEMS)]
    longitude_deg: Annotated[list[Longitude], Field(max_length=MAX_BATCH_ITEMS)]


class AisBatch(WireModel):
    source_id: SourceId
    seq: Seq
    time_s: TimeS
    reports: AisReportsModel


class AdsbReportsModel(ColumnsModel):
    time_s: Annotated[list[TimeS], Field(max_length=MAX_BATCH_ITEMS)]
    icao24: Annotated[list[Icao24], Field(max_length=MAX_BATCH_ITEMS)]
    latitude_deg: Annotated[list[Latitude], Field(max_length=MAX_BATCH_ITEMS)]
    longitude_deg: Annotated[list[Longitude], Field(max_length=MAX_BATCH_ITEMS)]
    altitude_m: Annotated[list[Altitude | None], Field(max_length=MAX_BATCH_ITEMS)] | None = Field(
        default=None, description="geometric height above the WGS-84 ellipsoid (null: not reported)"
    )
    mode_3a: Annotated[list[Mode3A | None], Field(max_length=MAX_BATCH_ITEMS)] | None = Field(
        default=None, description="Mode 3/A code per report, 4 octal digits (null: none; CAT021 I021/070)"
    )
    flight_level: Annotated[list[FlightLevel | None], Field(max_length=MAX_BATCH_ITEMS)] | None = Field(
        default=None,
        description="barometric flight level per report (FL = 100 ft; null: none; CAT021 I021/145)",
    )


class AdsbBatch(WireModel):
    """ADS-B position reports (contract §4.2): each ``icao24`` is one bias-free reference track."""

    source_id: SourceId
    seq: Seq
    time_s: TimeS
    reports: AdsbReportsModel


# -- output models -------------------------------------------------------------------------


class OutModel(BaseModel):
    model_config = ConfigDict(extra="forbid")


#: How unambiguous a track's recent plot associations were (``Track.quality``).
#: A probability, e.g. a pair's score.
Probability = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
Quality = Annotated[StrictFloat, Field(ge=0.0, le=1.0, allow_inf_nan=False)]


class Track(OutModel):
    track_id: str
    status: Literal["tentative", "confirmed"]
    time_s: float
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    position_ecef_m: tuple[float, float, float]
    velocity_ecef_mps: tuple[float, float, float]
    plots: int
    truth_id: str | None = None
    mode_3a: str | None = Field(default=None, description="the latest Mode 3/A code of the track's plots")
    mode_s: str | None = Field(default=None, description="the latest Mode S address of the track's plots")
    quality: Quality | None = Field(
        default=None,
        description="how unambiguous the track's recent plot associations were (1 = every plot "
        "clearly its own); null when not known",
    )


class TrackBatch(OutModel):
    radar_id: str
    time_s: float
    tracks: list[Track]


class Pair(OutModel):
    track_a: str
    track_b: str
    status: Literal["tentative", "confirmed"]
    score: Annotated[
        float,
        Field(
            ge=0,
            le=1,
            description="probability that the pair is right, from its accumulated evidence "
            "(svd-topology; calibrated on simulated data, docs/evaluation/dense.md); other methods: "
            "the share of the last updates whose decision chose the pair",
        ),
    ]
    statistic: float | None = Field(description="test statistic of the method; null if none was computed")
    rotation_weight: float | None = Field(
        description="weight of the fitted rotation (SVD paper §1.5); null when the decision fitted no "
        "rotation (e.g. bias-compensated chi-square association of a track with too few neighbours)"
    )
    scale: float | None = Field(description="scale of the fitted similarity; null when none was fitted")
    neighbors: int = Field(description="neighbours matched by the topology fit; 0 when no fit was made")
    hits: int
    first_time_s: float
    last_time_s: float
    basis: PairBasis | None = Field(
        default=None,
        description="what the latest decision rested on: the topology match of one update, the "
        "bias-compensated test of one update once registered, the pair's accumulated history, or a "
        "bias-free reference source; null when the method does not say",
    )
    held: bool = Field(
        default=False,
        description="a tentative pair that was confirmed and is held: its evidence turned against "
        'it while a track was contested (docs/correlation.md, "Held pairs"); false otherwise',
    )


class PairSet(OutModel):
    radar_a: str
    radar_b: str
    time_s: float
    method: str
    pairs: list[Pair]


class SystemTrackMember(OutModel):
    radar_id: str = Field(description="a radar id or a reference source's id")
    track_id: str


class SystemTrack(OutModel):
    """One target's fused, bias-compensated state (contract §4.4)."""

    system_track_id: str = Field(
        description="unique, never reused; stays with the target while any member lives"
    )
    status: Literal["tentative", "confirmed"]
    time_s: float
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    position_ecef_m: tuple[float, float, float]
    velocity_ecef_mps: tuple[float, float, float]
    position_sigma_m: float = Field(description="RMS position error per axis, sqrt(trace(P) / 3)")
    members: list[SystemTrackMember]


class SystemTrackBatch(OutModel):
    time_s: float | None = Field(description="data time of the system tracks; null before the first")
    system_tracks: list[SystemTrack]


class Rejection(OutModel):
    key: str
    radar_id: str | None = None
    reason: RejectionReason
    detail: str
    time_s: float | None = Field(
        default=None,
        description="when the service received the message (its wall clock; in an offline replay, "
        "the recorded time of receipt)",
    )


# -- worker-to-worker payloads (partitioned workers, docs/contract.md "Scale-out") -----------

#: At most this many tracks in one ``TrackStates`` (a radar's whole table).
MAX_TRACKS = 100_000
#: Bound on ECEF coordinates (m) and velocities (m/s) a peer may send: far beyond the Earth.
MAX_ECEF_M = 1e8
Finite = Annotated[float, Field(allow_inf_nan=False)]
Ecef = Annotated[float, Field(ge=-MAX_ECEF_M, le=MAX_ECEF_M, allow_inf_nan=False)]
Vec3 = tuple[Ecef, Ecef, Ecef]
#: A row-major 6x6 covariance of ``[position, velocity]`` (m, m/s).
Covariance = Annotated[list[Finite], Field(min_length=36, max_length=36)]
#: A row-major 3x3 covariance (m^2).
Covariance3 = Annotated[list[Finite], Field(min_length=9, max_length=9)]


#: A float column packed (:mod:`service.wire.packed`): the base64 of its little-endian doubles in
#: row order; at most a whole table's covariances.
Packed = Annotated[
    str,
    Field(
        pattern=PACKED_PATTERN,
        max_length=(MAX_TRACKS * 36 * 8 + 2) // 3 * 4,
        description="base64 (RFC 4648, padded) of the column's little-endian IEEE-754 doubles in row order",
    ),
]
#: The columns a ``TrackStates`` may pack: values per track, bounds (NaN: allowed, as null).
_PACKABLE: dict[str, tuple[int, float, float, bool]] = {
    "time_s": (1, 0.0, MAX_TIME_S, False),
    "position_ecef_m": (3, -MAX_ECEF_M, MAX_ECEF_M, False),
    "velocity_ecef_mps": (3, -MAX_ECEF_M, MAX_ECEF_M, False),
    "covariance": (36, -np.inf, np.inf, False),
    "quality": (1, 0.0, 1.0, True),
}


class TrackStateColumns(ColumnsModel):
    """One row per track: what correlation needs of a radar's tracks (state and covariance).
    The float columns are each a list of numbers or packed (:data:`Packed`)."""

    track_id: Annotated[list[str], Field(max_length=MAX_TRACKS)]
    confirmed: Annotated[list[StrictBool], Field(max_length=MAX_TRACKS)]
    time_s: Annotated[list[TimeS], Field(max_length=MAX_TRACKS)] | Packed
    position_ecef_m: Annotated[list[Vec3], Field(max_length=MAX_TRACKS)] | Packed
    velocity_ecef_mps: Annotated[list[Vec3], Field(max_length=MAX_TRACKS)] | Packed
    covariance: Annotated[list[Covariance], Field(max_length=MAX_TRACKS)] | Packed
    plots: Annotated[list[Annotated[StrictInt, Field(ge=0)]], Field(max_length=MAX_TRACKS)]
    truth_id: Annotated[list[str | None], Field(max_length=MAX_TRACKS)] | None = Field(
        default=None, description="simulation only, as in TrackBatch"
    )
    mode_3a: Annotated[list[str | None], Field(max_length=MAX_TRACKS)] | None = None
    mode_s: Annotated[list[str | None], Field(max_length=MAX_TRACKS)] | None = None
    quality: Annotated[list[Quality | None], Field(max_length=MAX_TRACKS)] | Packed | None = Field(
        default=None, description="as Track.quality; left out when no track has one; packed: NaN for null"
    )

    @model_validator(mode="after")
    def _check_lengths(self) -> TrackStateColumns:
        """The listed columns have one length, and each packed one holds that many rows of
        numbers within the list form's bounds."""
        names = [n for n in type(self).model_fields if not isinstance(getattr(self, n), str)]
        _equal_lengths(self, names)
        n = len(self.track_id)
        for name, (width, low, high, nan_ok) in _PACKABLE.items():
            text = getattr(self, name)
            if isinstance(text, str):
                values = unpack_floats(text, n * width)  # (ValueError: not valid)
                ok = np.isfinite(values) & (values >= low) & (values <= high)
                if not np.all(ok | np.isnan(values) if nan_ok else ok):
                    raise ValueError(f"{name}: numbers outside [{low}, {high}] or not finite")
        return self


class TrackStates(WireModel):
    """A radar's tracks as its owner's correlation sees them, for the workers that correlate
    its pairs: the whole table (``full``) or the rows changed since ``seq - 1`` and the ids
    that left (``removed``).  ``time_s`` is the data time the table is valid at."""

    radar_id: SourceId
    seq: Annotated[StrictInt, Field(ge=0, le=MAX_SEQ)]
    time_s: TimeS
    full: StrictBool
    count: Annotated[StrictInt, Field(ge=0, le=MAX_TRACKS)] | None = Field(
        default=None, description="tracks in the table once this message is applied (a check)"
    )
    removed: Annotated[list[str], Field(max_length=MAX_TRACKS)] = Field(default_factory=list)
    expiry: StrictBool = Field(
        default=False, description="the table the radar's tracks coasted to when it expired"
    )
    tracks: TrackStateColumns


class WorkerClock(WireModel):
    """A partitioned worker's progress, put after every input it took: how far it has
    released (every table up to ``released_s`` is published before this message) and the
    data clock of each radar it owns (what it has accepted)."""

    partition: Annotated[str, Field(pattern=r"^[0-9]{1,6}/[0-9]{1,6}$")]
    released_s: TimeS | None = None
    correlated_s: TimeS | None = Field(
        default=None,
        description="every correlation update up to this data time is done and its rows are published",
    )
    held: tuple[TimeS, SourceId] | None = Field(
        default=None,
        description="(progress) the release order's place (data time, radar id) of the oldest batch "
        "this worker holds for the aid of association: every table before it is published, none "
        "after (released_s is then just short of its data time)",
    )
    clocks: Annotated[dict[SourceId, TimeS], Field(max_length=MAX_TRACKS)] = Field(default_factory=dict)
    lone_clocks: Annotated[dict[SourceId, tuple[TimeS, TimeS]], Field(max_length=MAX_TRACKS)] = Field(
        default_factory=dict,
        description="(clock) the first and newest data time of each radar of this worker's whose clock "
        "is lone (no other source has confirmed it yet, docs/contract.md 7.1): another worker's radar "
        "agreeing with it confirms its own",
    )

    @model_validator(mode="after")
    def _check_lone_spans(self) -> WorkerClock:
        """A lone clock's first data time is not after its newest."""
        for rid, (first, newest) in self.lone_clocks.items():
            if first > newest:
                raise ValueError(
                    f"lone_clocks[{rid!r}]: first data time {first} is after the newest {newest}"
                )
        return self

    salt: int | None = Field(
        default=None,
        ge=0,
        le=2**31 - 1,
        description="the salt of the partition's hashing (TOPOFUSION_PARTITION_SALT), when not 0: "
        "every worker of a network needs the same",
    )
    packed_states: bool | None = Field(
        default=None,
        description="(progress) this worker reads TrackStates with packed float columns; a worker "
        "packs its own once every other worker has said so",
    )
    frame_states: bool | None = Field(
        default=None,
        description="(progress) this worker reads TrackStates as frames (docs/contract.md, "
        "'Scale-out'); a worker sends its own so once every other worker has said so",
    )
    frame_links: bool | None = Field(
        default=None,
        description="(progress) this worker reads PairLinks as frames (docs/contract.md, "
        "'Scale-out'); a worker sends its own so once every other worker has said so",
    )
    frame_rows: bool | None = Field(
        default=None,
        description="(progress) this worker reads RegistrationRows as frames (docs/contract.md, "
        "'Scale-out'); a worker sends its own so once every other worker has said so",
    )


class RegistrationRows(WireModel):
    """The confirmed-pair rows one pair update added to its registration memory (joint bias
    estimate): row ``k`` pairs track ``track_a[k]`` of ``source_a`` (a radar) with
    ``track_b[k]`` of ``source_b`` (a radar, or a bias-free reference when ``reference``)."""

    source_a: SourceId
    source_b: SourceId
    reference: bool = False
    time_s: TimeS
    track_a: Annotated[list[str], Field(max_length=MAX_TRACKS)]
    track_b: Annotated[list[str], Field(max_length=MAX_TRACKS)]
    p_a: Annotated[list[Vec3], Field(max_length=MAX_TRACKS)]
    p_b: Annotated[list[Vec3], Field(max_length=MAX_TRACKS)]
    s: Annotated[list[Covariance3], Field(max_length=MAX_TRACKS)]
    v: Annotated[list[Vec3], Field(max_length=MAX_TRACKS)] | None = Field(
        default=None,
        description="each pair's ECEF velocity (m/s, the mean of its two tracks'), which the "
        "time-bias term needs; absent: the rows say nothing of time biases",
    )

    @model_validator(mode="after")
    def _check_lengths(self) -> RegistrationRows:
        return _equal_lengths(self, ("track_a", "track_b", "p_a", "p_b", "s", "v"))


#: A pair correlator's registration holds its two radars' terms (one: a radar whose partner
#: is held as the reference).
MAX_REGISTRATION_RADARS = 2
#: Terms a radar's registration has: range offset (m), azimuth offset (rad), elevation offset
#: (rad), range gain (ppm), time bias (s).
REGISTRATION_TERMS = 5


class LinksRegistration(WireModel):
    """A pair correlator's own registration after the update its links follow (the aid of
    association): each of its radars' five terms (range offset m, azimuth offset rad,
    elevation offset rad, range gain ppm, time bias s) and their relative covariance, ``5 n``
    rows of ``5 n`` for ``n`` radars, in the order of ``radar_ids`` (each one of the pair's
    sources, once)."""

    radar_ids: Annotated[list[SourceId], Field(min_length=1, max_length=MAX_REGISTRATION_RADARS)]
    terms: list[Annotated[list[Finite], Field(min_length=REGISTRATION_TERMS, max_length=REGISTRATION_TERMS)]]
    covariance: list[list[Finite]]

    @model_validator(mode="after")
    def _check_shapes(self) -> LinksRegistration:
        n = len(self.radar_ids)
        if len(set(self.radar_ids)) != n:
            raise ValueError("registration: radar_ids must differ")
        if len(self.terms) != n:
            raise ValueError(f"registration: {len(self.terms)} rows of terms for {n} radars")
        size = REGISTRATION_TERMS * n
        if len(self.covariance) != size or any(len(row) != size for row in self.covariance):
            raise ValueError(f"registration: the covariance must be {size} rows of {size}")
        return self


class PairLinks(WireModel):
    """A pair's confirmed pairs after one of its updates, for the worker that draws the system
    tracks (worker 1 of a partitioned network): pair ``k`` is track ``track_a[k]`` of
    ``source_a`` with track ``track_b[k]`` of ``source_b``, at ``score[k]``.  The update
    followed the release of radar ``release``'s table at data time ``time_s``."""

    source_a: SourceId
    source_b: SourceId
    time_s: TimeS
    release: SourceId
    track_a: Annotated[list[str], Field(max_length=MAX_TRACKS)]
    track_b: Annotated[list[str], Field(max_length=MAX_TRACKS)]
    score: Annotated[list[Probability], Field(max_length=MAX_TRACKS)]
    #: The pair's registration then, sent while the aid of association is on (absent: not
    #: registered, or the aid is off).
    registration: LinksRegistration | None = None

    @model_validator(mode="after")
    def _check_lengths(self) -> PairLinks:
        return _equal_lengths(self, ("track_a", "track_b", "score"))


class ZenohInfo(OutModel):
    mode: str
    listen: list[str]
    connect: list[str]


class RadarStatus(OutModel):
    radar_id: str
    batches: int
    plots: int
    rejected: int
    lost_batches: int
    window_plots: int
    tracks_confirmed: int
    tracks_tentative: int
    last_time_s: float | None
    restarts: int = Field(default=0, description="publisher restarts recognised (seq back near 1)")
    window_evicted: int = Field(
        default=0, description="plots evicted from the window by its plot bound (oldest first)"
    )
    plots_coincident: int = Field(
        default=0,
        description="plots dropped as repeats of another plot of their batch: the same resolution "
        "cell (a small fraction of the site's sigmas) and Mode S address",
    )
    expired: bool = Field(default=False, description="no batch for the source expiry time of data")
    scan_period_observed_s: float | None = Field(
        default=None,
        description="the revisit period (s) the radar's plots show (null: not measured yet); "
        "the tracker counts in it where it contradicts the site's scan_period_s",
    )
    measurement_sigma_scale: float = Field(
        default=1.0,
        description="what the tracker multiplies the site's sigmas by: above 1 where the tracks' "
        "innovations show the radar's errors larger than declared",
    )
    aided_associations: int = Field(
        default=0,
        ge=0,
        description="associations of the radar's tracks whose plot was chosen by its distance from "
        "a confirmed partner on another radar (the engine configuration's tracking.aid; 0 with it off)",
    )
    pd_measured: float | None = Field(
        default=None,
        description="the detection probability the radar's established tracks show: the share of "
        "the looks due from them, one a scan each, in which they took a plot (null: not measured yet)",
    )
    misses_to_delete: int | None = Field(
        default=None,
        description="expected misses in a row that now delete an established confirmed track: "
        "tracking.manager.confirmed_max_misses (3), more on a radar whose measured Pd makes that "
        "run likely for an aircraft still there",
    )


class CorrelationTimings(OutModel):
    updates: int
    last_ms: float
    p50_ms: float
    p99_ms: float
    duration_buckets: dict[str, int] = Field(
        default_factory=dict,
        description="every update's time as a cumulative histogram: by upper bound in seconds "
        "(Prometheus le; the last, +Inf, counts every update), the updates that took at most it",
    )
    duration_sum_s: float = Field(default=0.0, description="the sum of every update's time (s)")
    pending: int = Field(
        default=0,
        description="radar messages the correlation stage has not answered yet (contract 5.1; "
        "0 when it runs in the service's own process)",
    )


class WorkerInfo(OutModel):
    """One worker of a partitioned network as this worker sees it."""

    partition: str = Field(description="K/N")
    alive: bool = Field(description="its Zenoh liveliness token is present")
    radars: list[str] = Field(description="radars it tracks (from its last status)")
    pair_sets: int = Field(description="radar pairs it correlates (from its last status)")
    status_age_s: float | None = Field(description="wall seconds since its last status; null: none yet")


class PartitionStatus(OutModel):
    """Who owns what in a partitioned network (``--partition K/N``)."""

    partition: str = Field(description="this worker, K/N")
    count: int
    bias_worker: int = Field(description="the partition that solves the joint bias estimate")
    salt: int = Field(default=0, description="the salt of the hashing (TOPOFUSION_PARTITION_SALT; 0: none)")
    workers: list[WorkerInfo]
    missing: list[int] = Field(
        description="partitions with no live worker: their radars and pairs are absent"
    )
    progress: dict[str, Any] = Field(
        default_factory=dict,
        description="this worker's data clocks: released_s (its tables), merged_s (every worker's, in "
        "order), correlated_s, held (tables waiting for a slower worker), state_gaps (track-state messages "
        "that could not be applied), reordered (tables that came after the merge had released a later "
        "one, from a worker no longer waited for, and were released out of order), aid_held (this "
        "worker's batches held until every worker's links and tables their aid of association reads "
        "are in: tracking.aid), aid_forced (batches tracked without waiting, as more than 2048 "
        "waited)",
    )


class IdentityPair(OutModel):
    radar_a: str
    radar_b: str
    pairs_with_mode_s: int
    mode_s_equal: int


class IdentityQuality(OutModel):
    """Confirmed pairs whose two tracks both carry a Mode S address, and how many agree."""

    pairs_with_mode_s: int
    mode_s_equal: int
    agreement: float | None = Field(description="mode_s_equal / pairs_with_mode_s; null when none")
    by_pair: list[IdentityPair] = Field(default_factory=list)


class QueueStatus(OutModel):
    """The ingest queue between Zenoh and the worker (contract §4.6)."""

    depth: int = Field(description="samples waiting for the worker")
    capacity: int = Field(description="bound in samples (TOPOFUSION_QUEUE_SIZE)")
    high_water: int = Field(description="the most samples ever waiting at once")
    dropped: int = Field(description="samples dropped on a full queue")
    bytes: int = Field(default=0, description="payload bytes waiting")
    capacity_bytes: int = Field(default=0, description="bound in payload bytes (TOPOFUSION_QUEUE_BYTES)")
    dropped_by_key: dict[str, int] = Field(
        default_factory=dict, description="the drops by key expression (at most 1024 keys, the rest summed)"
    )


class StateStatus(OutModel):
    """``--state-dir``: where the state is kept and how its writes go (contract §4.6)."""

    directory: str
    epoch: int = Field(description="this start's track-id epoch (0: the first start with the directory)")
    writes: int = Field(description="state files written (at the start, periodic, final)")
    failures: int = Field(description="writes that failed (e.g. a full disk; the next is tried)")
    data_time_s: float | None = Field(description="newest data clock of the state on disk; null: none")
    bytes: int = Field(description="size of the last file written")
    write_s: float = Field(description="seconds the last write took (encoding, writing, fsync)")


class FeedStatus(OutModel):
    """The feed on the wall clock (``service.pipeline.feed``): are the outputs still live."""

    stale: bool = Field(description="the data clock has not moved for TOPOFUSION_ENGINE__FEED__STALE_S")
    reason: str = Field(description="why the outputs are stale; empty when they are not")
    idle_s: float | None = Field(description="wall s since the data clock last moved; null: no data yet")
    refused_since_taken: int = Field(description="inputs refused since the last one taken")
    outages: int = Field(
        description="whole-feed outages that ended (the data clock jumped with a quorum, or came back "
        "after every source had expired)"
    )
    last_outage_s: float = Field(description="data-time length of the last such outage (s)")
    expired_by_wall_clock: int = Field(
        description="sources expired for silence on the wall clock while the data clock stood still"
    )
    behind_s: float | None = Field(
        default=None,
        description="data s the outputs (outputs_time_s) are behind the newest batch taken: what a "
        "flooding or lagging source costs the others (bounded by max_lag_s and the correlation's "
        "backlog); null before any output",
    )


class Status(OutModel):
    uptime_s: float
    method: str
    prefix: str
    zenoh: ZenohInfo
    radars: list[RadarStatus]
    pairs_confirmed: int
    pairs_tentative: int
    pairs_held: int = Field(default=0, description="of the tentative pairs, those held (Pair.held)")
    correlation: CorrelationTimings
    outputs_time_s: float | None = Field(
        default=None,
        description="contract 5.1: the data time up to which every published output (tracks, pairs, "
        "biases, system tracks) reflects every input the service has processed; null before any",
    )
    rejected: dict[str, int]
    queue: QueueStatus | None = Field(default=None, description="the ingest queue")
    feed: FeedStatus | None = Field(default=None, description="whether the outputs are still live")
    state: StateStatus | None = Field(default=None, description="with --state-dir only")
    partition: PartitionStatus | None = Field(
        default=None, description="partitioned workers only: who owns what, which partitions are missing"
    )
    identity: IdentityQuality | None = Field(
        default=None,
        description="identity quality (contract 4.1): confirmed pairs whose tracks both carry a Mode S "
        "address, and the share with equal addresses",
    )


class RadarInfo(RadarSite):
    """`GET /radars` entry: the site with its counters."""

    batches: int = 0
    plots: int = 0
    rejected: int = 0
    lost_batches: int = 0
    last_time_s: float | None = None


class BiasEstimate(OutModel):
    radar_id: str
    range_bias_m: float
    azimuth_bias_deg: float
    elevation_bias_deg: float
    pairs_used: int
    time_s: float
    range_bias_sigma_m: float | None = Field(
        default=None, description="1-sigma of range_bias_m (cluster-robust); null: not known"
    )
    azimuth_bias_sigma_deg: float | None = Field(
        default=None, description="1-sigma of azimuth_bias_deg (cluster-robust); null: not known"
    )
    elevation_bias_sigma_deg: float | None = Field(
        default=None, description="1-sigma of elevation_bias_deg (cluster-robust); null: not known"
    )
    range_gain_ppm: float | None = Field(
        default=None,
        description="range gain (ppm): reported range = true range x (1 + gain 1e-6) + range_bias_m; "
        "null: not estimated",
    )
    range_gain_sigma_ppm: float | None = Field(
        default=None, description="1-sigma of range_gain_ppm (cluster-robust); null: not estimated"
    )
    time_bias_s: float | None = Field(
        default=None,
        description="time-stamp bias (s): reported time = true time + time_bias_s; relative to the "
        "network's mean clock unless a bias-free reference (ADS-B, AIS) reaches the radar; "
        "null: not estimated",
    )
    time_bias_sigma_s: float | None = Field(
        default=None, description="1-sigma of time_bias_s (cluster-robust); null: not estimated"
    )


class BiasSet(OutModel):
    """The joint bias estimate as the worker that solves it publishes it (``{prefix}/biases``)."""

    time_s: float | None = Field(description="data time of the solve; null before the first")
    partition: str = Field(description="the worker that solved it, K/N")
    biases: list[BiasEstimate]


class PerformanceDetection(OutModel):
    pd: float | None = Field(description="detected / expected scans of the reference aircraft in coverage")
    pd_sigma: float | None = Field(description="1-sigma of pd (binomial)")
    expected: int = Field(description="scans in which a reference aircraft was inside the coverage")
    detected: int = Field(description="of those, scans with a plot of the aircraft")


class PerformancePosition(OutModel):
    rms_m: float | None = Field(description="horizontal error RMS after compensating the estimated biases")
    median_m: float | None = Field(description="median horizontal error after compensating the biases")
    rms_uncorrected_m: float | None = Field(description="horizontal error RMS before compensating")
    range_rms_m: float | None = Field(description="RMS of the range error about its mean (random part)")
    azimuth_rms_deg: float | None = Field(description="RMS of the azimuth error about its mean")
    plots: int = Field(description="plots behind these figures")


class PerformanceCode(OutModel):
    checked: int = Field(description="plots where both the plot and the reference carry the code")
    correct: int
    rate: float | None = Field(description="correct / checked")


class PerformanceRequirements(OutModel):
    pd_min: float
    mode_3a_min: float
    mode_c_min: float


class PerformanceVerdict(OutModel):
    pd: bool | None
    mode_3a: bool | None
    mode_c: bool | None


class RadarPerformance(OutModel):
    """A radar's performance against the paired bias-free references (contract §5.3)."""

    radar_id: str
    time_s: float | None = Field(description="data time the figures reach; null before any")
    window_s: float = Field(description="the sliding window of data time behind the figures")
    references: list[str] = Field(description="kinds of the references used: ads-b, ais")
    aircraft: int = Field(description="reference aircraft detected in the window")
    detection: PerformanceDetection
    position: PerformancePosition
    mode_3a: PerformanceCode
    mode_c: PerformanceCode = Field(description="flight level within 200 ft of the reference's")
    requirements: PerformanceRequirements
    verdict: PerformanceVerdict


# -- rejection reasons ---------------------------------------------------------------------

_REASON_BY_ERROR: dict[str, RejectionReason] = {
    "json_invalid": "malformed_json",
    "json_type": "malformed_json",
    "finite_number": "non_finite",
    "greater_than": "out_of_range",
    "greater_than_equal": "out_of_range",
    "less_than": "out_of_range",
    "less_than_equal": "out_of_range",
    "too_long": "too_large",
    "out_of_range": "out_of_range",
}
_PRIORITY: tuple[RejectionReason, ...] = (
    "malformed_json",
    "too_large",
    "non_finite",
    "out_of_range",
    "schema",
)


def rejection_reason(error: ValidationError) -> tuple[RejectionReason, str]:
    """The contract reason for a validation error, and a short human detail."""
    errors = error.errors(include_url=False)
    # (a payload that is JSON but not an object, e.g. ``[1, 2]``: the object the message needs
    # is missing at the root, contract §2.8's ``malformed_json``; a nested one is ``schema``)
    reasons = [
        "malformed_json"
        if e["type"] == "model_type" and not e["loc"]
        # a NaN or infinity where an integer belongs (``seq``) is as non-finite as in a float column
        else "non_finite"
        if isinstance(e.get("input"), float) and not math.isfinite(e["input"])
        else _REASON_BY_ERROR.get(e["type"], "schema")
        for e in errors
    ]
    best = min(reasons, key=_PRIORITY.index) if reasons else "schema"
    first = next(e for e, r in zip(errors, reasons, strict=True) if r == best)
    loc = ".".join(str(p) for p in first["loc"])
    detail = f"{loc}: {first['msg']}" if loc else str(first["msg"])
    if len(errors) > 1:
        detail += f" (+{len(errors) - 1} more)"
    return best, detail[:500]


#: Every payload of the contract, by schema file stem.
WIRE_MODELS: dict[str, type[BaseModel]] = {
    "RadarSite": RadarSite,
    "PlotBatch": PlotBatch,
    "AisBatch": AisBatch,
    "AdsbBatch": AdsbBatch,
    "TrackBatch": TrackBatch,
    "PairSet": PairSet,
    "SystemTrackBatch": SystemTrackBatch,
    "Rejection": Rejection,
    "Status": Status,
    "BiasEstimate": BiasEstimate,
    "RadarInfo": RadarInfo,
    "TrackStates": TrackStates,
    "RegistrationRows": RegistrationRows,
    "PairLinks": PairLinks,
    "BiasSet": BiasSet,
    "WorkerClock": WorkerClock,
    "RadarPerformance": RadarPerformance,
}
