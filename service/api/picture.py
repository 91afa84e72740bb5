"""The operator picture (docs/contract.md §4.5): ``GET /picture`` and its live feed.

``GET /picture`` is a page of plain HTML, CSS and JavaScript (``service/api/static/``: no
library, no font, no tile, nothing from another host) that draws, on a lat/lon graticule with
pan and zoom: the radar sites with their coverage rings, the radars' tracks (faint), the system
tracks (bold, with their ids and velocity leaders), the correlation links between paired radar
tracks, each radar's bias estimate as an arrow with an uncertainty ellipse, and a health panel.

``GET /picture/events`` feeds it: server-sent events, one compact JSON snapshot about every
second of wall time (``interval_s``), built from the node's latest read-model snapshot (the
state ``/status``, ``/radars``, ``/radars/{id}/tracks``, ``/pairs``, ``/system-tracks`` and
``/biases`` answer).  It is bounded: confirmed tracks only unless ``status=all``, and at most
``max_items`` system tracks, ``max_items`` radar tracks over all radars and ``max_items``
links (the counts left out are in ``truncated``).  Snapshots are built at most once per
``CACHE_S`` for any number of viewers, on a worker thread (a partitioned worker's ``/pairs``
asks the other workers over Zenoh).

The maths here is only presentation (east/north components of a velocity at a track's
latitude and longitude): the numerics stay in the engine (the import rules of pyproject.toml).
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated, Any

import orjson
from fastapi import FastAPI, Query, Request
from fastapi.responses import HTMLResponse, StreamingResponse
from starlette.concurrency import run_in_threadpool

from service.api.deps import NodeDep
from service.transport.node import ServiceNode

STATIC_DIR = Path(__file__).resolve().parent / "static"
#: Default and largest ``max_items`` of ``/picture/events``.
DEFAULT_MAX_ITEMS = 2000
MAX_ITEMS_LIMIT = 20000
#: Default wall seconds between two events, and the bounds of ``interval_s``.
DEFAULT_INTERVAL_S = 1.0
MIN_INTERVAL_S, MAX_INTERVAL_S = 0.2, 10.0
#: A stream ends after this many wall seconds; the browser's EventSource reconnects by itself
#: (``retry``), so that no connection outlives a shutdown or a proxy's idle limit for long.
MAX_STREAM_S = 300.0
RETRY_MS = 2000
#: A snapshot is reused by every viewer for this long (wall seconds).
CACHE_S = 0.5
#: The page loads its own script and styles and its feed, nothing else (inline styles: the
#: colour swatches of the health panel).
PICTURE_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "connect-src 'self'; base-uri 'self'; form-action 'self'"
)
#: Coordinates are rounded to this many decimals of a degree (about 1 m).
DECIMALS = 5


def _east_north(lat_deg: float, lon_deg: float, v: list[float]) -> tuple[float, float]:
    """East and north components (m/s) of an ECEF velocity at a latitude and longitude."""
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    sla, cla, slo, clo = math.sin(la), math.cos(la), math.sin(lo), math.cos(lo)
    east = -slo * v[0] + clo * v[1]
    north = -sla * clo * v[0] - sla * slo * v[1] + cla * v[2]
    return round(east, 1), round(north, 1)


def _r(x: float | None, digits: int = DECIMALS) -> float | None:
    return None if x is None or not math.isfinite(x) else round(x, digits)


def build_snapshot(
    node: ServiceNode, status: str = "confirmed", max_items: int = DEFAULT_MAX_ITEMS
) -> dict[str, Any]:
    """The picture's JSON snapshot (what each event of ``/picture/events`` carries)."""
    snap = node.snapshot
    st = node.status()
    sites = node.radars()
    truncated = {"system_tracks": 0, "tracks": 0, "links": 0}

    # radar tracks: max_items over all radars, shared out evenly
    radar_ids = sorted(snap.tracks)
    per_radar = max(1, max_items // max(1, len(radar_ids)))
    tracks: dict[str, list[list[Any]]] = {}
    where: dict[str, dict[str, tuple[float, float]]] = {}
    for rid in radar_ids:
        every = snap.track_batch(rid, "all") or {"tracks": []}
        where[rid] = {t["track_id"]: (t["latitude_deg"], t["longitude_deg"]) for t in every["tracks"]}
        rows = (
            every["tracks"] if status == "all" else [t for t in every["tracks"] if t["status"] == "confirmed"]
        )
        truncated["tracks"] += max(0, len(rows) - per_radar)
        tracks[rid] = [
            [t["track_id"], _r(t["latitude_deg"]), _r(t["longitude_deg"]), int(t["status"] == "confirmed")]
            for t in rows[:per_radar]
        ]

    # correlation links: between the two radar tracks of each pair whose positions are known
    links: list[list[Any]] = []
    for ps in node.pair_sets(None, None, "all" if status == "all" else "confirmed"):
        at_a, at_b = where.get(ps["radar_a"], {}), where.get(ps["radar_b"], {})
        for p in ps["pairs"]:
            pa, pb = at_a.get(p["track_a"]), at_b.get(p["track_b"])
            if pa is None or pb is None:
                continue
            if len(links) >= max_items:
                truncated["links"] += 1
                continue
            links.append(
                [ps["radar_a"], ps["radar_b"], _r(pa[0]), _r(pa[1]), _r(pb[0]), _r(pb[1]), p["status"][0]]
            )

    system = snap.system_tracks(status)
    rows = system["system_tracks"]
    truncated["system_tracks"] = max(0, len(rows) - max_items)
    system_tracks = [
        [
            t["system_track_id"],
            _r(t["latitude_deg"]),
            _r(t["longitude_deg"]),
            *_east_north(t["latitude_deg"], t["longitude_deg"], t["velocity_ecef_mps"]),
            _r(t["position_sigma_m"], 1),
            len(t["members"]),
            int(t["status"] == "confirmed"),
        ]
        for t in rows[:max_items]
    ]

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

    health = [
        {
            "radar_id": r["radar_id"],
            "batches": r["batches"],
            "plots": r["plots"],
            "rejected": r["rejected"],
            "lost_batches": r["lost_batches"],
            "window_plots": r["window_plots"],
            "tracks_confirmed": r["tracks_confirmed"],
            "tracks_tentative": r["tracks_tentative"],
            "last_time_s": r["last_time_s"],
            "expired": bool(r.get("expired", False)),
        }
        for r in st["radars"]
    ]
    missing = (st.get("partition") or {}).get("missing", [])
    return {
        "wall_s": round(time.time(), 3),
        "time_s": system["time_s"],
        "status": status,
        "max_items": max_items,
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
        "health": {
            "radars": health,
            "correlation": st["correlation"],
            "pairs_confirmed": st["pairs_confirmed"],
            "pairs_tentative": st["pairs_tentative"],
            "rejected": st["rejected"],
            "queue": st.get("queue", {}),
            "missing_partitions": missing,
            "method": st["method"],
        },
        "truncated": truncated,
    }


class SnapshotCache:
    """One encoded snapshot per ``(status, max_items)`` for every viewer, at most ``CACHE_S`` old."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._held: dict[tuple[str, int], tuple[float, bytes]] = {}

    def get(self, node: ServiceNode, status: str, max_items: int) -> bytes:
        key = (status, max_items)
        with self._lock:
            held = self._held.get(key)
            if held is not None and time.monotonic() - held[0] < CACHE_S:
                return held[1]
            body = orjson.dumps(build_snapshot(node, status, max_items))
            self._held = {k: v for k, v in self._held.items() if time.monotonic() - v[0] < CACHE_S}
            self._held[key] = (time.monotonic(), body)
            return body


def page_html() -> str:
    return (STATIC_DIR / "picture.html").read_text(encoding="utf-8")


def add_picture(app: FastAPI) -> None:
    """``/picture`` and ``/picture/events`` on ``app`` (as its own routes: FastAPI lists an
    included router as one entry of ``app.routes``, without its paths)."""
    cache = SnapshotCache()

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
            503: {"description": "service starting"},
        },
    )
    async def picture_events(
        request: Request,
        node: NodeDep,
        status: Annotated[str, Query(pattern="^(confirmed|all)$")] = "confirmed",
        max_items: Annotated[int, Query(ge=1, le=MAX_ITEMS_LIMIT)] = DEFAULT_MAX_ITEMS,
        interval_s: Annotated[float, Query(ge=MIN_INTERVAL_S, le=MAX_INTERVAL_S)] = DEFAULT_INTERVAL_S,
    ) -> StreamingResponse:
        async def events() -> AsyncIterator[bytes]:
            yield f"retry: {RETRY_MS}\n\n".encode()
            end = time.monotonic() + MAX_STREAM_S
            while time.monotonic() < end and not await request.is_disconnected():
                body = await run_in_threadpool(cache.get, node, status, max_items)
                yield b"event: snapshot\ndata: " + body + b"\n\n"
                await asyncio.sleep(interval_s)

        return StreamingResponse(
            events(),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
        )
