"""The ADS-B reference study (lab/topofusion_lab/evaluation/adsb.py): its scoring on a
hand-built case, its stream against the simulator's wire messages, and a tiny end-to-end run."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from service.geo import Site
from service.tracking.base import TrackTable
from topofusion_lab.evaluation import adsb
from topofusion_lab.scenarios.simulator import identity_of, wire_messages

SITE = Site("A", 31.2, 118.5, 30.0)


def addr(name: str) -> str:
    return identity_of(name)[1]


def table(rows: list[tuple[str, str | None, bool, str | None]]) -> TrackTable:
    """Tracks ``(track_id, truth_id, confirmed, mode_s)`` (positions play no part in scoring)."""
    n = len(rows)
    return TrackTable(
        track_id=np.array([r[0] for r in rows], dtype=str),
        confirmed=np.array([r[2] for r in rows], dtype=bool),
        time_s=np.zeros(n),
        position_ecef_m=SITE.enu_to_ecef(np.zeros((n, 3))),
        velocity_ecef_mps=np.zeros((n, 3)),
        covariance=np.tile(np.eye(6), (n, 1, 1)),
        plots=np.full(n, 5, dtype=np.int64),
        truth_id=np.array([r[1] for r in rows], dtype=object),
        mode_s=np.array([r[3] for r in rows], dtype=object),
    )


def heard(first: float, last: float, lat: float = 31.0, lon: float = 119.0) -> adsb.Heard:
    return adsb.Heard(first, last, lat, lon)


def test_score_on_a_known_case() -> None:
    t = 1000.0
    tracks = table(
        [
            ("A-1", "T1", True, addr("T1")),  # right pair, settled
            ("A-2", "T2", True, addr("T6")),  # paired with T6's address: its track swapped to T6
            ("A-3", None, True, None),  # clutter, paired with T7's address
            ("A-4", "T4", False, addr("T4")),  # tentative: not common
            ("A-5", "T5", True, None),  # unequipped, unpaired: not common
            ("A-6", "T6", True, addr("T6")),  # equipped, settled, its address taken by A-2
            ("A-8", "T8", True, addr("T8")),  # right pair, but confirmed only 30 s ago
            ("A-10", "T10", True, addr("T10")),  # equipped, settled, in no pair
        ]
    )
    since = {"A-1": 100.0, "A-2": 100.0, "A-3": 100.0, "A-5": 100.0, "A-6": 100.0, "A-8": 970.0, "A-9": 90.0}
    # A-10 is missing from ``since``: taken as confirmed now (not settled)
    ears = {
        addr("T1"): heard(50.0, 999.0),
        addr("T2"): heard(50.0, 999.0, lat=31.0),
        addr("T4"): heard(50.0, 999.0),
        addr("T6"): heard(50.0, 999.0, lat=31.09),  # 10 km north of T2
        addr("T7"): heard(50.0, 999.0),
        addr("T8"): heard(50.0, 999.0),
        addr("T9"): heard(50.0, 980.0),
        addr("T10"): heard(50.0, 999.0),
    }
    memory = {"A-9": ("T9", addr("T9"))}  # deleted since the pair set's update: a right pair
    pairs = [
        ("A-1", addr("T1")),
        ("A-2", addr("T6")),
        ("A-3", addr("T7")),
        ("A-8", addr("T8")),
        ("A-9", addr("T9")),
    ]
    s = adsb.score("A", tracks, pairs, ears, since, t, memory)
    c = s.counts
    assert (c.confirmed, c.correct, c.false) == (5, 3, 2)
    # common: T1, T2, T6, T8, T10 (T4 tentative, T5 unequipped, T9's track gone); found: T1, T8
    assert (c.common, c.found) == (5, 2)
    # settled (>= 60 s): T1, T2, T6 (T8 confirmed 30 s ago, T10 just now)
    assert (c.settled_common, c.settled_found) == (3, 1)
    # T2 and T6 are missed, both through the false pair A-2 / T6's address
    assert c.settled_unpaired == 0
    # settled pairs, A-9 (A-8 is 30 s old)
    assert (c.settled_confirmed, c.settled_false) == (4, 2)
    by_track = {w.track_a: w for w in s.wrong}
    assert set(by_track) == {"A-2", "A-3"}
    w2 = by_track["A-2"]
    assert (w2.cause, w2.truth_id, w2.code_matches, w2.address_tracked, w2.gone) == (
        "other",
        "T2",
        True,
        True,
        False,
    )
    assert w2.distance_km == pytest.approx(10.0, rel=0.01)
    w3 = by_track["A-3"]
    assert (w3.cause, w3.truth_id, w3.address_tracked) == ("clutter", None, False)
    assert sorted(ok for _, ok in s.pair_ages) == [False, False, True, True, True]
    assert sorted(s.aircraft_ages) == [
        (0.0, False),
        (30.0, True),
        (900.0, False),
        (900.0, False),
        (900.0, True),
    ]


def test_a_missed_aircraft_in_no_pair_counts_as_unpaired() -> None:
    tracks = table([("A-1", "T1", True, addr("T1")), ("A-2", "T2", True, addr("T2"))])
    ears = {addr("T1"): heard(0.0, 500.0), addr("T2"): heard(0.0, 500.0)}
    s = adsb.score("A", tracks, [("A-1", addr("T1"))], ears, {"A-1": 0.0, "A-2": 0.0}, 500.0)
    assert (s.counts.settled_common, s.counts.settled_found, s.counts.settled_unpaired) == (2, 1, 1)
    # an aircraft last heard more than RECENT_S ago is not common
    ears[addr("T2")] = heard(0.0, 500.0 - adsb.RECENT_S - 1.0)
    s = adsb.score("A", tracks, [("A-1", addr("T1"))], ears, {"A-1": 0.0, "A-2": 0.0}, 500.0)
    assert (s.counts.common, s.counts.found) == (1, 1)


def test_adsb_pairs_take_the_radar_side_whichever_way_the_set_is_sorted() -> None:
    sets = [
        {
            "radar_a": "A",
            "radar_b": "adsb",
            "pairs": [
                {"track_a": "A-1", "track_b": "aaaaaa", "status": "confirmed"},
                {"track_a": "A-2", "track_b": "bbbbbb", "status": "tentative"},
            ],
        },
        {
            "radar_a": "A",
            "radar_b": "B",
            "pairs": [{"track_a": "A-1", "track_b": "B-1", "status": "confirmed"}],
        },
        {
            "radar_a": "ADSB",
            "radar_b": "B",
            "pairs": [{"track_a": "cccccc", "track_b": "B-3", "status": "confirmed"}],
        },
    ]
    assert adsb.adsb_pairs(sets, "A", "adsb") == [("A-1", "aaaaaa")]
    assert adsb.adsb_pairs(sets, "B", "ADSB") == [("B-3", "cccccc")]


def test_an_address_counts_from_its_first_report_with_a_height() -> None:
    ears: dict[str, adsb.Heard] = {}
    body = {
        "reports": {
            "time_s": [1.0, 1.0, 2.0, 3.0],
            "icao24": ["aaaaaa", "bbbbbb", "aaaaaa", "aaaaaa"],
            "latitude_deg": [1.0, 2.0, 1.1, 1.2],
            "longitude_deg": [3.0, 4.0, 3.1, 3.2],
            "altitude_m": [None, 100.0, 200.0, None],
        }
    }
    adsb.hear(ears, body)
    assert ears["aaaaaa"] == adsb.Heard(2.0, 3.0, 1.2, 3.2)
    assert ears["bbbbbb"] == adsb.Heard(1.0, 1.0, 2.0, 4.0)


def test_the_study_streams_the_simulator_s_wire_messages() -> None:
    job = adsb.Job(0, adsb.CONDITIONS[0], (0, 0, 0), 12.0)
    sc, seed = adsb.scenario_of(job)
    got = [(k, p) for _, k, p, _ in adsb.stream(sc, seed)]
    assert got == list(wire_messages(sc, seed))
    assert any(k == "fusion/adsb/adsb/reports" for k, _ in got)
    plots = next(json.loads(p)["plots"] for k, p in got if k.endswith("/plots"))
    assert plots["mode_s"] and all(
        m == addr(t) for m, t in zip(plots["mode_s"], plots["truth_id"], strict=True)
    )


def test_biases_are_drawn_per_radar_in_the_study_s_ranges() -> None:
    for r in range(20):
        job = adsb.Job(11, adsb.CONDITIONS[-1], (3, 11, r), 10.0)
        sc, _ = adsb.scenario_of(job)
        assert len(sc.radars) == 3
        for radar in sc.radars:
            assert 100.0 <= abs(radar.range_bias_m) <= 600.0
            assert 0.1 <= abs(radar.azimuth_bias_deg) <= 0.5
            assert abs(radar.elevation_bias_deg) <= 0.15
    a, _ = adsb.scenario_of(adsb.Job(0, adsb.CONDITIONS[0], (0, 0, 0), 10.0))
    b, _ = adsb.scenario_of(adsb.Job(0, adsb.CONDITIONS[0], (0, 0, 1), 10.0))
    assert a.radars[0].range_bias_m != b.radars[0].range_bias_m


def test_worst_of_a_run_without_an_estimate_is_missing() -> None:
    assert math.isnan(adsb._worst([0.01, math.nan], low=False))
    assert adsb._worst([0.01, 0.05], low=False) == 0.05
    assert adsb._worst([0.97, 0.99], low=True) == 0.97


@pytest.mark.slow
def test_a_tiny_study_end_to_end(tmp_path: Path) -> None:
    lone = replace(adsb.CONDITIONS[0], label="lone, 30 aircraft", targets=30)
    network = replace(adsb.CONDITIONS[-2], label="A, B, 30 aircraft", targets=30)
    messages: list[str] = []
    md = adsb.run(
        tmp_path,
        runs=1,
        seed=0,
        progress=messages.append,
        conditions=(lone, network),
        duration_s=150.0,
        workers=1,
    )
    assert (tmp_path / "adsb_vs_age.png").stat().st_size > 0
    assert (tmp_path / "adsb_bias.png").stat().st_size > 0
    assert md.startswith("## ADS-B as a bias-free reference")
    for heading in ("### Lone radar", "### Network", "### Goals"):
        assert heading in md
    assert "| lone, 30 aircraft | 1 x 1 |" in md
    assert "| A, B, 30 aircraft | 1 x 2 |" in md
    assert "**Pairs, reading (1)**" in md and "**Lone-radar biases within 10 %**" in md
    assert len(messages) == 3  # the plan and one line per run
    # a run itself, of the study's length (its goal is stated for those: over 150 s the
    # estimate of this seed's range bias is 9-11 % off, by the tracker's noise): a clean
    # stream, right pairs, absolute biases within 10 %
    res = adsb.run_one(adsb.Job(0, lone, (0, 0, 0), adsb.DURATION_S))
    assert res.errors == 0
    (radar,) = res.radars
    c = radar.counts
    assert c.confirmed >= 10 and c.correct == c.confirmed
    assert c.settled_found == c.settled_common > 0
    assert radar.estimate is not None
    assert radar.relative("range_bias_m") <= 0.1 and radar.relative("azimuth_bias_deg") <= 0.1
    # the identity figure needs no truth: nearly every pair's radar track carries its address
    assert res.identity_pairs >= c.confirmed - 1 and res.identity_equal >= 0.9 * res.identity_pairs
    assert radar.checkpoints and radar.updates
