"""A simulated scenario as an ASTERIX feed, and its JSON messages at ASTERIX resolution.

:func:`asterix_datagrams` turns the simulator's messages into what a surveillance network
would send: each radar's plot batch as CAT048 target reports followed by a CAT034 sector
crossing at the batch's time, each ADS-B batch as CAT021 reports, in UDP-sized datagrams.  It
needs radars that send ``altitude_m`` (``two_d``; CAT048 carries a height, I048/110, not an
elevation) and sites with ``sac``/``sic``.

:func:`at_asterix_resolution` rounds a JSON message to the steps the items carry (1/128 s,
1/256 NM, 360/2^16 deg, 25 ft, 180/2^30 deg, 6.25 ft), so that the JSON input and the
ASTERIX feed hold the same information and must give the same tracks and pairs.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from typing import Any

from service.asterix.decode import FT_M, NM_M, Cat021Report, Cat034Message, Cat048Report
from topofusion_lab.asterix_encode import encode_cat021_blocks, encode_cat034_blocks, encode_cat048_blocks
from topofusion_lab.scenarios.simulator import SimMessage

DAY_S = 86_400.0
#: The steps of the items written (EUROCONTROL CAT048 1.32, CAT021 2.7).
TOD_STEP = 1.0 / 128.0
RANGE_STEP_M = NM_M / 256.0
AZIMUTH_STEP_DEG = 360.0 / 65536.0
HEIGHT_STEP_M = 25.0 * FT_M
LATLON_STEP_DEG = 180.0 / 2**30
ADSB_HEIGHT_STEP_M = 6.25 * FT_M
#: SAC/SIC of the simulated ADS-B ground station.
ADSB_SAC_SIC = (0, 1)


def _q(x: float, step: float) -> float:
    return round(x / step) * step


def _tod(t: float) -> float:
    return t - math.floor(t / DAY_S) * DAY_S


def _time(t: float) -> float:
    day = math.floor(t / DAY_S) * DAY_S
    return day + _q(t - day, TOD_STEP)


def asterix_datagrams(
    messages: Iterable[SimMessage], sac_sic: dict[str, tuple[int, int]], max_bytes: int = 1400
) -> Iterator[bytes]:
    """The datagrams of ``messages`` (sites are skipped: the bridge has its sites file)."""
    for m in messages:
        yield from message_datagrams(m, sac_sic, max_bytes)


def message_datagrams(
    m: SimMessage, sac_sic: dict[str, tuple[int, int]], max_bytes: int = 1400
) -> list[bytes]:
    """The datagrams of one message: a radar's plot batch as CAT048 then one CAT034 sector
    crossing at the batch's time, an ADS-B batch as CAT021; none for a site or an AIS batch
    (AIS is not ASTERIX)."""
    if m.kind == "plots":
        return list(_radar(m.body, *sac_sic[m.radar_id], max_bytes))
    if m.kind == "adsb":
        r = m.body["reports"]
        alt = r.get("altitude_m") or [None] * len(r["time_s"])
        reports = [
            Cat021Report(*ADSB_SAC_SIC, _tod(t), icao, la, lo, h, None)
            for t, icao, la, lo, h in zip(
                r["time_s"], r["icao24"], r["latitude_deg"], r["longitude_deg"], alt, strict=True
            )
        ]
        return encode_cat021_blocks(reports, max_bytes)
    return []


def _radar(body: dict[str, Any], sac: int, sic: int, max_bytes: int) -> Iterator[bytes]:
    p = body["plots"]
    n = len(p["time_s"])
    if "altitude_m" not in p:
        raise ValueError("asterix_datagrams needs radars that send altitude_m (two_d)")
    none = [None] * n
    reports = [
        Cat048Report(sac, sic, _tod(t), r, a, m3a, fl, ms, h, False)
        for t, r, a, h, m3a, ms, fl in zip(
            p["time_s"],
            p["range_m"],
            p["azimuth_deg"],
            p["altitude_m"],
            p.get("mode_3a") or none,
            p.get("mode_s") or none,
            p.get("flight_level") or none,
            strict=True,
        )
    ]
    yield from encode_cat048_blocks(reports, max_bytes)
    yield from encode_cat034_blocks([Cat034Message(sac, sic, 2, _tod(body["time_s"]), None)], max_bytes)


def at_asterix_resolution(kind: str, body: dict[str, Any]) -> dict[str, Any]:
    """A copy of a ``plots`` or ``adsb`` message rounded as the ASTERIX feed carries it."""
    if kind == "plots":
        p = body["plots"]
        plots = {
            **p,
            "time_s": [_time(t) for t in p["time_s"]],
            "range_m": [_q(r, RANGE_STEP_M) for r in p["range_m"]],
            "azimuth_deg": [_q(a, AZIMUTH_STEP_DEG) % 360.0 for a in p["azimuth_deg"]],
            "altitude_m": [_q(h, HEIGHT_STEP_M) for h in p["altitude_m"]],
        }
        plots.pop("truth_id", None)  # not in the feed
        return {**body, "time_s": _time(body["time_s"]), "plots": plots}
    if kind == "adsb":
        r = body["reports"]
        reports = {
            **r,
            "time_s": [_time(t) for t in r["time_s"]],
            "latitude_deg": [_q(x, LATLON_STEP_DEG) for x in r["latitude_deg"]],
            "longitude_deg": [_q(x, LATLON_STEP_DEG) for x in r["longitude_deg"]],
        }
        if "altitude_m" in r:
            reports["altitude_m"] = [
                None if h is None else _q(h, ADSB_HEIGHT_STEP_M) for h in r["altitude_m"]
            ]
        return {**body, "time_s": _time(body["time_s"]), "reports": reports}
    return body
