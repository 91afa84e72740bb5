"""CAT021 Mode 3/A (I021/070) and flight level (I021/145) reach ``AdsbBatch`` (contract §5.2)."""

from __future__ import annotations

from typing import Any

import asterix.generated as gen

from service.asterix.bridge import AsterixBridge, BridgeParams, DayClock
from service.asterix.decode import Cat021Report, Decoded, decode_datagram
from service.wire.models import AdsbBatch, RadarSite

C021 = gen.Cat_021_2_7
MIDNIGHT = 1_763_769_600.0
SITES = [RadarSite(radar_id="A", latitude_deg=48.0, longitude_deg=2.0, sac=25, sic=11)]


def _record(tod: float, icao: int, m3a: str | None, fl: float | None) -> Any:
    args: dict[str, Any] = {
        "010": (("SAC", 25), ("SIC", 1)),
        "040": ((("ATP", 0), ("ARC", 0), ("RC", 0), ("RAB", 0), None),),
        "131": (("LAT", (48.5, "°")), ("LON", (2.5, "°"))),
        "080": icao,
        "073": (tod, "s"),
        "140": (10_000.0 / 0.3048, "ft"),
    }
    if m3a is not None:
        args["070"] = (0, ("MODE3A", m3a))  # four spare bits, then the 12-bit code
    if fl is not None:
        args["145"] = (fl, "FL")
    return C021.cv_record.create(args)


def _decoded(*records: Any) -> Decoded:
    out = Decoded()
    decode_datagram(C021.create(list(records)).unparse().to_bytes(), out)
    assert out.errors == {}
    return out


def test_the_decoder_reads_mode_3a_and_flight_level_of_cat021() -> None:
    d = _decoded(_record(10.0, 0x3C6444, "4521", 340.25), _record(10.5, 0x3C6445, None, None))
    a, b = d.cat021
    assert (a.icao24, a.mode_3a, a.flight_level) == ("3c6444", "4521", 340.25)
    assert (b.icao24, b.mode_3a, b.flight_level) == ("3c6445", None, None)


def test_the_bridge_fills_the_adsb_columns_and_leaves_them_out_when_nobody_sent_them() -> None:
    bridge = AsterixBridge(SITES, BridgeParams(adsb_source_id="adsb-x", adsb_batch_s=1.0), DayClock(MIDNIGHT))
    d = _decoded(
        _record(5.0, 0x3C6444, "4521", 340.0),
        _record(5.5, 0x3C6445, None, 1e4),  # a level beyond what I021/145 may hold: garbled
        _record(6.2, 0x3C6444, "4521", 340.5),
    )
    (msg,) = bridge.feed(d)
    body = AdsbBatch.model_validate(msg.body)
    assert body.reports.mode_3a == ["4521", None]
    assert body.reports.flight_level == [340.0, None]
    (msg,) = bridge.flush()
    assert msg.body["reports"]["mode_3a"] == ["4521"] and msg.body["reports"]["flight_level"] == [340.5]
    plain = AsterixBridge(SITES, BridgeParams(adsb_source_id="adsb-x", adsb_batch_s=1.0), DayClock(MIDNIGHT))
    plain.feed(_decoded(_record(5.0, 0x3C6444, None, None)))
    (msg,) = plain.flush()
    assert "mode_3a" not in msg.body["reports"] and "flight_level" not in msg.body["reports"]


def test_a_report_tuple_without_the_new_field_is_still_one() -> None:
    r = Cat021Report(25, 1, 5.0, "3c6444", 48.1, 2.1, 10_000.0, 330.0)
    assert r.mode_3a is None
