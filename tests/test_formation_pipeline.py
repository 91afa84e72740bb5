"""The ``formation`` scenario and its whole-pipeline measurement (lab/.../formation_pipeline.py).

Correctness of the scenario and of the scoring only: no accuracy threshold (the correlators
are still being improved; the measurement is what checks them).  The simulator's ``truth_id``
is read here by the evaluation only.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from service.engine import Snapshot
from topofusion_lab.evaluation.formation_pipeline import (
    formation_scenario,
    main,
    measure,
    run_pipeline,
    score_snapshot,
)
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import FormationSpec, _Targets

#: A small, easy formation for a short run through the engine (about 2 s).
SMALL = {"targets": 12, "spacing_m": 4_000.0, "duration_s": 240.0}


def test_formation_starts_together_on_a_jittered_lattice() -> None:
    sc = get_scenario("formation")
    assert sc.formation is not None
    assert len(sc.radars) == 3 and 20 <= sc.targets <= 40
    assert min(r.pd for r in sc.radars) <= 0.8 < max(r.pd for r in sc.radars)
    assert all(0.2 <= abs(r.azimuth_bias_deg) <= 0.5 for r in sc.radars)
    f = sc.formation
    targets = _Targets(sc, np.random.default_rng(3))
    pos, vel = targets.pos, targets.vel
    h = math.radians(f.heading_deg)
    np.testing.assert_allclose(
        vel, np.tile([f.speed_mps * math.sin(h), f.speed_mps * math.cos(h), 0.0], (sc.targets, 1))
    )
    assert np.all((pos[:, 2] >= sc.altitude_m[0]) & (pos[:, 2] <= sc.altitude_m[1]))
    # every aircraft within jitter of its lattice point: the nearest other one is 0.5-1.5 spacings away
    d = np.hypot(*(pos[:, None, :2] - pos[None, :, :2]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    nearest = d.min(axis=1)
    assert np.all(nearest >= (1 - 2 * f.jitter) * f.spacing_m - 1e-6)
    assert np.all(nearest <= math.hypot(1, 2 * f.jitter) * f.spacing_m + 1e-6)
    centre = pos[:, :2].mean(axis=0)
    assert np.hypot(*(centre - [f.start_east_m, f.start_north_m])) < f.spacing_m
    assert list(targets.ids) == [f"T{i}" for i in range(1, sc.targets + 1)]
    # the whole flight stays in the area, so no aircraft is replaced
    targets.advance(sc.duration_s or 0.0)
    assert targets.count == sc.targets


def test_formation_knobs() -> None:
    sc = formation_scenario(targets=7, spacing_m=900.0, duration_s=60.0)
    assert (sc.targets, sc.duration_s) == (7, 60.0)
    assert sc.formation is not None and sc.formation.spacing_m == 900.0
    assert formation_scenario() == get_scenario("formation")
    with pytest.raises(ValueError, match="spacing"):
        replace(sc.formation, jitter=0.5)
    with pytest.raises(ValueError, match="spacing"):
        FormationSpec(spacing_m=0.0)


def _recount(snap: Snapshot) -> dict[str, dict[str, int]]:
    """The scores again, from the contract's JSON as the service serves it (``TrackBatch``,
    ``PairSet``), not from the snapshot's columns."""
    truth = {
        (b["radar_id"], t["track_id"]): t["truth_id"] for b in snap.track_batches("all") for t in b["tracks"]
    }
    aircraft = {
        b["radar_id"]: {t["truth_id"] for t in b["tracks"] if t["truth_id"] is not None}
        for b in snap.track_batches("confirmed")
    }
    out = {}
    for ps in snap.pair_sets(status="confirmed"):
        a, b = ps["radar_a"], ps["radar_b"]
        common = aircraft[a] & aircraft[b]
        kept = [p for p in ps["pairs"] if (a, p["track_a"]) in truth and (b, p["track_b"]) in truth]
        judged = [(truth[(a, p["track_a"])], truth[(b, p["track_b"])]) for p in kept]
        right = [x for x, y in judged if x is not None and x == y]
        out[f"{a}-{b}"] = {
            "common": len(common),
            "confirmed": len(ps["pairs"]),
            "correct": len(right),
            "found": len(set(right) & common),
            "false": len(judged) - len(right),
            "gone": len(ps["pairs"]) - len(kept),
        }
    return out


def test_scores_through_the_engine() -> None:
    sc = formation_scenario(**SMALL)
    runs = list(run_pipeline(sc, seed=1, at_s=[80.0, 160.0]))
    assert [t for t, _, _ in runs] == [80.0, 160.0, SMALL["duration_s"]]
    engine = runs[-1][2]
    assert not engine.rejected
    for _, snap, _ in runs:
        s = score_snapshot(snap)
        for key, p in s["pairs"].items():
            assert p["correct"] + p["false"] + p["gone"] == p["confirmed"], key
            assert p["found"] <= min(p["common"], p["correct"]), key
        assert s["pairs"] == _recount(snap)
        tot = s["total"]
        assert tot == {f: sum(p[f] for p in s["pairs"].values()) for f in tot}
        # the score bins hold every judged confirmed pair once, the right ones among them
        assert sum(s["scores"]["score_n"]) == tot["confirmed"] - tot["gone"]
        assert sum(s["scores"]["score_right"]) == tot["correct"]
        assert 0.0 <= s["scores"]["brier_sum"] <= tot["confirmed"] - tot["gone"]
    final = score_snapshot(runs[-1][1])
    assert set(final["pairs"]) == {"A-B", "A-C", "B-C"}
    assert set(final["radars"]) == {"A", "B", "C"}
    for rid, r in final["radars"].items():
        assert 0 < r["aircraft"] <= SMALL["targets"], rid
        assert r["aircraft"] + r["duplicates"] + r["clutter"] == r["confirmed_tracks"], rid
    # the common pairs are the aircraft both radars hold a confirmed track of
    tracked = {rid: set(t for t in _confirmed_truths(runs[-1][1], rid)) for rid in "ABC"}
    for key, p in final["pairs"].items():
        a, b = key.split("-")
        assert p["common"] == len(tracked[a] & tracked[b]) > 0, key
    assert final["total"]["confirmed"] > 0 and final["total"]["correct"] > 0


def _confirmed_truths(snap: Snapshot, radar_id: str) -> list[str]:
    _, table = snap.tracks[radar_id]
    return [str(t) for t, c in zip(table.truth_id, table.confirmed, strict=True) if c and t is not None]


def test_measure_and_report(capsys: pytest.CaptureFixture[str]) -> None:
    lines: list[str] = []
    got = measure(2, "nearest", checkpoints=2, progress=lines.append, **SMALL)
    assert (got["seed"], got["method"], got["targets"], got["spacing_m"]) == (2, "nearest", 12, 4_000.0)
    assert [c["t_s"] for c in got["checkpoints"]] == [80.0, 160.0, 240.0]
    assert got["final"] == got["checkpoints"][-1] and len(lines) == 3
    f = got["final"]
    assert f["correct_pct"] == pytest.approx(100 * f["total"]["found"] / f["total"]["common"])
    judged = f["total"]["confirmed"] - f["total"]["gone"]
    assert f["false_pct"] == pytest.approx(100 * f["total"]["false"] / judged)
    assert set(got["biases"]) == {"A", "B", "C"}

    assert (
        main(
            [
                "--seeds",
                "1",
                "--method",
                "nearest",
                "--targets",
                "6",
                "--duration",
                "120",
                "--checkpoints",
                "1",
            ]
        )
        == 0
    )
    out = capsys.readouterr()
    assert "nearest: formation of 6 aircraft, 2000 m lattice, 120 s" in out.out
    assert "  mean " in out.out and "seed 1 nearest t= 120s" in out.err
