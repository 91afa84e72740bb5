"""The bridge's own rules (service/asterix/bridge.py): batches by CAT034, time across midnight,
heights, sources, and what it leaves out."""

from __future__ import annotations

import pytest

from service.asterix.bridge import DAY_S, FL_M, AsterixBridge, BridgeParams, DayClock
from service.asterix.decode import Cat021Report, Cat034Message, Cat048Report, Decoded
from service.wire.models import MAX_BATCH_ITEMS, AdsbBatch, PlotBatch, RadarSite

MIDNIGHT = 1_700_006_400.0  # 2023-11-15T00:00:00Z
assert MIDNIGHT % DAY_S == 0
SITES = [
    RadarSite(radar_id="R1", latitude_deg=48.0, longitude_deg=2.0, sac=25, sic=11),
    RadarSite(radar_id="R2", latitude_deg=48.5, longitude_deg=2.5, sac=25, sic=12),
    RadarSite(radar_id="R3", latitude_deg=49.0, longitude_deg=3.0),  # no sac/sic: not mapped
]


def plot(tod: float, sic: int = 11, **kw: object) -> Cat048Report:
    fields: dict[str, object] = {
        "sac": 25,
        "sic": sic,
        "tod_s": tod,
        "rho_m": 50_000.0,
        "theta_deg": 10.0,
        "mode_3a": None,
        "flight_level": None,
        "mode_s": None,
        "height_m": None,
        "test_target": False,
    }
    fields.update(kw)
    return Cat048Report(**fields)  # type: ignore[arg-type]


def sector(tod: float, sic: int = 11, kind: int = 2) -> Cat034Message:
    return Cat034Message(25, sic, kind, tod, 90.0)


def decoded(*records: object) -> Decoded:
    out = Decoded()
    for r in records:
        {Cat048Report: out.cat048, Cat034Message: out.cat034, Cat021Report: out.cat021}[type(r)].append(r)
    return out


def test_day_clock_crosses_midnight_both_ways() -> None:
    clock = DayClock(MIDNIGHT)
    assert clock.time_s(86_399.0) == MIDNIGHT + 86_399.0
    assert clock.time_s(0.5) == MIDNIGHT + DAY_S + 0.5  # after midnight: the next day
    assert clock.time_s(86_399.9) == MIDNIGHT + 86_399.9  # a late report from before midnight
    assert clock.time_s(3.0) == MIDNIGHT + DAY_S + 3.0
    # the capture's time stamp decides when there is one
    assert DayClock().time_s(86_399.0, reference_s=MIDNIGHT + DAY_S + 1.0) == MIDNIGHT + 86_399.0
    assert DayClock().time_s(2.0, reference_s=MIDNIGHT - 1.0) == MIDNIGHT + 2.0


def test_plots_are_batched_at_each_sector_message_by_their_own_time() -> None:
    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    # one datagram: a plot after the sector boundary comes before the sector message
    out = bridge.feed(decoded(plot(100.0), plot(101.5), plot(100.9, mode_s="3c6444"), sector(101.0)))
    ((msg),) = out
    body = PlotBatch.model_validate(msg.body)
    assert (msg.kind, msg.source_id, body.seq, body.time_s) == ("plots", "R1", 1, MIDNIGHT + 101.0)
    assert body.plots.time_s == [MIDNIGHT + 100.0, MIDNIGHT + 100.9]
    assert body.plots.mode_s == [None, "3c6444"]
    assert body.plots.altitude_m is None  # nothing to derive one from
    # north marker: the held plot goes; an empty sector still gives a batch (the radar's clock)
    (msg,) = bridge.feed(decoded(sector(102.0, kind=1)))
    assert (msg.body["seq"], msg.body["plots"]["time_s"]) == (2, [MIDNIGHT + 101.5])
    (msg,) = bridge.feed(decoded(sector(103.0)))
    assert (msg.body["seq"], msg.body["plots"]["time_s"]) == (3, [])
    # a sector message late or out of order never moves the batch time back
    (msg,) = bridge.feed(decoded(sector(102.5)))
    assert msg.body["time_s"] == MIDNIGHT + 103.0


def test_heights_flight_levels_and_codes() -> None:
    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    bridge.feed(
        decoded(
            plot(1.0, height_m=9_000.0, flight_level=300.0, mode_3a="7000"),  # measured height wins
            plot(1.1, flight_level=300.0),  # ISA: FL x 100 ft
            plot(1.2, flight_level=2000.0),  # beyond I048/090's valid range: garbled
        )
    )
    (msg,) = bridge.flush()
    p = PlotBatch.model_validate(msg.body).plots
    assert p.altitude_m == [9_000.0, pytest.approx(300 * FL_M), None]
    assert p.flight_level == [300.0, 300.0, None]
    assert p.mode_3a == ["7000", None, None]
    no_fl = AsterixBridge(SITES, BridgeParams(altitude_from_fl=False), DayClock(MIDNIGHT))
    no_fl.feed(decoded(plot(1.0, flight_level=300.0)))
    (msg,) = no_fl.flush()
    assert "altitude_m" not in msg.body["plots"]


def test_unusable_reports_are_counted_by_cause() -> None:
    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    d = decoded(
        plot(1.0, sic=99),  # unknown source
        plot(1.0, rho_m=None, theta_deg=None),
        plot(1.0, tod_s=None),
        sector(2.0, sic=99),
        Cat021Report(25, 1, 1.0, None, 48.0, 2.0, None, None),
        Cat021Report(25, 1, 1.0, "3c6444", None, None, None, None),
    )
    d.errors["undecodable"] += 2
    assert bridge.feed(d) == []
    assert bridge.flush() == []
    assert dict(bridge.unusable) == {
        "cat048_unknown_source": 1,
        "cat048_no_position": 1,
        "cat048_no_time": 1,
        "cat034_unknown_source": 1,
        "cat021_no_address": 1,
        "cat021_no_position": 1,
        "blocks_undecodable": 2,
    }


def test_a_radar_without_cat034_is_cut_by_time_and_two_radars_stay_apart() -> None:
    bridge = AsterixBridge(SITES, BridgeParams(max_batch_s=2.0), DayClock(MIDNIGHT))
    assert bridge.feed(decoded(plot(10.0), plot(10.5, sic=12), plot(11.0))) == []
    (msg,) = bridge.feed(decoded(plot(12.0), plot(12.2)))
    assert (msg.source_id, msg.body["time_s"], len(msg.body["plots"]["time_s"])) == ("R1", MIDNIGHT + 12.2, 4)
    rest = bridge.flush()
    assert [(m.source_id, m.body["plots"]["time_s"]) for m in rest] == [("R2", [MIDNIGHT + 10.5])]


def test_adsb_reports_become_batches_of_one_source() -> None:
    bridge = AsterixBridge(SITES, BridgeParams(adsb_source_id="adsb-x", adsb_batch_s=1.0), DayClock(MIDNIGHT))
    a = Cat021Report(25, 1, 5.0, "3c6444", 48.1, 2.1, 10_000.0, 330.0)
    b = Cat021Report(25, 2, 5.5, "3c6445", 48.2, 2.2, None, 330.0)
    assert bridge.feed(decoded(a, b)) == []
    (msg,) = bridge.feed(decoded(a._replace(tod_s=6.2)))
    body = AdsbBatch.model_validate(msg.body)
    assert (msg.kind, body.source_id, body.seq, body.time_s) == ("adsb", "adsb-x", 1, MIDNIGHT + 5.5)
    assert body.reports.icao24 == ["3c6444", "3c6445"]
    assert body.reports.altitude_m == [10_000.0, None]  # barometric levels are not heights
    (msg,) = bridge.flush()
    assert msg.body["seq"] == 2 and "altitude_m" in msg.body["reports"]


def test_two_radars_with_one_sac_sic_are_refused() -> None:
    with pytest.raises(ValueError, match="SAC/SIC 25/11"):
        AsterixBridge([*SITES, RadarSite(radar_id="R9", latitude_deg=1.0, longitude_deg=1.0, sac=25, sic=11)])


def test_a_height_beyond_the_contract_costs_its_record_the_height_not_its_batch_the_record() -> None:
    """I048/110 and I021/140 can hold heights of -62 km: such a height is left out (counted),
    the record used without it, so that the service takes the batch it is in."""
    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    (msg,) = bridge.feed(
        decoded(plot(100.0, height_m=-62_000.0), plot(100.5, height_m=9_000.0), sector(101.0))
    )
    assert PlotBatch.model_validate(msg.body).plots.altitude_m == [None, 9_000.0]
    a = Cat021Report(25, 1, 100.0, "3c6444", 48.1, 2.1, -62_000.0, 330.0)
    assert bridge.feed(decoded(a, a._replace(icao24="3c6445", geometric_height_m=10_000.0))) == []
    (msg,) = bridge.flush()
    assert AdsbBatch.model_validate(msg.body).reports.altitude_m == [None, 10_000.0]
    assert bridge.unusable == {"cat048_bad_height": 1, "cat021_bad_height": 1}


def test_test_targets_and_times_of_day_past_a_day_are_left_out() -> None:
    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    test_target = plot(100.2, test_target=True)  # the radar's own test transponder
    past = plot(DAY_S + 100.3)  # the 24-bit item holds up to 36 h; a day has 24
    (msg,) = bridge.feed(decoded(plot(100.0), test_target, past, sector(101.0)))
    assert msg.body["plots"]["time_s"] == [MIDNIGHT + 100.0]
    late = Cat021Report(25, 1, DAY_S + 5.0, "3c6444", 48.1, 2.1, None, 330.0)
    assert bridge.feed(decoded(late, Cat034Message(25, 11, 2, DAY_S + 102.0, 90.0))) == []
    assert bridge.unusable == {
        "cat048_test_target": 1,
        "cat048_bad_time": 1,
        "cat021_bad_time": 1,
        "cat034_bad_time": 1,
    }


def test_an_adsb_report_stamped_ahead_holds_no_batch_open() -> None:
    """One report 25 s ahead of the capture's clock (inside the 30 s tolerance): the batches go
    on every second, and the report goes out in the batch of its own time."""
    bridge = AsterixBridge(SITES, BridgeParams(adsb_batch_s=1.0), DayClock(MIDNIGHT))
    batches = []
    for k in range(40):
        now = MIDNIGHT + 100.0 + k
        reports = [Cat021Report(25, 1, 99.5 + k, "3c6444", 48.1, 2.1, None, 330.0)]
        if k == 2:
            reports.append(reports[0]._replace(icao24="3c6445", tod_s=127.0))
        batches += [AdsbBatch.model_validate(m.body) for m in bridge.feed(decoded(*reports), now)]
    assert len(batches) == 39  # one a second (the last still held)
    times = [b.time_s for b in batches]
    assert times == sorted(times) and times[0] == MIDNIGHT + 99.5
    ahead = [b for b in batches if "3c6445" in b.reports.icao24]
    assert len(ahead) == 1 and ahead[0].time_s == MIDNIGHT + 127.0


def test_reports_held_past_a_batch_s_bound_go_out_in_batches_the_contract_takes() -> None:
    bridge = AsterixBridge(SITES, BridgeParams(adsb_batch_s=1.0), DayClock(MIDNIGHT))
    ahead = [
        Cat021Report(25, 1, 110.0 + i * 1e-4, f"{i:06x}", 48.1, 2.1, None, 330.0)
        for i in range(MAX_BATCH_ITEMS + 5)
    ]
    # stamped 10 s ahead of the capture's clock: held (none is due), however many
    assert bridge.feed(decoded(*ahead), MIDNIGHT + 100.0) == []
    batches = [AdsbBatch.model_validate(m.body) for m in bridge.flush()]
    assert [len(b.reports.icao24) for b in batches] == [MAX_BATCH_ITEMS, 5]
    assert batches[0].time_s <= batches[1].time_s


def test_an_adsb_feed_that_lags_the_clock_still_makes_one_batch_a_second() -> None:
    """Reports arriving 1.5 s behind the capture's clock (a relay's buffer): one batch per
    --adsb-batch of the clock, not one per report."""
    bridge = AsterixBridge(SITES, BridgeParams(adsb_batch_s=1.0), DayClock(MIDNIGHT))
    sent = []
    for k in range(1000):  # 100 reports a second for 10 s
        now = MIDNIGHT + 100.0 + k / 100
        report = Cat021Report(25, 1, now - MIDNIGHT - 1.5, "3c6444", 48.1, 2.1, None, 330.0)
        sent += bridge.feed(decoded(report), now)
    assert 9 <= len(sent) <= 10, len(sent)
    assert sum(len(m.body["reports"]["time_s"]) for m in sent + bridge.flush()) == 1000
