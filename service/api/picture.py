"""The operator picture (docs/contract.md §4.5): ``GET /picture`` and its live feed.

``GET /picture`` is a page of plain HTML, CSS and JavaScript (``service/api/static/``: no
library, no font, no tile, nothing from another host) that draws, on a lat/lon graticule with
pan and zoom over the coastlines and borders of ``static/basemap.json`` (Natural Earth, made
by the lab's basemap script, docs/picture.md): the radar sites with their coverage rings, the
radars' tracks (faint), the system tracks (bold, with their ids, flight levels, velocity
leaders and trails), the correlation links between paired radar tracks, each radar's bias
estimate as an arrow with an uncertainty ellipse, a selected track's members and pairs,
filters kept in the address, and a health panel (with each radar's
``/radars/{id}/performance`` where there is one).

``GET /picture/events`` feeds it: server-sent events, one compact JSON snapshot about every
second of wall time (``interval_s``), built from the node's latest read-model snapshot (the
state ``/status``, ``/radars``, ``/radars/{id}/tracks``, ``/pairs``, ``/system-tracks`` and
``/biases`` answer).  It is bounded: confirmed tracks only unless ``status=all``, and at most
``max_items`` system tracks, ``max_items`` radar tracks over all radars and ``max_items``
links (the counts left out are in ``truncated``).  Each row is a list whose cells ``COLUMNS``
names (the snapshot carries them as ``columns``): what the page's filters, labels and selection
panel need (flight level, Mode S, Mode 3/A, speed, age, a system track's members, a pair's
score and basis).  The health part gives each source's lag and rates in data time
(:func:`picture_health`, :class:`DataRates`), and whether the data is a replay.

Any number of viewers costs the service a bounded amount of work (docs/picture.md):

* a viewer's ``max_items`` is rounded down to one of ``MAX_ITEMS_STEPS`` and its
  ``interval_s`` up to one of ``INTERVAL_STEPS``, so there are at most 2 x 14 shapes of
  snapshot (``status`` x ``max_items``);
* snapshots are built on a shared clock of ``TICK_S``: each shape at most once per tick, by
  one builder thread of the feed's own (never a thread the request handlers need), encoded and
  framed as an event once, and the same bytes go to every viewer of that shape; the state
  common to the shapes of a status is read from the node once per tick, and only when the
  node's snapshot changed is it converted again;
* viewers of one interval wake together on that clock, so they share the builds;
* a viewer that does not take its events is dropped (its connection reset) once
  ``picture_backlog`` of its intervals pass with an event still not handed over; what it holds
  meanwhile is its connection's kernel send buffer (``picture_send_buffer``) and at most one
  event in the server;
* at most ``picture_max_clients`` viewers at once (503 beyond).

The builder reads only the node's immutable snapshot and its status (no lock the worker
takes); what it costs the worker is Python time, bounded by the above.

The maths here is only presentation (east/north components of a velocity at a track's
latitude and longitude): the numerics stay in the engine (the import rules of pyproject.toml).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import orjson
from fastapi import FastAPI, Query
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from starlette.types import Receive, Scope, Send

from service.api.deps import NodeDep
from service.api.limits import HttpLimits
from service.api.server import CONNECTION_EXTENSION
from service.transport.node import ServiceNode

log = logging.getLogger("topofusion.picture")

STATIC_DIR = Path(__file__).resolve().parent / "static"
#: Default and largest ``max_items`` of ``/picture/events``.
DEFAULT_MAX_ITEMS = 2000
MAX_ITEMS_LIMIT = 20000
#: ``max_items`` is rounded down to 1, 2 or 5 times a power of ten (1, 2, 5, 10, ..., 20 000).
MAX_ITEMS_STEPS = tuple(m * 10**k for k in range(5) for m in (1, 2, 5) if m * 10**k <= MAX_ITEMS_LIMIT)
#: Default wall seconds between two events, and the bounds of ``interval_s`` (422 outside).
DEFAULT_INTERVAL_S = 1.0
MIN_INTERVAL_S, MAX_INTERVAL_S = 0.2, 10.0
#: ``interval_s`` is rounded up to one of these (s).
INTERVAL_STEPS = (0.5, 1.0, 2.0, 5.0, 10.0)
#: The clock snapshots are built on (s): a shape's snapshot is built at most once per tick.
TICK_S = INTERVAL_STEPS[0]
#: How long one snapshot serves every viewer of its shape (s).
CACHE_S = TICK_S
#: A stream ends after this many wall seconds; the browser's EventSource reconnects by itself
#: (``retry``), so that no connection outlives a shutdown or a proxy's idle limit for long.
MAX_STREAM_S = 300.0
RETRY_MS = 2000
#: A viewer refused for the client cap is told to come back after this many seconds.
REFUSED_RETRY_S = 5
#: The share of one core (of the interpreter's lock, which the worker needs too) that
#: converting the node's state for the picture may take: after a conversion that took c
#: seconds the next waits at least c / BUILD_SHARE, and snapshots meanwhile carry the state of
#: the last (with fresh health figures).
BUILD_SHARE = 0.1
#: Under a load of viewers beyond ``picture_max_bytes_s``, every viewer's interval is stretched
#: by the same power of two, up to this factor.
MAX_STRIDE = 16
#: Seconds between two log lines about dropped viewers.
LOG_EVERY_S = 10.0
#: The page loads its own script and styles and its feed, nothing else (inline styles: the
#: colour swatches of the health panel).
PICTURE_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "connect-src 'self'; base-uri 'self'; form-action 'self'"
)
#: Coordinates are rounded to this many decimals of a degree (about 1 m).
DECIMALS = 5
EVENT_HEAD = b"event: snapshot\ndata: "
#: The health panel's rates are over this many seconds of data time (at least
#: ``RATE_MIN_SPAN_S``), from at most ``RATE_SAMPLES`` samples of the counters.
RATE_WINDOW_S = 10.0
RATE_MIN_SPAN_S = 1.0
RATE_SAMPLES = 256
#: The data is a replay when its clock is this far (s) from the wall clock, or runs at a speed
#: (data s per wall s) outside this band: a live feed's data time follows the wall clock
#: within its latency, and at its pace.
REPLAY_OFFSET_S = 120.0
REPLAY_SPEED = (0.8, 1.25)

#: ``(status, max_items)`` after rounding.
Shape = tuple[str, int]


def quantised_max_items(max_items: int) -> int:
    """The step of ``MAX_ITEMS_STEPS`` a requested ``max_items`` is served with."""
    return max((s for s in MAX_ITEMS_STEPS if s <= max_items), default=MAX_ITEMS_STEPS[0])


def quantised_interval_s(interval_s: float) -> float:
    """The step of ``INTERVAL_STEPS`` a requested ``interval_s`` is served with."""
    return next((s for s in INTERVAL_STEPS if s >= interval_s - 1e-9), INTERVAL_STEPS[-1])


def _east_north(lat_deg: float, lon_deg: float, v: list[float]) -> tuple[float, float]:
    """East and north components (m/s) of an ECEF velocity at a latitude and longitude."""
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    sla, cla, slo, clo = math.sin(la), math.cos(la), math.sin(lo), math.cos(lo)
    east = -slo * v[0] + clo * v[1]
    north = -sla * clo * v[0] - sla * slo * v[1] + cla * v[2]
    return round(east, 1), round(north, 1)


def _r(x: float | None, digits: int = DECIMALS) -> float | None:
    return None if x is None or not math.isfinite(x) else round(x, digits)


#: The cells of each row of a snapshot's ``tracks``, ``system_tracks`` and ``links`` (the
#: snapshot carries them as ``columns``; the status cell is last, 1/0 or ``c``/``t``).  ``fl``:
#: flight level (hundreds of feet of the track's altitude), ``ve``/``vn``: east/north speed
#: (m/s), ``age_s``: data seconds since the track's last update, ``members``: ``[source,
#: track id]`` of each, ``score``/``basis``: the pair's (``PairSet``).
COLUMNS = {
    "tracks": ("id", "lat", "lon", "ve", "vn", "fl", "mode_s", "mode_3a", "age_s", "confirmed"),
    "system_tracks": (
        "id",
        "lat",
        "lon",
        "ve",
        "vn",
        "sigma_m",
        "fl",
        "mode_s",
        "mode_3a",
        "age_s",
        "members",
        "confirmed",
    ),
    "links": (
        "radar_a",
        "radar_b",
        "lat_a",
        "lon_a",
        "lat_b",
        "lon_b",
        "track_a",
        "track_b",
        "score",
        "basis",
        "status",
    ),
}
#: The international foot (m): a flight level is the altitude in hundreds of them.
FEET = 0.3048


def _fl(altitude_m: float | None) -> int | None:
    """Flight level: the altitude in hundreds of feet (the picture's filters and labels)."""
    return None if altitude_m is None or not math.isfinite(altitude_m) else round(altitude_m / FEET / 100)


def _age(now_s: float | None, time_s: float | None) -> float | None:
    return None if now_s is None or time_s is None else round(max(0.0, now_s - time_s), 1)


def picture_data(node: ServiceNode) -> dict[str, Any]:
    """What every snapshot of one moment shares, from the node's read-model snapshot: every
    site, radar track, link and system track (confirmed or not, each row ending with its
    status; the cells are ``COLUMNS``'), and the bias estimates.  :func:`for_status` takes a
    status's rows from it."""
    snap = node.snapshot
    sites = node.radars()
    # (partitioned, while worker 1 does not answer: no system tracks; the health panel's
    # missing workers say why)
    system = node.system_tracks("all") or {"time_s": None, "system_tracks": []}
    times = [t for t, _ in snap.tracks.values()]
    now_s = system["time_s"] if system["time_s"] is not None else max(times, default=None)

    tracks: dict[str, list[list[Any]]] = {}
    where: dict[str, dict[str, tuple[float | None, float | None]]] = {}
    #: (source, track id) -> Mode S, Mode 3/A and time of each track (for its system track)
    ident: dict[tuple[str, str], tuple[Any, Any, float]] = {}
    for rid in sorted(snap.tracks):
        every = snap.track_batch(rid, "all") or {"tracks": []}
        rows, at = [], {}
        for t in every["tracks"]:
            lat, lon = _r(t["latitude_deg"]), _r(t["longitude_deg"])
            at[t["track_id"]] = (lat, lon)  # rounded once, for the track and all its links
            ident[(rid, t["track_id"])] = (t["mode_s"], t["mode_3a"], t["time_s"])
            rows.append(
                [
                    t["track_id"],
                    lat,
                    lon,
                    *_east_north(t["latitude_deg"], t["longitude_deg"], t["velocity_ecef_mps"]),
                    _fl(t["altitude_m"]),
                    t["mode_s"],
                    t["mode_3a"],
                    _age(now_s, t["time_s"]),
                    int(t["status"] == "confirmed"),
                ]
            )
        tracks[rid], where[rid] = rows, at

    # correlation links: between the two radar tracks of each pair whose positions are known
    links: list[list[Any]] = []
    for ps in node.pair_sets(None, None, "all"):
        ra, rb = ps["radar_a"], ps["radar_b"]
        at_a, at_b = where.get(ra, {}), where.get(rb, {})
        for p in ps["pairs"]:
            pa, pb = at_a.get(p["track_a"]), at_b.get(p["track_b"])
            if pa is not None and pb is not None:
                links.append(
                    [
                        ra,
                        rb,
                        pa[0],
                        pa[1],
                        pb[0],
                        pb[1],
                        p["track_a"],
                        p["track_b"],
                        _r(p["score"], 3),
                        p["basis"],
                        p["status"][0],
                    ]
                )

    system_tracks = []
    for t in system["system_tracks"]:
        members = [[m["radar_id"], m["track_id"]] for m in t["members"]]
        known = [ident[k] for m in members if (k := (m[0], m[1])) in ident]
        # a system track's identity: the first of its members' that has one
        mode_s = next((i[0] for i in known if i[0] is not None), None)
        mode_3a = next((i[1] for i in known if i[1] is not None), None)
        system_tracks.append(
            [
                t["system_track_id"],
                _r(t["latitude_deg"]),
                _r(t["longitude_deg"]),
                *_east_north(t["latitude_deg"], t["longitude_deg"], t["velocity_ecef_mps"]),
                _r(t["position_sigma_m"], 1),
                _fl(t["altitude_m"]),
                mode_s,
                mode_3a,
                _age(now_s, max((i[2] for i in known), default=None)),
                members,
                int(t["status"] == "confirmed"),
            ]
        )

    by_site = {s["radar_id"]: s for s in sites}
    biases = []
    for b in snap.biases():
        site = by_site.get(b["radar_id"], {})
        n = max(1, int(b["pairs_used"]))
        # The estimate's own 1-sigma; where it is not known (null, or a bias worker of an
        # older version), an approximation: the radar's random errors over the square root
        # of the pairs used.
        range_sigma = b.get("range_bias_sigma_m")
        azimuth_sigma = b.get("azimuth_bias_sigma_deg")
        if range_sigma is None:
            range_sigma = float(site.get("range_sigma_m", 200.0)) / math.sqrt(n)
        if azimuth_sigma is None:
            azimuth_sigma = float(site.get("azimuth_sigma_deg", 0.2)) / math.sqrt(n)
        biases.append(
            {
                "radar_id": b["radar_id"],
                "range_m": _r(b["range_bias_m"], 1),
                "azimuth_deg": _r(b["azimuth_bias_deg"], 4),
                "range_sigma_m": _r(range_sigma, 1),
                "azimuth_sigma_deg": _r(azimuth_sigma, 4),
                "pairs_used": int(b["pairs_used"]),
                "time_s": b["time_s"],
            }
        )
    return {
        "time_s": system["time_s"],
        "sites": [
            {
                "radar_id": s["radar_id"],
                "latitude_deg": _r(s["latitude_deg"]),
                "longitude_deg": _r(s["longitude_deg"]),
            }
            for s in sites
        ],
        "tracks": tracks,
        "links": links,
        "system_tracks": system_tracks,
        "biases": biases,
    }


def for_status(data: Mapping[str, Any], status: str) -> dict[str, Any]:
    """``data``'s rows of ``status`` (``all``, or ``confirmed``: rows whose last cell is 1 or
    ``c``), at most ``MAX_ITEMS_LIMIT`` of each kind, with the counts before that bound."""
    if status == "all":
        tracks, links, system = data["tracks"], data["links"], data["system_tracks"]
    else:
        tracks = {rid: [t for t in rows if t[-1]] for rid, rows in data["tracks"].items()}
        links = [link for link in data["links"] if link[-1] == "c"]
        system = [t for t in data["system_tracks"] if t[-1]]
    return {
        "time_s": data["time_s"],
        "sites": data["sites"],
        "tracks": {rid: rows[:MAX_ITEMS_LIMIT] for rid, rows in tracks.items()},
        "track_totals": {rid: len(rows) for rid, rows in tracks.items()},
        "links": links[:MAX_ITEMS_LIMIT],
        "links_total": len(links),
        "system_tracks": system[:MAX_ITEMS_LIMIT],
        "system_total": len(system),
        "biases": data["biases"],
    }


class DataRates:
    """Each source's plots and batches per second of data time, and how fast the data clock
    runs against the wall clock, from the counters of successive health reads.

    Over data time rather than wall time: a recording replayed at five times real time still
    shows a radar's own rate.  The window is on the network's data clock (the newest data time
    of any source), so a source that falls silent drops to 0 plots/s while the others go on.
    Samples are taken only when that clock moves (at most ``RATE_SAMPLES`` held)."""

    def __init__(self) -> None:
        #: (network data time, wall time, {source: (plots, batches)})
        self._samples: deque[tuple[float, float, dict[str, tuple[int, int]]]] = deque(maxlen=RATE_SAMPLES)

    def update(
        self, data_s: float | None, wall_s: float, counters: dict[str, tuple[int, int]]
    ) -> tuple[dict[str, tuple[float, float]], float | None]:
        """The rates per source (plots/s, batches/s; absent until the window spans
        ``RATE_MIN_SPAN_S``), and data seconds per wall second (None until known)."""
        held = self._samples
        if data_s is None:
            return {}, None
        if held and data_s < held[-1][0]:
            held.clear()  # the data clock went back: another recording
        if not held or data_s > held[-1][0]:
            held.append((data_s, wall_s, counters))
        # keep one sample at least a window old (the window's start)
        while len(held) > 2 and data_s - held[1][0] >= RATE_WINDOW_S:
            held.popleft()
        (t0, w0, first), (t1, w1, last) = held[0], held[-1]
        span = t1 - t0
        rates = {}
        if span >= RATE_MIN_SPAN_S:
            for rid, (plots, batches) in last.items():
                if rid in first:
                    rates[rid] = (
                        round((plots - first[rid][0]) / span, 1),
                        round((batches - first[rid][1]) / span, 2),
                    )
        speed = round(span / (w1 - w0), 2) if w1 - w0 >= RATE_MIN_SPAN_S else None
        return rates, speed


def picture_health(node: ServiceNode, rates: DataRates | None = None, wall_s: float = 0.0) -> dict[str, Any]:
    """The health panel's part of a snapshot (from ``node.status()``).

    A source's ``lag_s`` is how far its data clock is behind the newest of any source (data
    time, not the wall clock: a fast run or a replay of an old recording would be minutes
    ahead or years behind the wall clock, which says nothing of a source's lateness).
    ``replay``: the data clock is more than ``REPLAY_OFFSET_S`` from the wall clock, or runs
    at a speed other than real time (``data_speed``, data seconds per wall second).  Rates
    (``plots_s``, ``batches_s``) come from ``rates``, None without it."""
    st = node.status()
    times = [r["last_time_s"] for r in st["radars"] if r["last_time_s"] is not None]
    newest = max(times, default=None)
    counters = {r["radar_id"]: (int(r["plots"]), int(r["batches"])) for r in st["radars"]}
    per_source, speed = rates.update(newest, wall_s, counters) if rates is not None else ({}, None)
    radars = [
        {
            "radar_id": r["radar_id"],
            "batches": r["batches"],
            "plots": r["plots"],
            "plots_s": per_source[r["radar_id"]][0] if r["radar_id"] in per_source else None,
            "batches_s": per_source[r["radar_id"]][1] if r["radar_id"] in per_source else None,
            "rejected": r["rejected"],
            "lost_batches": r["lost_batches"],
            "window_plots": r["window_plots"],
            "tracks_confirmed": r["tracks_confirmed"],
            "tracks_tentative": r["tracks_tentative"],
            "last_time_s": r["last_time_s"],
            "lag_s": None
            if newest is None or r["last_time_s"] is None
            else round(newest - r["last_time_s"], 3),
            "expired": bool(r.get("expired", False)),
        }
        for r in st["radars"]
    ]
    off_clock = newest is not None and abs(wall_s - newest) > REPLAY_OFFSET_S
    off_speed = speed is not None and not REPLAY_SPEED[0] <= speed <= REPLAY_SPEED[1]
    return {
        "radars": radars,
        "data_time_s": newest,
        "data_speed": speed,
        "replay": bool(off_clock or off_speed),
        "correlation": st["correlation"],
        "pairs_confirmed": st["pairs_confirmed"],
        "pairs_tentative": st["pairs_tentative"],
        "pairs_held": st.get("pairs_held", 0),
        "rejected": st["rejected"],
        "queue": st.get("queue", {}),
        "missing_partitions": (st.get("partition") or {}).get("missing", []),
        "method": st["method"],
    }


def shaped(
    data: Mapping[str, Any], health: dict[str, Any], wall_s: float, status: str, max_items: int
) -> dict[str, Any]:
    """The snapshot of one shape: ``data`` (:func:`for_status`'s) cut to ``max_items`` of each
    kind (radar tracks shared out evenly over the radars), with what was cut in ``truncated``."""
    # max_items over the radars: an equal share each, the first ones one more for the rest
    share, rest = divmod(max_items, max(1, len(data["tracks"])))
    room = {rid: share + (k < rest) for k, rid in enumerate(data["tracks"])}
    return {
        "wall_s": wall_s,
        "time_s": data["time_s"],
        "status": status,
        "max_items": max_items,
        "sites": data["sites"],
        "columns": COLUMNS,
        "tracks": {rid: rows[: room[rid]] for rid, rows in data["tracks"].items()},
        "links": data["links"][:max_items],
        "system_tracks": data["system_tracks"][:max_items],
        "biases": data["biases"],
        "health": health,
        "truncated": {
            "system_tracks": max(0, data["system_total"] - max_items),
            "tracks": sum(max(0, n - room[rid]) for rid, n in data["track_totals"].items()),
            "links": max(0, data["links_total"] - max_items),
        },
    }


def build_snapshot(
    node: ServiceNode, status: str = "confirmed", max_items: int = DEFAULT_MAX_ITEMS
) -> dict[str, Any]:
    """The picture's JSON snapshot (what each event of ``/picture/events`` carries)."""
    data = for_status(picture_data(node), status)
    wall_s = round(time.time(), 3)
    return shaped(data, picture_health(node, None, wall_s), wall_s, status, max_items)


@dataclass
class _Moment:
    """What every shape shares at one tick (the builder thread's alone)."""

    tick: int
    health: dict[str, Any]
    wall_s: float


class PictureFeed:
    """The snapshots every viewer shares, and the viewers (one feed per app).

    Event-loop side: :meth:`event` (a shape's event at a tick: built once, awaited by all),
    the viewer count.  Builder side (its one thread): the per-status common part and the
    encoding of each shape.
    """

    def __init__(self, limits: HttpLimits) -> None:
        self.limits = limits
        self.clients = 0
        #: Viewers dropped for their backlog, and refused for the cap (since the start).
        self.dropped = 0
        self.refused = 0
        #: Events built so far (one per shape and tick at most).
        self.builds = 0
        self._builds: dict[Shape, tuple[int, asyncio.Future[bytes]]] = {}
        self._pool: ThreadPoolExecutor | None = None
        #: Viewers by shape and interval (in ticks), the latest event's size of each shape,
        #: and the stride all intervals are stretched by (worked out once per tick).
        self._viewers: Counter[tuple[Shape, int]] = Counter()
        self._sizes: dict[Shape, int] = {}
        self._stride = (-1, 1)
        # the builder thread's alone:
        self._moment: _Moment | None = None
        self._data: dict[str, Any] | None = None
        self._data_of: object = None  # the node's read-model snapshot ``_data`` was made from
        self._data_due = 0.0  # no new conversion before (monotonic s)
        self._views: dict[str, dict[str, Any]] = {}  # ``_data`` by status
        self._rates = DataRates()
        #: Conversions of the node's state so far (``picture_data``).
        self.conversions = 0
        self._logged_at = -LOG_EVERY_S

    @staticmethod
    def tick_now() -> int:
        return int(time.monotonic() // TICK_S)

    def join(self, shape: Shape, every: int) -> None:
        self.clients += 1
        self._viewers[(shape, every)] += 1

    def leave(self, shape: Shape, every: int) -> None:
        self.clients -= 1
        self._viewers[(shape, every)] -= 1
        if self._viewers[(shape, every)] <= 0:
            del self._viewers[(shape, every)]

    def demand(self) -> float:
        """Bytes per second the viewers ask for, at their own intervals."""
        return sum(
            n * self._sizes.get(shape, 0) / (every * TICK_S) for (shape, every), n in self._viewers.items()
        )

    def stride(self) -> int:
        """The power of two (up to ``MAX_STRIDE``) every interval is stretched by, so that the
        viewers together get at most ``picture_max_bytes_s`` (as long as that is enough)."""
        tick, stride = self._stride
        now = self.tick_now()
        if tick != now:
            demand, budget = self.demand(), self.limits.picture_max_bytes_s
            stride = 1
            while stride < MAX_STRIDE and demand / stride > budget:
                stride *= 2
            self._stride = (now, stride)
        return stride

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    async def event(self, node: ServiceNode, shape: Shape, tick: int) -> bytes:
        """The event of ``shape`` at ``tick`` (or a later one already built), framed."""
        held = self._builds.get(shape)
        if held is None or held[0] < tick:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="picture")
            future = asyncio.get_running_loop().run_in_executor(self._pool, self._build, node, shape, tick)
            future.add_done_callback(_consume)
            held = self._builds[shape] = (tick, future)
        # shielded: a viewer that leaves must not cancel the build the others wait for
        event = await asyncio.shield(held[1])
        self._sizes[shape] = len(event)
        return event

    def _build(self, node: ServiceNode, shape: Shape, tick: int) -> bytes:
        status, max_items = shape
        moment = self._moment
        if moment is None or moment.tick < tick:  # (a viewer late for its tick gets the newer)
            self._refresh(node)
            wall_s = round(time.time(), 3)
            moment = self._moment = _Moment(tick, picture_health(node, self._rates, wall_s), wall_s)
        assert self._data is not None
        view = self._views.get(status)
        if view is None:
            view = self._views[status] = for_status(self._data, status)
        self.builds += 1
        body = orjson.dumps(shaped(view, moment.health, moment.wall_s, status, max_items))
        return EVENT_HEAD + body + b"\n\n"

    def _refresh(self, node: ServiceNode) -> None:
        """Convert the node's state again if it changed (a partitioned worker's links come
        from the others as well: always), and if the last conversion has been rested for."""
        now = time.monotonic()
        snap = node.snapshot
        changed = snap is not self._data_of or not node.partition.whole
        if self._data is not None and not (changed and now >= self._data_due):
            return
        began = time.perf_counter()
        self._data = picture_data(node)
        self._data_of, self._views = snap, {}
        self._data_due = now + (time.perf_counter() - began) / BUILD_SHARE
        self.conversions += 1

    def note_dropped(self, scope: Scope, waited_s: float) -> None:
        self.dropped += 1
        now = time.monotonic()
        if now - self._logged_at >= LOG_EVERY_S:
            client = scope.get("client") or ("?", 0)
            log.warning(
                "picture viewer %s:%s dropped: an event waited %.1f s to be taken "
                "(TOPOFUSION_HTTP_PICTURE_BACKLOG); %d dropped since the start",
                client[0],
                client[1],
                waited_s,
                self.dropped,
            )
            self._logged_at = now


def _consume(future: asyncio.Future[bytes]) -> None:
    """A build that failed is logged here once, whoever (if anyone) was waiting for it."""
    if not future.cancelled() and (exc := future.exception()) is not None:
        log.error("picture snapshot not built", exc_info=exc)


class PictureStream(Response):
    """One viewer's ``text/event-stream``: an event of its shape on each of its ticks."""

    media_type = "text/event-stream"

    def __init__(self, feed: PictureFeed, node: ServiceNode, shape: Shape, interval_s: float) -> None:
        self.feed = feed
        self.node = node
        self.shape = shape
        self.every = max(1, round(interval_s / TICK_S))  # ticks between two events
        self.status_code = 200
        self.background = None
        self.init_headers({"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        feed = self.feed
        if feed.clients >= feed.limits.picture_max_clients:
            feed.refused += 1
            refused = JSONResponse(
                {"detail": "too many picture viewers; try again later"},
                status_code=503,
                headers={"Retry-After": str(REFUSED_RETRY_S)},
            )
            await refused(scope, receive, send)
            return
        feed.join(self.shape, self.every)
        gone = asyncio.Event()

        async def watch() -> None:
            while (await receive())["type"] != "http.disconnect":
                pass
            gone.set()

        watcher = asyncio.create_task(watch())
        bound = scope.get("extensions", {}).get(CONNECTION_EXTENSION, {}).get("bound_output")
        if bound is not None:
            bound(feed.limits.picture_send_buffer)
        try:
            await send({"type": "http.response.start", "status": 200, "headers": self.raw_headers})
            retry = f"retry: {RETRY_MS}\n\n".encode()
            await send({"type": "http.response.body", "body": retry, "more_body": True})
            await self._stream(scope, send, gone)
        finally:
            feed.leave(self.shape, self.every)
            watcher.cancel()

    async def _stream(self, scope: Scope, send: Send, gone: asyncio.Event) -> None:
        feed = self.feed
        # how long an event may wait to be taken: the viewer's backlog of intervals
        patience_s = feed.limits.picture_backlog * self.every * TICK_S
        closing = scope.get("extensions", {}).get(CONNECTION_EXTENSION, {}).get("closing")
        stops = [gone] if closing is None else [gone, closing]
        end = time.monotonic() + MAX_STREAM_S
        tick = feed.tick_now()
        going = True
        if feed.stride() > 1:
            # under load the first event waits for the next shared tick as well: viewers that
            # come and go (dropped ones reconnect) must not get past the bytes budget
            period = self.every * feed.stride()
            tick = (tick // period + 1) * period
            going = await _sleep_until(tick * TICK_S, stops)
        while going:
            try:
                event = await feed.event(self.node, self.shape, tick)
            except Exception:  # logged once by the feed; the stream ends (the browser returns)
                break
            if not await self._hand_over(scope, send, event, patience_s):
                return
            # the next tick of this interval (stretched under load): shared by its viewers
            period = self.every * feed.stride()
            tick = (feed.tick_now() // period + 1) * period
            at = tick * TICK_S
            going = at < end and await _sleep_until(at, stops)
        if not gone.is_set():
            await self._hand_over(scope, send, b"", patience_s, more=False)

    async def _hand_over(
        self, scope: Scope, send: Send, body: bytes, patience_s: float, more: bool = True
    ) -> bool:
        """Give ``body`` to the server; False (and the connection closed) when the viewer
        has not taken enough of what came before for it to go within ``patience_s``."""
        try:
            await asyncio.wait_for(
                send({"type": "http.response.body", "body": body, "more_body": more}), timeout=patience_s
            )
            return True
        except TimeoutError:
            self.feed.note_dropped(scope, patience_s)
            abort = scope.get("extensions", {}).get(CONNECTION_EXTENSION, {}).get("abort")
            if abort is not None:
                abort()  # the server's own: closes without logging an unfinished response
            # (under another server the unfinished response makes it close the connection)
            return False


async def _sleep_until(at: float, stops: list[asyncio.Event]) -> bool:
    """Wait until ``at`` (monotonic); False as soon as one of ``stops`` is set."""
    if any(e.is_set() for e in stops):
        return False
    waits = [asyncio.ensure_future(e.wait()) for e in stops]
    done, pending = await asyncio.wait(waits, timeout=max(0.0, at - time.monotonic()))
    for w in pending:
        w.cancel()
    return not done


def page_html() -> str:
    return (STATIC_DIR / "picture.html").read_text(encoding="utf-8")


def add_picture(app: FastAPI, limits: HttpLimits) -> PictureFeed:
    """``/picture`` and ``/picture/events`` on ``app`` (as its own routes: FastAPI lists an
    included router as one entry of ``app.routes``, without its paths); the feed they share."""
    feed = PictureFeed(limits)

    @app.get("/picture", response_class=HTMLResponse, summary="The live operator picture (HTML)")
    def picture() -> HTMLResponse:
        return HTMLResponse(
            page_html(), headers={"Cache-Control": "no-cache", "Content-Security-Policy": PICTURE_CSP}
        )

    @app.get(
        "/picture/events",
        response_class=StreamingResponse,
        summary="The operator picture's live feed (server-sent events)",
        responses={
            200: {"content": {"text/event-stream": {}}, "description": "`snapshot` events"},
            503: {"description": "service starting, or too many viewers"},
        },
    )
    async def picture_events(
        node: NodeDep,
        status: Annotated[str, Query(pattern="^(confirmed|all)$")] = "confirmed",
        max_items: Annotated[int, Query(ge=1, le=MAX_ITEMS_LIMIT)] = DEFAULT_MAX_ITEMS,
        interval_s: Annotated[float, Query(ge=MIN_INTERVAL_S, le=MAX_INTERVAL_S)] = DEFAULT_INTERVAL_S,
    ) -> Response:
        shape = (status, quantised_max_items(max_items))
        return PictureStream(feed, node, shape, quantised_interval_s(interval_s))

    return feed
