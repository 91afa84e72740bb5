"""The picture's health figures in data time (service/api/picture.py), and its basemap asset.

The browser tests (tests/test_picture_browser.py) show them on a stream from 2021 at five
times real time; here the rules themselves, on counters made up for the purpose: a radar's lag
behind the newest source, its rates per second of data time, and when the data is a replay.
"""

from __future__ import annotations

import json
from typing import Any, cast

import pytest

from service.api.picture import (
    RATE_WINDOW_S,
    REPLAY_OFFSET_S,
    STATIC_DIR,
    DataRates,
    picture_health,
)
from service.transport.node import ServiceNode

NOW = 1_764_000_000.0  # a wall clock (s)


class _Node:
    """What picture_health reads of a node: its status."""

    def __init__(self) -> None:
        self.radars: list[dict[str, Any]] = []

    def set(self, **radars: tuple[float | None, int]) -> None:
        """Each radar's latest data time and plots so far (a batch per 10 plots)."""
        self.radars = [
            {
                "radar_id": rid,
                "batches": plots // 10,
                "plots": plots,
                "rejected": 0,
                "lost_batches": 0,
                "window_plots": 0,
                "tracks_confirmed": 0,
                "tracks_tentative": 0,
                "last_time_s": last,
            }
            for rid, (last, plots) in radars.items()
        ]

    def status(self) -> dict[str, Any]:
        return {
            "radars": self.radars,
            "correlation": {},
            "pairs_confirmed": 0,
            "pairs_tentative": 0,
            "rejected": {},
            "method": "topology",
        }


def health(node: _Node, rates: DataRates | None, wall_s: float) -> dict[str, Any]:
    return picture_health(cast(ServiceNode, node), rates, wall_s)


def by_radar(h: dict[str, Any], key: str) -> dict[str, Any]:
    return {r["radar_id"]: r[key] for r in h["radars"]}


def test_lag_is_behind_the_newest_source_in_data_time() -> None:
    node = _Node()
    old = 1_614_600_000.0  # 2021: years behind the wall clock
    node.set(A=(old + 100.0, 10), B=(old + 96.5, 10), C=(None, 0))
    h = health(node, None, NOW)
    assert by_radar(h, "lag_s") == {"A": 0.0, "B": 3.5, "C": None}
    assert h["data_time_s"] == old + 100.0 and h["replay"] is True
    # live: data within seconds of the wall clock, no replay
    node.set(A=(NOW - 0.4, 10), B=(NOW - 2.0, 10))
    h = health(node, None, NOW)
    assert by_radar(h, "lag_s") == {"A": 0.0, "B": 1.6} and h["replay"] is False
    # a fast run from a start near the wall clock, minutes ahead of it now
    node.set(A=(NOW + 2 * REPLAY_OFFSET_S, 10))
    assert health(node, None, NOW)["replay"] is True


def test_rates_are_per_second_of_data_time() -> None:
    node, rates = _Node(), DataRates()
    t0 = NOW - 3600.0
    h: dict[str, Any] = {}
    # five data seconds per wall second, A 12 plots per data second, B 3, C silent after 8 s
    for k in range(31):
        t = t0 + 0.5 * k  # data time: ticks of 0.1 s wall
        node.set(A=(t, 12 * round(2 * t) // 2), B=(t - 1.0, 3 * round(t)), C=(min(t, t0 + 8.0), 100))
        h = health(node, rates, NOW + 0.1 * k)
        if k == 0:
            assert by_radar(h, "plots_s") == {"A": None, "B": None, "C": None}
    got = by_radar(h, "plots_s")
    assert got["A"] == pytest.approx(12.0, rel=0.1) and got["B"] == pytest.approx(3.0, rel=0.2)
    assert got["C"] == 0.0  # silent over the window: not its old rate
    assert by_radar(h, "batches_s")["A"] == pytest.approx(1.2, rel=0.1)
    assert h["data_speed"] == pytest.approx(5.0, rel=0.01) and h["replay"] is True
    # the window is a window: a change of rate shows within RATE_WINDOW_S
    t = t0 + 15.0
    base = 12 * round(2 * t) // 2
    for k in range(1, int(2 * RATE_WINDOW_S) + 3):
        node.set(A=(t + 0.5 * k, base + 30 * k))
        h = health(node, rates, NOW + 10.0 + 0.5 * k)
    assert by_radar(h, "plots_s")["A"] == pytest.approx(60.0, rel=0.01)
    assert h["data_speed"] == pytest.approx(1.0, rel=0.01)
    # a new recording from earlier: the rates start again
    node.set(A=(t0, 5))
    assert by_radar(health(node, rates, NOW + 30.0), "plots_s") == {"A": None}


def test_basemap_asset_is_small_and_well_formed() -> None:
    """static/basemap.json (lab/topofusion_lab/basemap.py): a few hundred KB at most, land rings
    and borders of delta-encoded quantised degrees that decode onto the globe, and its notice."""
    path = STATIC_DIR / "basemap.json"
    assert path.stat().st_size < 400_000
    data = json.loads(path.read_text(encoding="utf-8"))
    assert "Natural Earth" in data["source"] and 0 < data["unit"] <= 0.05
    assert len(data["land"]) > 500 and len(data["borders"]) > 100
    points = 0
    for line in data["land"] + data["borders"]:
        assert len(line) % 2 == 0 and len(line) >= 4
        x = y = 0
        for i in range(0, len(line), 2):
            x, y = x + line[i], y + line[i + 1]
            assert -180.0 <= x * data["unit"] <= 180.0 and -90.0 <= y * data["unit"] <= 90.0
        points += len(line) // 2
    assert points > 20_000
    notice = (STATIC_DIR / "NOTICE").read_text(encoding="utf-8")
    assert "Natural Earth" in notice and "public domain" in notice and "world-atlas" in notice
