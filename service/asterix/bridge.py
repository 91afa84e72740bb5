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
  one per ``adsb_batch_s`` of the bridge's clock (below; the data's own: of the reports'
  times): each holds the reports held up to that clock, a report stamped ahead of it (within
  the tolerance) waits for the batch of its time, and a batch's time never goes back.
* Heights: a 3-D radar's measured height (I048/110, above mean sea level) is taken as
  ``altitude_m``: the geoid lies within about 100 m of the WGS-84 ellipsoid, well inside a
  radar's height error at range.  Without it, the flight level (I048/090, barometric) is
  turned into a height by the ICAO standard atmosphere (FL x 100 ft, ``altitude_from_fl``):
  real pressure altitudes differ from geometric heights by up to a few hundred metres, which
  moves a plot's ground position by only the height error times the elevation angle's sine.
  The flight level itself always goes into the ``flight_level`` column.  An ADS-B report's
  geometric height (I021/140, above the ellipsoid) is its ``altitude_m``; its Mode 3/A code
  (I021/070) and barometric flight level (I021/145) go into the ``mode_3a`` and
  ``flight_level`` columns, which the performance assessment checks the radars' codes against
  (the service carries an aircraft's last height forward).
* **Time**: ASTERIX stamps time of day; :class:`DayClock` puts it on the day nearest to a
  reference time (the capture's time stamp, else the latest time it made, else the start
  date), so a stream crosses midnight without a jump.
* **The bridge's own clock** judges every time it derives: the capture's time stamp of the
  datagram (pcap, pcapng) or the wall clock at receipt (live UDP), passed in as
  ``reference_s``; without one (``--date``, raw files, a packet without a stamp) the data's own
  clock, the newest time it accepted, a datagram's records judged in time order (the decoder
  gives them category by category, and a file's chunk may span minutes).  A CAT048 plot,
  CAT034 message or CAT021 report more than ``max_time_ahead_s`` ahead of that clock or
  ``max_time_behind_s`` behind it is dropped (counted ``cat048_time_ahead`` etc.): one stray
  stamp must not move a radar's batch time (which never goes back, so it would stay there) nor
  hold an ADS-B batch open.  The data's own clock has nothing outside the data to go by, so
  ``rebase_after_records`` records in a row out of tolerance, agreeing with each other, move it
  to them (a recording that jumps or resumes after a pause, or a first record that was wrong).
* **Held records are bounded**: at most ``max_held_records`` plots and ADS-B reports together
  (each at most :data:`HELD_RECORD_BYTES` in memory, which bounds the bytes), and a radar's held
  plots span at most ``max_held_s`` of data time (an ADS-B batch is cut at ``adsb_batch_s``);
  the oldest go first, counted (``cat048_held_overflow``, ``cat048_held_too_long``,
  ``cat021_held_overflow``).  The bounds hold after each :meth:`AsterixBridge.feed`: inside one,
  a datagram's plots wait for its own sector messages (at most one datagram's records more).
* **Loss is not hidden**: when records of a source were dropped while held, or the caller says
  data of a source may have been lost before decoding (:meth:`AsterixBridge.mark_lost`: UDP
  datagrams dropped by the kernel or by the bridge's queue), the source's next batch skips one
  ``seq`` number, so the service counts one lost batch (``lost_batches``) per batch interval
  that lost data; a batch dropped outright (a failed put) leaves its number unused as well.

Records it cannot use are counted by cause (:attr:`AsterixBridge.unusable`).
"""

from __future__ import annotations

import math
import operator
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from service.asterix.decode import Cat021Report, Cat048Report, Decoded
from service.wire.models import (
    MAX_ALTITUDE_M,
    MAX_BATCH_ITEMS,
    MAX_FLIGHT_LEVEL,
    MIN_ALTITUDE_M,
    MIN_FLIGHT_LEVEL,
    RadarSite,
)

#: Seconds in a day (ASTERIX time of day wraps at UTC midnight).
DAY_S = 86_400.0
#: One flight level in metres under the ICAO standard atmosphere (100 ft).
FL_M = 30.48
#: CAT034 message types that close a batch (I034/000): north marker, sector crossing.
BATCH_MESSAGES = frozenset({1, 2})
#: Memory a held plot or ADS-B report takes at most (bytes): its column slots, floats and a
#: Mode S / ICAO address string; about 215 measured with every field set
#: (tests/asterix/test_asterix_limits.py checks it), so ``max_held_records`` x this bounds the
#: bytes held.
HELD_RECORD_BYTES = 256


class DayClock:
    """Time of day to Unix seconds on the day nearest to a reference time (see module)."""

    def __init__(self, start_s: float | None = None) -> None:
        #: The date's midnight to start from when no other reference is known.
        self.start_s = start_s
        #: The newest time made (and, through the bridge, accepted): the data's own clock.
        self.latest_s: float | None = None

    def place(self, tod_s: float, reference_s: float | None = None) -> float:
        """``tod_s`` on the day nearest to ``reference_s`` (else to :attr:`latest_s`, else on the
        start date), without taking it as the clock's newest time."""
        ref = reference_s if reference_s is not None else self.latest_s
        if ref is None:
            ref = (self.start_s or 0.0) + tod_s
        day = math.floor((ref - tod_s) / DAY_S + 0.5)  # the day putting tod nearest to ref
        return day * DAY_S + tod_s

    def note(self, t: float) -> None:
        """Take ``t`` as made: the newest time moves on to it (never back)."""
        if self.latest_s is None or t > self.latest_s:
            self.latest_s = t

    def time_s(self, tod_s: float, reference_s: float | None = None) -> float:
        t = self.place(tod_s, reference_s)
        self.note(t)
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
    #: A time more than this ahead of the bridge's clock is dropped (s).  Radars, capture hosts
    #: and the bridge's host keep UTC to well under a second (GPS, NTP); within 30 s a wrong stamp
    #: moves a radar's batch time ahead of the others by less than the service's lag allowance
    #: (``SequencerParams.max_lag_s``, 30 s), so it neither makes them lag nor gets rejected,
    #: and its batches are back on time within those 30 s.
    max_time_ahead_s: float = 30.0
    #: A time more than this behind the bridge's clock is dropped (s).  A plot reaches the
    #: bridge within its radar's scan (at most about 12 s) plus the network's delay; 60 s also
    #: leaves room for a relay that buffers, while older data would land in a batch far behind
    #: the radar's clock, which the service has moved past.
    max_time_behind_s: float = 60.0
    #: Without an outside clock, this many records in a row (in time order) out of tolerance of
    #: the data's own clock, within tolerance of each other (none in tolerance of the clock
    #: between them), move that clock to them: a recording that jumps in time or resumes after
    #: a pause, or a first record that was wrong.  More than a 1500-octet datagram holds (at
    #: most 133 plots), so a stray record or datagram never does; after a jump up to this many
    #: records are lost (a few seconds of a radar's plots).  A larger block of wrong times
    #: would move it, so a feed that may carry such runs on the wall clock (no ``--date``).
    #: With capture stamps or the wall clock nothing moves the clock but time itself.
    rebase_after_records: int = 200
    #: Plots and ADS-B reports held at most, all sources together: twice the most one batch may
    #: carry (``MAX_BATCH_ITEMS``, 100 000), about 51 MB (``HELD_RECORD_BYTES``).  A radar cut
    #: by sector messages holds one sector's plots (tens to hundreds); past the bound the source
    #: holding the most drops the quarter it has held longest (counted ``..._held_overflow``).
    max_held_records: int = 200_000
    #: A radar's held plots span at most this much data time (s): four scans of the slowest
    #: radars (15 s); only a radar whose sector messages stopped holds more.  Past it the plots
    #: older than three quarters of it before the newest are dropped (``cat048_held_too_long``;
    #: in steps of a quarter, so the work per plot stays constant).
    max_held_s: float = 60.0


_PLOT_COLUMNS = ("time_s", "range_m", "azimuth_deg", "altitude_m", "mode_3a", "mode_s", "flight_level")
_REQUIRED = frozenset({"time_s", "range_m", "azimuth_deg"})
_ADSB_COLUMNS = ("time_s", "icao24", "latitude_deg", "longitude_deg", "altitude_m", "mode_3a", "flight_level")
#: Optional ADS-B columns, sent only when some report of the batch carries one.
_ADSB_OPTIONAL = ("altitude_m", "mode_3a", "flight_level")
_TIME_AHEAD = {c: f"{c}_time_ahead" for c in ("cat048", "cat034", "cat021")}
_TIME_BEHIND = {c: f"{c}_time_behind" for c in ("cat048", "cat034", "cat021")}


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
    #: Data of this radar was lost since its last batch: the next one skips a ``seq`` number.
    lost: bool = False


@dataclass(frozen=True)
class Message:
    """One payload to publish: ``kind`` is ``plots`` or ``adsb``."""

    kind: str
    source_id: str
    body: dict[str, Any]


def _only(columns: dict[str, list[Any]], keep: list[int]) -> dict[str, list[Any]]:
    """The rows ``keep`` of every column."""
    if len(keep) < 2:  # itemgetter of one index gives the item, not a tuple
        return {n: [c[i] for i in keep] for n, c in columns.items()}
    get = operator.itemgetter(*keep)
    return {n: list(get(c)) for n, c in columns.items()}


def _split_at(
    columns: dict[str, list[Any]], time_s: float
) -> tuple[dict[str, list[Any]], dict[str, list[Any]]]:
    """The rows of ``columns`` stamped at or before ``time_s`` (at most ``MAX_BATCH_ITEMS``, the
    first held), and the rest, each in the order held."""
    t = columns["time_s"]
    take = [i for i, x in enumerate(t) if x <= time_s][:MAX_BATCH_ITEMS]
    if len(take) == len(t):
        return columns, {n: [] for n in columns}
    taken = set(take)
    return _only(columns, take), _only(columns, [i for i in range(len(t)) if i not in taken])


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
        #: The latest ADS-B batch's time (a batch's time never goes back), and the latest
        #: report time taken (the data's own clock of the batches).
        self._adsb_last_s = -math.inf
        self._adsb_seen_s = -math.inf
        self._adsb_lost = False
        #: Plots and ADS-B reports held now (all sources).
        self.held = 0
        #: Without an outside clock: the jump that records out of tolerance may be making (the
        #: newest of them) and how many in a row agree with it.
        self._jump_s = 0.0
        self._jump_records = 0
        #: Times the data's own clock moved to a jump (``rebase_after_records``).
        self.rebased = 0
        #: The sources (radar ids, the ADS-B id) the last :meth:`feed` used records of.
        self.fed: set[str] = set()
        #: Records not used, by cause.
        self.unusable: Counter[str] = Counter()
        #: Records used, by category; messages made, by kind.
        self.used: Counter[str] = Counter()
        self.sent: Counter[str] = Counter()

    # -- input ---------------------------------------------------------------------------------
    def feed(self, decoded: Decoded, reference_s: float | None = None) -> list[Message]:
        """The messages ``decoded`` (one datagram's or chunk's records) completes;
        ``reference_s``: the bridge's clock for this datagram (its capture time stamp, or the
        wall clock at receipt), None for the data's own clock (module doc)."""
        out: list[Message] = []
        self.fed = set()
        for cause, n in decoded.errors.items():
            self.unusable[f"blocks_{cause}"] += n
        # usable records with their time of day, then their times judged all together
        plots: list[tuple[str, Cat048Report, float, float]] = []
        for r in decoded.cat048:
            radar = self.radar_of.get((r.sac, r.sic))
            if radar is None:
                self.unusable["cat048_unknown_source"] += 1
            elif r.rho_m is None or r.theta_deg is None or r.rho_m <= 0.0:
                self.unusable["cat048_no_position"] += 1
            elif r.tod_s is None:
                self.unusable["cat048_no_time"] += 1
            elif not r.tod_s < DAY_S:  # (the 24-bit item holds up to 36 h; a day has 24)
                self.unusable["cat048_bad_time"] += 1
            elif r.test_target:  # a radar's own test transponder, not an aircraft
                self.unusable["cat048_test_target"] += 1
            else:
                plots.append((radar, r, r.tod_s, r.theta_deg))
        reports: list[tuple[Cat021Report, float]] = []
        for a in decoded.cat021:
            if a.icao24 is None:
                self.unusable["cat021_no_address"] += 1
            elif a.latitude_deg is None or a.longitude_deg is None:
                self.unusable["cat021_no_position"] += 1
            elif a.tod_s is None:
                self.unusable["cat021_no_time"] += 1
            elif not a.tod_s < DAY_S:
                self.unusable["cat021_bad_time"] += 1
            elif not (-90.0 <= a.latitude_deg <= 90.0 and -180.0 <= a.longitude_deg <= 180.0):
                self.unusable["cat021_no_position"] += 1
            else:
                reports.append((a, a.tod_s))
        sectors: list[tuple[str, float]] = []
        for msg in decoded.cat034:
            if msg.message_type not in BATCH_MESSAGES:
                continue
            radar = self.radar_of.get((msg.sac, msg.sic))
            if radar is None:
                self.unusable["cat034_unknown_source"] += 1
            elif msg.tod_s is None:
                self.unusable["cat034_no_time"] += 1
            elif not msg.tod_s < DAY_S:
                self.unusable["cat034_bad_time"] += 1
            else:
                sectors.append((radar, msg.tod_s))
        cats = ["cat048"] * len(plots) + ["cat021"] * len(reports) + ["cat034"] * len(sectors)
        tods = [x[2] for x in plots] + [x[1] for x in reports] + [x[1] for x in sectors]
        times = self._times(cats, tods, reference_s)
        n, m = len(plots), len(plots) + len(reports)
        for (radar, r, _, theta), t in zip(plots, times[:n], strict=True):
            if t is not None:
                self._plot(radar, r, theta, t)
        for (a, _), t in zip(reports, times[n:m], strict=True):
            if t is not None:
                self._adsb_report(a, t, reference_s, out)
        for (radar, _), t in zip(sectors, times[m:], strict=True):
            if t is not None:
                out += self._sector(radar, t)
        for radar in self._unsectored:
            pending = self._pending[radar]
            if pending.saw_sector:
                continue
            if pending.last_s - pending.first_s >= self.params.max_batch_s:
                out += self._cut(radar, pending, pending.last_s)
        self._unsectored.clear()
        # the bounds once this datagram's own sector messages have cut what they close (its
        # plots are all taken before its sector messages)
        for radar in self.fed:
            held = self._pending.get(radar)
            if held is not None and held.saw_sector and held.last_s - held.first_s > self.params.max_held_s:
                self._expire(held)
        if self.held > self.params.max_held_records:
            self._shed()
        return out

    def mark_lost(self, sources: set[str]) -> None:
        """Data of ``sources`` (radar ids, the ADS-B id) may have been lost before decoding: the
        next batch of each skips one ``seq`` number (module doc)."""
        for source in sources:
            pending = self._pending.get(source)
            if pending is not None:
                pending.lost = True
            elif source == self.params.adsb_source_id:
                self._adsb_lost = True

    # -- time ----------------------------------------------------------------------------------
    def _times(self, cats: list[str], tods: list[float], reference_s: float | None) -> list[float | None]:
        """Each time of day as Unix seconds if it is within tolerance of the bridge's clock,
        else None (counted by ``cats``, the records' categories; module doc)."""
        clock, p = self.clock, self.params
        place = clock.place
        ts = [place(tod, reference_s) for tod in tods]
        if not ts:
            return []
        # Mostly every time is in tolerance: one look at the earliest and the latest says so (by
        # the data's own clock too: in time order each is judged against the newest before it,
        # which is at least the clock and at most the time itself).
        ref = reference_s if reference_s is not None else clock.latest_s
        if ref is not None and ref - p.max_time_behind_s <= min(ts) and max(ts) <= ref + p.max_time_ahead_s:
            clock.note(max(ts))
            if reference_s is None:
                self._jump_records = 0
            return list(ts)
        if reference_s is not None:
            lo, hi = reference_s - p.max_time_behind_s, reference_s + p.max_time_ahead_s
            judged: list[float | None] = []
            for cat, t in zip(cats, ts, strict=True):
                if t > hi:
                    self.unusable[_TIME_AHEAD[cat]] += 1
                    judged.append(None)
                elif t < lo:
                    self.unusable[_TIME_BEHIND[cat]] += 1
                    judged.append(None)
                else:
                    clock.note(t)
                    judged.append(t)
            return judged
        # The data's own clock: in time order, so that the records of a datagram (taken category
        # by category) or of a file's chunk (which may span minutes) judge each other as made.
        judged = [None] * len(ts)
        for i in sorted(range(len(ts)), key=ts.__getitem__):
            judged[i] = self._own_time(ts[i], cats[i])
        return judged

    def _own_time(self, t: float, cat: str) -> float | None:
        """``t`` judged by the data's own clock (:attr:`DayClock.latest_s`), None if out of
        tolerance (counted); enough records in a row out of it that agree move it."""
        clock, p = self.clock, self.params
        latest = clock.latest_s
        if latest is None or -p.max_time_behind_s <= t - latest <= p.max_time_ahead_s:
            self._jump_records = 0
            clock.note(t)
            return t
        jump = self._jump_s
        if self._jump_records and -p.max_time_behind_s <= t - jump <= p.max_time_ahead_s:
            self._jump_records += 1
            self._jump_s = max(jump, t)
        else:
            self._jump_s, self._jump_records = t, 1
        if self._jump_records >= p.rebase_after_records:
            self._jump_records = 0
            self.rebased += 1
            clock.latest_s = self._jump_s  # the data moved on (or back): follow it
            return t
        self.unusable[_TIME_AHEAD[cat] if t > latest else _TIME_BEHIND[cat]] += 1
        return None

    # -- records -------------------------------------------------------------------------------
    def _plot(self, radar: str, r: Cat048Report, theta_deg: float, t: float) -> None:
        fl = r.flight_level
        if fl is not None and not (MIN_FLIGHT_LEVEL <= fl <= MAX_FLIGHT_LEVEL):
            fl = None  # outside what I048/090 may validly hold: a garbled code
        alt = self._height(r.height_m, "cat048_bad_height")
        if alt is None and fl is not None and self.params.altitude_from_fl:
            alt = fl * FL_M
        pending = self._pending.get(radar)
        if pending is None:
            pending = self._pending[radar] = _Pending()
        pending.first_s, pending.last_s = min(pending.first_s, t), max(pending.last_s, t)
        if not pending.saw_sector:
            self._unsectored.add(radar)
        cols = pending.columns
        cols["time_s"].append(t)
        cols["range_m"].append(r.rho_m)
        cols["azimuth_deg"].append(theta_deg % 360.0)
        cols["altitude_m"].append(alt)
        cols["mode_3a"].append(r.mode_3a)
        cols["mode_s"].append(r.mode_s)
        cols["flight_level"].append(fl)
        self.held += 1
        self.used["cat048"] += 1
        self.fed.add(radar)

    def _height(self, height_m: float | None, cause: str) -> float | None:
        """A measured height, or None (counted by ``cause``) beyond the heights the contract
        takes: the record is used without it, where the value would cost its whole batch."""
        if height_m is not None and not (MIN_ALTITUDE_M <= height_m <= MAX_ALTITUDE_M):
            self.unusable[cause] += 1
            return None
        return height_m

    def _sector(self, radar: str, t: float) -> list[Message]:
        pending = self._pending.get(radar)
        if pending is None:
            pending = self._pending[radar] = _Pending()
        pending.saw_sector = True
        self.fed.add(radar)
        return self._cut(radar, pending, t)

    def _adsb_report(self, r: Cat021Report, t: float, reference_s: float | None, out: list[Message]) -> None:
        """A report of time ``t``: the batch held goes out once the bridge's clock has moved
        ``adsb_batch_s`` on since it began.  The clock is the capture's time stamp or the wall
        clock (``reference_s``), so that one report stamped ahead holds no batch open; without
        one, the data's own: the latest report time taken."""
        self._adsb_seen_s = max(self._adsb_seen_s, t)
        now = reference_s if reference_s is not None else self._adsb_seen_s
        # full: a cut at most once per clock reading (reports held ahead of the clock would
        # otherwise be looked over again for every report that comes)
        full = len(self._adsb["time_s"]) >= MAX_BATCH_ITEMS and now != self._adsb_start
        if self._adsb_start is None:
            self._adsb_start = now  # (by the clock: a feed that lags it still cuts once a batch)
        elif now - self._adsb_start >= self.params.adsb_batch_s or full:
            out += self._send_adsb(now)
            self._adsb_start = now
        cols = self._adsb
        cols["time_s"].append(t)
        cols["icao24"].append(r.icao24)
        cols["latitude_deg"].append(r.latitude_deg)
        cols["longitude_deg"].append(r.longitude_deg)
        cols["altitude_m"].append(self._height(r.geometric_height_m, "cat021_bad_height"))
        fl = r.flight_level
        if fl is not None and not (MIN_FLIGHT_LEVEL <= fl <= MAX_FLIGHT_LEVEL):
            fl = None  # outside what I021/145 may validly hold: a garbled level
        cols["mode_3a"].append(r.mode_3a)
        cols["flight_level"].append(fl)
        self.held += 1
        self.used["cat021"] += 1
        self.fed.add(self.params.adsb_source_id)

    # -- bounds --------------------------------------------------------------------------------
    def _expire(self, pending: _Pending) -> None:
        """Drop a radar's plots older than three quarters of ``max_held_s`` before its newest."""
        cutoff = pending.last_s - 0.75 * self.params.max_held_s
        t = pending.columns["time_s"]
        keep = [i for i, x in enumerate(t) if x >= cutoff]
        self._dropped(len(t) - len(keep), "cat048_held_too_long")
        pending.columns = _only(pending.columns, keep)
        pending.first_s = min(pending.columns["time_s"])  # the newest is kept
        pending.lost = True

    def _shed(self) -> None:
        """Past ``max_held_records``: the source holding the most drops the quarter it has held
        longest (records come in time order, give or take a scan, so these are its oldest)."""
        while self.held > self.params.max_held_records:
            pending = max(self._pending.values(), key=lambda p: len(p.columns["time_s"]), default=_Pending())
            adsb = len(self._adsb["time_s"]) > len(pending.columns["time_s"])
            cols = self._adsb if adsb else pending.columns
            n = max(1, len(cols["time_s"]) // 4)
            kept = {name: c[n:] for name, c in cols.items()}
            if adsb:
                self._adsb, self._adsb_lost = kept, True
                if not kept["time_s"]:
                    self._adsb_start = None
            else:
                pending.columns, pending.lost = kept, True
                held = kept["time_s"]
                pending.first_s, pending.last_s = (min(held), max(held)) if held else (math.inf, -math.inf)
            self._dropped(n, "cat021_held_overflow" if adsb else "cat048_held_overflow")

    def _dropped(self, n: int, cause: str) -> None:
        self.held -= n
        self.unusable[cause] += n

    # -- output --------------------------------------------------------------------------------
    def _cut(self, radar: str, pending: _Pending, time_s: float) -> list[Message]:
        """Send the plots of ``radar`` up to ``time_s`` as one batch (also when none)."""
        # a batch's time never goes back (a late or reordered sector message)
        batch_s = max(time_s, pending.last_batch_s)
        sent, pending.columns = _split_at(pending.columns, time_s)
        self.held -= len(sent["time_s"])
        pending.seq += 2 if pending.lost else 1  # a lost batch's number stays unused
        pending.lost = False
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

    def _send_adsb(self, now: float = math.inf) -> list[Message]:
        """The ADS-B reports held up to the clock ``now`` as one batch (those stamped after it
        wait for a later one); its time is the latest report's, and never goes back."""
        if not any(x <= now for x in self._adsb["time_s"]):
            return []  # (nothing due: the held reports stay as they are, uncopied)
        cols, self._adsb = _split_at(self._adsb, now)
        self.held -= len(cols["time_s"])
        self._adsb_seq += 2 if self._adsb_lost else 1
        self._adsb_lost = False
        reports = {n: c for n, c in cols.items() if n not in _ADSB_OPTIONAL or any(x is not None for x in c)}
        self._adsb_last_s = max(self._adsb_last_s, max(cols["time_s"]))
        body = {
            "source_id": self.params.adsb_source_id,
            "seq": self._adsb_seq,
            "time_s": self._adsb_last_s,
            "reports": reports,
        }
        self.sent["adsb"] += 1
        return [Message("adsb", self.params.adsb_source_id, body)]

    def flush(self) -> list[Message]:
        """Everything still held, e.g. when the input ended or the bridge stops."""
        out: list[Message] = []
        for radar, pending in self._pending.items():
            while pending.columns["time_s"]:  # more than one batch holds only past MAX_BATCH_ITEMS
                out += self._cut(radar, pending, pending.last_s)
        while self._adsb["time_s"]:  # (more than one batch only past MAX_BATCH_ITEMS)
            out += self._send_adsb()
        self._adsb_start = None
        return out
