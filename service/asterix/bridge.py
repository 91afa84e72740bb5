"""ASTERIX records to the contract's payloads (contract §4.3): no I/O, no Zenoh.

:class:`AsterixBridge` takes what the decoder made of each datagram and gives the messages to
publish:

* **CAT048** target reports become plots of the radar whose ``sac``/``sic`` the sites name.
  They are held per radar and sent as one ``PlotBatch`` at each **CAT034** sector crossing or
  north marker of that radar, with ``time_s`` = the message's time: the batch holds the plots
  detected up to that time (by their own time of day, so the order of blocks inside a
  datagram does not matter), later ones wait for the next message.  A radar that sends no
  CAT034 at all has its plots cut into batches of ``max_batch_s`` of data time.
* **CAT021** ADS-B reports become ``AdsbBatch`` messages of one source (``adsb_source_id``),
  one per ``adsb_batch_s`` of data time.
* Heights: a 3-D radar's measured height (I048/110, above mean sea level) is taken as
  ``altitude_m``: the geoid lies within about 100 m of the WGS-84 ellipsoid, well inside a
  radar's height error at range.  Without it, the flight level (I048/090, barometric) is
  turned into a height by the ICAO standard atmosphere (FL x 100 ft, ``altitude_from_fl``):
  real pressure altitudes differ from geometric heights by up to a few hundred metres, which
  moves a plot's ground position by only the height error times the elevation angle's sine.
  The flight level itself always goes into the ``flight_level`` column.  An ADS-B report's
  geometric height (I021/140, above the ellipsoid) is its ``altitude_m``; its barometric
  level is not used (the service carries an aircraft's last height forward).
* **Time**: ASTERIX stamps time of day; :class:`DayClock` puts it on the day nearest to a
  reference time (the capture's time stamp, else the latest time it made, else the start
  date), so a stream crosses midnight without a jump.

Records it cannot use are counted by cause (:attr:`AsterixBridge.unusable`).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from service.asterix.decode import Cat021Report, Cat048Report, Decoded
from service.wire.models import MAX_BATCH_ITEMS, MAX_FLIGHT_LEVEL, MIN_FLIGHT_LEVEL, RadarSite

#: Seconds in a day (ASTERIX time of day wraps at UTC midnight).
DAY_S = 86_400.0
#: One flight level in metres under the ICAO standard atmosphere (100 ft).
FL_M = 30.48
#: CAT034 message types that close a batch (I034/000): north marker, sector crossing.
BATCH_MESSAGES = frozenset({1, 2})


class DayClock:
    """Time of day to Unix seconds on the day nearest to a reference time (see module)."""

    def __init__(self, start_s: float | None = None) -> None:
        #: The date's midnight to start from when no other reference is known.
        self.start_s = start_s
        self.latest_s: float | None = None

    def time_s(self, tod_s: float, reference_s: float | None = None) -> float:
        ref = reference_s if reference_s is not None else self.latest_s
        if ref is None:
            ref = (self.start_s or 0.0) + tod_s
        day = math.floor((ref - tod_s) / DAY_S + 0.5)  # the day putting tod nearest to ref
        t = day * DAY_S + tod_s
        if self.latest_s is None or t > self.latest_s:
            self.latest_s = t
        return t


@dataclass(frozen=True)
class BridgeParams:
    #: Source id of the ADS-B reports (every CAT021 data source feeds this one source).
    adsb_source_id: str = "adsb"
    #: An ADS-B batch is sent per this many seconds of data time.
    adsb_batch_s: float = 1.0
    #: A radar without CAT034 messages has its plots cut into batches this long (data s).
    max_batch_s: float = 2.0
    #: Without a measured height, derive ``altitude_m`` from the flight level (module doc).
    altitude_from_fl: bool = True


_PLOT_COLUMNS = ("time_s", "range_m", "azimuth_deg", "altitude_m", "mode_3a", "mode_s", "flight_level")
_REQUIRED = frozenset({"time_s", "range_m", "azimuth_deg"})
_ADSB_COLUMNS = ("time_s", "icao24", "latitude_deg", "longitude_deg", "altitude_m")


@dataclass
class _Pending:
    """A radar's plots not yet sent, as columns, and its batch counter."""

    seq: int = 0
    last_batch_s: float = -math.inf
    columns: dict[str, list[Any]] = field(default_factory=lambda: {n: [] for n in _PLOT_COLUMNS})
    saw_sector: bool = False
    #: Earliest and latest time of the held plots (the cut without CAT034 needs no scan).
    first_s: float = math.inf
    last_s: float = -math.inf


@dataclass(frozen=True)
class Message:
    """One payload to publish: ``kind`` is ``plots`` or ``adsb``."""

    kind: str
    source_id: str
    body: dict[str, Any]


class AsterixBridge:
    def __init__(
        self, sites: list[RadarSite], params: BridgeParams | None = None, clock: DayClock | None = None
    ):
        self.params = params or BridgeParams()
        self.clock = clock or DayClock()
        self.radar_of: dict[tuple[int, int], str] = {}
        for s in sites:
            if s.sac is not None and s.sic is not None:
                other = self.radar_of.get((s.sac, s.sic))
                if other is not None:
                    raise ValueError(f"sites: SAC/SIC {s.sac}/{s.sic} of {s.radar_id} is already {other}'s")
                self.radar_of[(s.sac, s.sic)] = s.radar_id
        self._pending: dict[str, _Pending] = {}
        #: Radars without CAT034 so far that got plots in the current feed.
        self._unsectored: set[str] = set()
        self._adsb: dict[str, list[Any]] = {n: [] for n in _ADSB_COLUMNS}
        self._adsb_seq = 0
        self._adsb_start: float | None = None
        #: Records not used, by cause.
        self.unusable: Counter[str] = Counter()
        #: Records used, by category; messages made, by kind.
        self.used: Counter[str] = Counter()
        self.sent: Counter[str] = Counter()

    # -- input ---------------------------------------------------------------------------------
    def feed(self, decoded: Decoded, reference_s: float | None = None) -> list[Message]:
        """The messages ``decoded`` (one datagram's or chunk's records) completes;
        ``reference_s``: the capture's time stamp of the datagram, if any."""
        out: list[Message] = []
        for cause, n in decoded.errors.items():
            self.unusable[f"blocks_{cause}"] += n
        for rep in decoded.cat048:
            self._plot(rep, reference_s)
        for ads in decoded.cat021:
            self._adsb_report(ads, reference_s, out)
        for msg in decoded.cat034:
            if msg.message_type not in BATCH_MESSAGES:
                continue
            radar = self.radar_of.get((msg.sac, msg.sic))
            if radar is None or msg.tod_s is None:
                self.unusable["cat034_unknown_source" if radar is None else "cat034_no_time"] += 1
                continue
            pending = self._pending.setdefault(radar, _Pending())
            pending.saw_sector = True
            out += self._cut(radar, pending, self.clock.time_s(msg.tod_s, reference_s))
        for radar in self._unsectored:
            pending = self._pending[radar]
            if pending.saw_sector:
                continue
            if pending.last_s - pending.first_s >= self.params.max_batch_s:
                out += self._cut(radar, pending, pending.last_s)
        self._unsectored.clear()
        return out

    def _plot(self, r: Cat048Report, reference_s: float | None) -> None:
        radar = self.radar_of.get((r.sac, r.sic))
        if radar is None:
            self.unusable["cat048_unknown_source"] += 1
            return
        if r.rho_m is None or r.theta_deg is None or r.rho_m <= 0.0:
            self.unusable["cat048_no_position"] += 1
            return
        if r.tod_s is None:
            self.unusable["cat048_no_time"] += 1
            return
        fl = r.flight_level
        if fl is not None and not (MIN_FLIGHT_LEVEL <= fl <= MAX_FLIGHT_LEVEL):
            fl = None  # outside what I048/090 may validly hold: a garbled code
        alt = r.height_m
        if alt is None and fl is not None and self.params.altitude_from_fl:
            alt = fl * FL_M
        pending = self._pending.setdefault(radar, _Pending())
        t = self.clock.time_s(r.tod_s, reference_s)
        pending.first_s, pending.last_s = min(pending.first_s, t), max(pending.last_s, t)
        if not pending.saw_sector:
            self._unsectored.add(radar)
        cols = pending.columns
        cols["time_s"].append(t)
        cols["range_m"].append(r.rho_m)
        cols["azimuth_deg"].append(r.theta_deg % 360.0)
        cols["altitude_m"].append(alt)
        cols["mode_3a"].append(r.mode_3a)
        cols["mode_s"].append(r.mode_s)
        cols["flight_level"].append(fl)
        self.used["cat048"] += 1

    def _adsb_report(self, r: Cat021Report, reference_s: float | None, out: list[Message]) -> None:
        if r.icao24 is None:
            self.unusable["cat021_no_address"] += 1
            return
        if r.latitude_deg is None or r.longitude_deg is None:
            self.unusable["cat021_no_position"] += 1
            return
        if r.tod_s is None:
            self.unusable["cat021_no_time"] += 1
            return
        if not (-90.0 <= r.latitude_deg <= 90.0 and -180.0 <= r.longitude_deg <= 180.0):
            self.unusable["cat021_no_position"] += 1
            return
        t = self.clock.time_s(r.tod_s, reference_s)
        if self._adsb_start is None:
            self._adsb_start = t
        elif t - self._adsb_start >= self.params.adsb_batch_s or len(self._adsb["time_s"]) >= MAX_BATCH_ITEMS:
            out += self._send_adsb()
            self._adsb_start = t
        cols = self._adsb
        cols["time_s"].append(t)
        cols["icao24"].append(r.icao24)
        cols["latitude_deg"].append(r.latitude_deg)
        cols["longitude_deg"].append(r.longitude_deg)
        cols["altitude_m"].append(r.geometric_height_m)
        self.used["cat021"] += 1

    # -- output --------------------------------------------------------------------------------
    def _cut(self, radar: str, pending: _Pending, time_s: float) -> list[Message]:
        """Send the plots of ``radar`` up to ``time_s`` as one batch (also when none)."""
        cols = pending.columns
        t = cols["time_s"]
        take = [i for i, x in enumerate(t) if x <= time_s]
        if len(take) > MAX_BATCH_ITEMS:
            take = take[:MAX_BATCH_ITEMS]
        # a batch's time never goes back (a late or reordered sector message)
        batch_s = max(time_s, pending.last_batch_s)
        if len(take) == len(t):
            sent, pending.columns = cols, {n: [] for n in _PLOT_COLUMNS}
        else:
            keep = sorted(set(range(len(t))) - set(take))
            sent = {n: [c[i] for i in take] for n, c in cols.items()}
            pending.columns = {n: [c[i] for i in keep] for n, c in cols.items()}
        pending.seq += 1
        pending.last_batch_s = batch_s
        held = pending.columns["time_s"]
        pending.first_s, pending.last_s = (min(held), max(held)) if held else (math.inf, -math.inf)
        plots = {n: c for n, c in sent.items() if n in _REQUIRED or any(x is not None for x in c)}
        self.sent["plots"] += 1
        return [
            Message(
                "plots", radar, {"radar_id": radar, "seq": pending.seq, "time_s": batch_s, "plots": plots}
            )
        ]

    def _send_adsb(self) -> list[Message]:
        cols = self._adsb
        if not cols["time_s"]:
            return []
        self._adsb = {n: [] for n in _ADSB_COLUMNS}
        self._adsb_seq += 1
        reports = {n: c for n, c in cols.items() if n != "altitude_m" or any(x is not None for x in c)}
        body = {
            "source_id": self.params.adsb_source_id,
            "seq": self._adsb_seq,
            "time_s": max(cols["time_s"]),
            "reports": reports,
        }
        self.sent["adsb"] += 1
        return [Message("adsb", self.params.adsb_source_id, body)]

    def flush(self) -> list[Message]:
        """Everything still held, e.g. when the input ended or the bridge stops."""
        out: list[Message] = []
        for radar, pending in self._pending.items():
            if pending.columns["time_s"]:
                out += self._cut(radar, pending, pending.last_s)
        out += self._send_adsb()
        self._adsb_start = None
        return out
