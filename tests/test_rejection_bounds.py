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
