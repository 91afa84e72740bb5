"""The bridge's limits (service/asterix/bridge.py, command.py): times judged against the
bridge's clock, held records bounded in count, bytes and data time, losses shown as skipped
``seq`` numbers, puts that fail and a stop's deadline."""

from __future__ import annotations

import gc
import threading
import time
import tracemalloc
from pathlib import Path

import pytest

from service.asterix.bridge import HELD_RECORD_BYTES, AsterixBridge, BridgeParams, DayClock, Message
from service.asterix.capture import Datagram
from service.asterix.command import Publisher, Run
from service.asterix.decode import Cat021Report, Cat034Message, Cat048Report, Decoded
from service.wire.models import PlotBatch, RadarSite
from topofusion_lab.asterix_encode import encode_cat034_block, encode_cat048_block

MIDNIGHT = 1_700_006_400.0  # 2023-11-15T00:00:00Z
NOW = MIDNIGHT + 43_200.0  # noon: the bridge's clock in these tests
SITES = [
    RadarSite(radar_id="R1", latitude_deg=48.0, longitude_deg=2.0, sac=25, sic=11),
    RadarSite(radar_id="R2", latitude_deg=48.5, longitude_deg=2.5, sac=25, sic=12),
]
H3, H6 = 3 * 3600.0, 6 * 3600.0


def plot(t: float, sic: int = 11, k: int = 0) -> Cat048Report:
    return Cat048Report(
        25, sic, t % 86_400.0, 50_000.0 + k, 10.0, "1234", 300.0, f"{k % 2**24:06x}", None, False
    )


def sector(t: float, sic: int = 11) -> Cat034Message:
    return Cat034Message(25, sic, 2, t % 86_400.0, 90.0)


def adsb(t: float, k: int = 0) -> Cat021Report:
    return Cat021Report(25, 1, t % 86_400.0, f"{k:06x}", 48.0, 2.0, 10_000.0, None)


def decoded(*records: object) -> Decoded:
    out = Decoded()
    for r in records:
        {Cat048Report: out.cat048, Cat034Message: out.cat034, Cat021Report: out.cat021}[type(r)].append(r)
    return out


def bodies(messages: list[Message]) -> list[tuple[str, int, float, int]]:
    return [
        (
            m.source_id,
            m.body["seq"],
            m.body["time_s"],
            len((m.body.get("plots") or m.body["reports"])["time_s"]),
        )
        for m in messages
    ]


# -- time -------------------------------------------------------------------------------------


def test_a_sector_message_out_of_tolerance_is_dropped_and_moves_no_batch_time() -> None:
    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    assert bodies(bridge.feed(decoded(plot(NOW - 0.5), sector(NOW)), NOW)) == [("R1", 1, NOW, 1)]
    assert bridge.feed(decoded(sector(NOW + H3)), NOW + 0.1) == []  # 3 h ahead of the clock
    assert bridge.feed(decoded(sector(NOW - 120.0)), NOW + 0.2) == []  # 2 min behind it
    got = bridge.feed(decoded(plot(NOW + 0.5), sector(NOW + 1.0)), NOW + 1.0)
    assert bodies(got) == [("R1", 2, NOW + 1.0, 1)]  # the next batch: on time
    assert bridge.unusable == {"cat034_time_ahead": 1, "cat034_time_behind": 1}
    # within the tolerance a stamp is taken as it is (clocks differ a little)
    p = BridgeParams()
    ahead = NOW + 1.0 + p.max_time_ahead_s - 1.0
    assert bodies(bridge.feed(decoded(sector(ahead)), NOW + 1.0)) == [("R1", 3, ahead, 0)]


def test_plots_and_adsb_reports_out_of_tolerance_are_dropped_never_held() -> None:
    bridge = AsterixBridge(SITES, BridgeParams(adsb_batch_s=1.0), DayClock(MIDNIGHT))
    stray = [plot(NOW + H6, k=k) for k in range(1000)]
    assert bridge.feed(decoded(*stray, plot(NOW - 0.2, k=7)), NOW) == []
    assert bridge.held == 1  # only the plot in time waits for its sector
    assert bridge.feed(decoded(adsb(NOW - 0.5), adsb(NOW + H3, 1), adsb(NOW - 0.4, 2)), NOW) == []
    assert bridge.held == 3
    # a batch a second of the bridge's clock, whatever a report stamped 3 h ahead says
    got = bridge.feed(decoded(adsb(NOW + 0.6, 3), sector(NOW)), NOW + 1.0)
    assert bodies(got) == [("adsb", 1, NOW - 0.4, 2), ("R1", 1, NOW, 1)]  # not held for 3 h
    assert bridge.unusable == {"cat048_time_ahead": 1000, "cat021_time_ahead": 1}


def test_without_an_outside_clock_the_data_judges_itself_and_follows_a_jump() -> None:
    params = BridgeParams(rebase_after_records=50)
    bridge = AsterixBridge(SITES, params, DayClock(MIDNIGHT))
    start = MIDNIGHT + 3_600.0
    bridge.feed(decoded(plot(start), sector(start + 0.1)))  # the first time starts the clock
    assert bridge.feed(decoded(sector(start + H3))) == []  # a stray stamp: dropped
    got = bridge.feed(decoded(plot(start + 0.5), sector(start + 1.0)))
    assert bodies(got) == [("R1", 2, start + 1.0, 1)]
    # stray times that do not agree with each other never move it, however many
    strays = [plot(start + 600.0 * (k + 1), k=k) for k in range(100)]
    assert bridge.feed(decoded(*strays, plot(start + 1.5), sector(start + 2.0)))[0].body["seq"] == 3
    off = bridge.unusable.pop("cat048_time_ahead") + bridge.unusable.pop("cat048_time_behind")
    assert bridge.rebased == 0 and off == 100  # (past 12 h a time of day is on the day before)
    # a recording that jumps 2 h: 50 records in a row out of tolerance move the clock to them
    later = start + 7_200.0
    bridge.feed(decoded(*[plot(later + 0.01 * k, k=k) for k in range(60)]))
    assert bridge.rebased == 1
    assert bridge.unusable == {"cat034_time_ahead": 1, "cat048_time_ahead": 49}
    assert bodies(bridge.feed(decoded(sector(later + 1.0)))) == [("R1", 4, later + 1.0, 11)]


def test_a_raw_file_with_a_stray_stamp_is_not_paced_by_it(tmp_path: Path) -> None:
    """Pacing a raw file follows the data's clock: a stray stamp 3 h ahead must not make the
    bridge wait 3 h (nor move R1's batches)."""
    raw = tmp_path / "feed.ast"
    raw.write_bytes(
        encode_cat048_block([plot(NOW)])
        + encode_cat034_block([sector(NOW + H3)])
        + encode_cat048_block([plot(NOW + 0.1)])
        + encode_cat034_block([sector(NOW + 0.2)])
    )
    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    sent: list[bytes] = []
    run = Run(bridge, Publisher(lambda k, p: sent.append(p), "fusion"), threading.Event(), speed=1.0)
    t0 = time.monotonic()
    run.files([raw])
    assert time.monotonic() - t0 < 2.0
    assert bridge.unusable == {"cat034_time_ahead": 1}
    assert [PlotBatch.model_validate_json(p).time_s for p in sent] == [pytest.approx(NOW + 0.2, abs=0.01)]


# -- held records -----------------------------------------------------------------------------


def test_held_records_are_bounded_in_count_the_longest_held_first() -> None:
    bridge = AsterixBridge(SITES, BridgeParams(max_held_records=100), DayClock(MIDNIGHT))
    bridge.feed(decoded(sector(NOW)), NOW)  # R1 is cut by sector messages from now on
    most = 0
    for i in range(25):
        bridge.feed(decoded(*[plot(NOW + 0.01 * (10 * i + k), k=10 * i + k) for k in range(10)]), NOW + 3)
        most = max(most, bridge.held)
    assert most <= 100 and bridge.held <= 100
    assert bridge.unusable["cat048_held_overflow"] == 250 - bridge.held
    (msg,) = bridge.feed(decoded(sector(NOW + 3.0)), NOW + 3)
    assert msg.body["seq"] == 3  # 2 stays unused: the service counts a lost batch
    kept = msg.body["plots"]["time_s"]
    assert kept == sorted(kept) and kept[-1] == NOW + 2.49  # the newest are the ones kept
    assert bridge.held == 0


def test_adsb_reports_count_against_the_bound_too() -> None:
    bridge = AsterixBridge(SITES, BridgeParams(max_held_records=50, adsb_batch_s=100.0), DayClock(MIDNIGHT))
    for i in range(120):
        bridge.feed(decoded(adsb(NOW + 0.01 * i, i)), NOW + 2)
        assert bridge.held <= 50
    assert bridge.unusable["cat021_held_overflow"] == 120 - bridge.held
    (msg,) = bridge.flush()
    assert msg.body["seq"] == 2 and msg.body["reports"]["icao24"][-1] == f"{119:06x}"


def test_a_radar_whose_sector_messages_stopped_holds_at_most_max_held_s() -> None:
    params = BridgeParams(max_held_s=20.0)
    bridge = AsterixBridge(SITES, params, DayClock(MIDNIGHT))
    bridge.feed(decoded(sector(NOW)), NOW)
    for i in range(600):  # 60 s of plots, 10 a second, and no sector message
        t = NOW + 0.1 * i
        bridge.feed(decoded(plot(t, k=i)), t)
        held = bridge._pending["R1"].columns["time_s"]
        assert max(held) - min(held) <= params.max_held_s
    assert bridge.unusable["cat048_held_too_long"] == 600 - bridge.held
    assert 150 <= bridge.held <= 200  # between three quarters of it and all of it


def test_one_chunk_longer_than_max_held_s_loses_nothing_to_its_own_sector_messages() -> None:
    """A raw file's chunk holds 90 s of a radar, plots and sector messages (the decoder gives
    them category by category): the data's own clock judges them in time order, and the plots
    wait for the chunk's own sector messages, whatever the span."""
    bridge = AsterixBridge(SITES, BridgeParams(max_held_s=20.0), DayClock(MIDNIGHT))
    bridge.feed(decoded(sector(NOW)))
    chunk = [plot(NOW + 0.1 * i, k=i) for i in range(900)] + [sector(NOW + 4.0 * j) for j in range(1, 23)]
    got = bridge.feed(decoded(*chunk))
    assert len(got) == 22 and sum(len(m.body["plots"]["time_s"]) for m in got) + bridge.held == 900
    assert bridge.held <= 20  # after the last sector message (at 88 s)
    assert not bridge.unusable


def test_held_records_take_at_most_held_record_bytes_each() -> None:
    """``max_held_records`` x ``HELD_RECORD_BYTES`` bounds the bytes held: measured."""
    bound = 20_000
    bridge = AsterixBridge(SITES, BridgeParams(max_held_records=bound, max_held_s=1e9), DayClock(MIDNIGHT))
    bridge.feed(decoded(sector(NOW - 1.0)), NOW)
    gc.collect()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        for i in range(30):  # 30 000 plots with every field, half again the bound
            records = [plot(NOW + 1e-5 * (1000 * i + k), k=1000 * i + k) for k in range(1000)]
            bridge.feed(decoded(*records), NOW)
            del records
        gc.collect()
        used = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert bridge.held <= bound
    assert used <= bound * HELD_RECORD_BYTES, used / bridge.held


def test_a_loss_before_decoding_skips_one_seq_number_per_source() -> None:
    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    bridge.feed(decoded(sector(NOW), sector(NOW, sic=12), adsb(NOW - 0.1)), NOW)
    assert bridge.fed == {"R1", "R2", "adsb"}
    bridge.mark_lost({"R1", "adsb", "unknown"})
    bridge.mark_lost({"R1"})  # twice in one interval: still one lost batch
    got = bridge.feed(decoded(adsb(NOW + 2.0), sector(NOW + 1.0), sector(NOW + 1.0, sic=12)), NOW + 2)
    # the held ADS-B report goes out as the first batch: its number 1 stays unused
    assert [(m.source_id, m.body["seq"]) for m in got] == [("adsb", 2), ("R1", 3), ("R2", 2)]
    got = bridge.feed(decoded(sector(NOW + 2.0)), NOW + 2)
    assert [(m.source_id, m.body["seq"]) for m in got] == [("R1", 4)]


# -- publishing -------------------------------------------------------------------------------


def test_a_failed_put_loses_its_batch_and_leaves_its_seq_unused() -> None:
    puts: list[bytes] = []

    def put(key: str, payload: bytes) -> None:
        if len(puts) == 1 and b'"seq":2' in payload:
            puts.append(b"")  # fail once
            raise RuntimeError("session closed")
        puts.append(payload)

    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    publisher = Publisher(put, "fusion")
    run = Run(bridge, publisher, threading.Event())
    for i in range(3):
        run.datagram(Datagram(encode_cat034_block([sector(NOW + i)]), None, "", ""), NOW + i)
    seqs = [PlotBatch.model_validate_json(p).seq for p in puts if p]
    assert seqs == [1, 3]
    assert publisher.failed == {"plots": 1} and publisher.sent == {"plots": 2}
    assert "batches lost to failed puts: plots 1 (session closed)" in run.summary()


def test_the_flush_at_a_stop_keeps_its_deadline() -> None:
    bridge = AsterixBridge(SITES, clock=DayClock(MIDNIGHT))
    bridge.feed(decoded(plot(NOW), plot(NOW, sic=12), adsb(NOW)), NOW)
    slow: list[str] = []

    def put(key: str, payload: bytes) -> None:
        slow.append(key)
        time.sleep(0.3)

    publisher = Publisher(put, "fusion")
    run = Run(bridge, publisher, threading.Event())
    t0 = time.monotonic()
    run.finish(time.monotonic() + 0.1)
    assert time.monotonic() - t0 < 1.0
    assert len(slow) == 1 and sum(publisher.unsent.values()) == 2
    assert "not sent within the stop's grace" in run.summary()


@pytest.mark.parametrize("field", ["max_time_ahead_s", "max_time_behind_s"])
def test_the_tolerances_are_the_cli_defaults(field: str) -> None:
    import argparse

    from service.asterix.command import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args([])
    flag = {"max_time_ahead_s": "max_time_ahead", "max_time_behind_s": "max_time_behind"}[field]
    assert getattr(args, flag) == getattr(BridgeParams(), field)
