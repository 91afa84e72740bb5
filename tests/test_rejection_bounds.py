"""What a hostile sender can make the service write about its rejections is bounded: a
``Rejection``'s ``detail`` (the contract's "at most a few hundred characters") and the log's
lines when every message comes under a new made-up source id."""

from __future__ import annotations

import json
import logging

import pytest

import service.pipeline.feed as feed
from service.engine import Engine, EngineConfig
from service.pipeline.feed import REJECTION_LOG_LINES, RejectionLog
from service.wire.outputs import MAX_DETAIL_CHARS


def test_a_rejection_detail_quoting_a_10_000_character_id_is_cut() -> None:
    engine = Engine(EngineConfig())
    rid = "r" * 10_000
    (o,) = engine.ingest(f"fusion/radar/{rid}/plots", b"{}", receive_time_s=0.0)
    body = json.loads(o.payload)
    assert body["reason"] == "schema"
    assert len(body["detail"]) <= MAX_DETAIL_CHARS and body["detail"].endswith("\u2026")
    (o,) = engine.ingest("fusion/radar/A/plots", b"{", receive_time_s=0.0)  # a short one: whole
    assert not json.loads(o.payload)["detail"].endswith("\u2026")
    engine.close()


def test_made_up_source_ids_do_not_flood_the_log(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """5 000 refusals, each of another source: at most ``REJECTION_LOG_LINES`` lines an interval,
    then one line counting the rest when the next interval starts (the log's own clock is
    the wall clock: set by hand here)."""
    now = [0.0]
    monkeypatch.setattr(feed.time, "monotonic", lambda: now[0])
    log = RejectionLog(interval_s=10.0)
    caplog.set_level(logging.WARNING, logger="service.pipeline.feed")
    for k in range(5_000):
        log.refused(f"fake-{k}", "unknown_radar", f"fusion/radar/fake-{k}/plots", "no site")
    assert len(caplog.records) == REJECTION_LOG_LINES
    now[0] = 11.0
    log.refused("fake-x", "unknown_radar", "fusion/radar/fake-x/plots", "no site")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == REJECTION_LOG_LINES + 2
    assert f"rejected {5_000 - REJECTION_LOG_LINES} more inputs" in lines[-2]
    assert "fake-x" in lines[-1]


def test_a_truth_id_longer_than_64_characters_is_refused() -> None:
    """``plots.truth_id`` is a simulator's aircraft name: a batch carrying 300 000-character
    ones held hundreds of MB in the plot window; past 64 characters it is ``schema``."""
    engine = Engine(EngineConfig())
    site = {"radar_id": "A", "latitude_deg": 31.0, "longitude_deg": 119.0}
    engine.ingest("fusion/radar/A/site", json.dumps(site).encode())

    def batch(seq: int, name: str) -> bytes:
        plots = {"time_s": [99.5], "range_m": [5e4], "azimuth_deg": [10.0], "truth_id": [name]}
        return json.dumps({"radar_id": "A", "seq": seq, "time_s": 100.0 + seq, "plots": plots}).encode()

    (o,) = engine.ingest("fusion/radar/A/plots", batch(1, "x" * 65), receive_time_s=0.0)
    assert json.loads(o.payload)["reason"] == "schema"
    assert not any(
        o.key.endswith("/errors") for o in engine.ingest("fusion/radar/A/plots", batch(2, "x" * 64))
    )
    engine.close()
