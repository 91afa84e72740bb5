"""The ``national`` load scenario: its geometry and data rate are what bench_national.py assumes;
the simulator's ``respawn`` option its soak uses."""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import replace

import numpy as np
import pytest

from service.geo import enu_rotation, geodetic_to_ecef
from tests.scenario_helpers import scenario_messages
from topofusion_lab.scenarios.catalog import get_scenario
from topofusion_lab.scenarios.simulator import _Targets


def test_national_geometry() -> None:
    sc = get_scenario("national")
    assert len(sc.radars) == 12
    assert len({r.radar_id for r in sc.radars}) == 12
    centre = geodetic_to_ecef(sc.center_lat_deg, sc.center_lon_deg, 0.0)
    rot = enu_rotation(sc.center_lat_deg, sc.center_lon_deg)
    enu = np.array(
        [rot.T @ (geodetic_to_ecef(r.latitude_deg, r.longitude_deg, 0.0) - centre) for r in sc.radars]
    )
    ring = np.hypot(enu[:, 0], enu[:, 1])
    np.testing.assert_allclose(ring, 125_000.0, rtol=0.01)  # a ring 250 km across
    bearings = np.sort(np.degrees(np.arctan2(enu[:, 0], enu[:, 1])) % 360.0)
    # evenly spread (the catalog places them with a spherical approximation: within a degree)
    np.testing.assert_allclose(np.diff(bearings), 30.0, atol=1.0)
    assert {r.scan_period_s for r in sc.radars} >= {4.0, 5.0, 6.0}
    for component in ("range_bias_m", "azimuth_bias_deg", "elevation_bias_deg"):
        values = np.array([getattr(r, component) for r in sc.radars])
        assert (values > 0).any() and (values < 0).any(), component
    assert all(0.9 <= r.pd <= 0.95 and 20 <= r.clutter_per_scan <= 50 for r in sc.radars)
    assert sc.targets == 1500


def test_national_plot_rate() -> None:
    duration_s = 12.0  # two scans of the slowest radars
    msgs = scenario_messages("national", duration_s=duration_s, seed=1)
    plots = sum(len(json.loads(p)["plots"]["time_s"]) for k, p in msgs if k.endswith("/plots"))
    assert 1_500 <= plots / duration_s <= 2_100  # about 1 750 plots/s


# sha256 of the messages of short runs, as the simulator wrote them before ``Scenario.respawn``
# existed: each run replaces some targets (two-radar 36 times, coastal 24 times with its AIS
# reports, national 9 times), so the default respawn must keep every scenario's stream as it was.
# (A new numpy that changed its random streams would change these too.)
EDGE_DIGESTS = {
    ("two-radar", 900.0): "c0ae4c93189591930b7013b68640ec63cbe15b8a6ef8f185d3884f91d5cfa4da",
    ("coastal", 3600.0): "655eedbaaf7c9b55285e7b53861b6a4c1dd63bdf06e53bc1b8733ca29ed867c6",
    ("national", 20.0): "961b1e135f84603fcdd5734c5ed04c643817dd145845b4a4d8fb27b9e647767a",
}


@pytest.mark.parametrize(("name", "duration_s"), sorted(EDGE_DIGESTS))
def test_edge_respawn_keeps_the_streams(name: str, duration_s: float) -> None:
    assert get_scenario(name).respawn == "edge"
    digest = hashlib.sha256()
    for key, payload in scenario_messages(name, duration_s=duration_s, seed=1):
        digest.update(key.encode() + b"\0" + payload + b"\n")
    assert digest.hexdigest() == EDGE_DIGESTS[(name, duration_s)]


def _inner_half_counts(respawn: str, hours: float = 2.0) -> np.ndarray:
    """Targets in the central square holding half of the national area, every 10 data minutes
    (20 000 targets: the count's noise is about 0.7 %)."""
    sc = replace(get_scenario("national"), targets=20_000, respawn=respawn)
    targets = _Targets(sc, np.random.default_rng(1))
    inner = sc.half_width_m / np.sqrt(2.0)
    counts = []
    for step in range(int(hours * 3600 / 2.0) + 1):
        if step % 300 == 0:
            counts.append(np.count_nonzero(np.all(np.abs(targets.pos[:, :2]) < inner, axis=1)))
        targets.advance(2.0)
    return np.array(counts) / sc.targets


def test_uniform_respawn_keeps_the_density() -> None:
    """``uniform``: a stationary load (soak tests); ``edge`` gathers the traffic in the middle."""
    uniform = _inner_half_counts("uniform")
    np.testing.assert_allclose(uniform, 0.5, rtol=0.03)  # every 10 min for 2 h
    assert abs(uniform.mean() - 0.5) < 0.005
    edge = _inner_half_counts("edge")
    assert edge[0] == pytest.approx(0.5, rel=0.03)
    assert edge[4] > 1.3 * edge[0]  # 40 min later


def test_uniform_respawn_enters_on_the_boundary_heading_inwards() -> None:
    sc = replace(get_scenario("national"), targets=5_000, respawn="uniform")
    targets = _Targets(sc, np.random.default_rng(2))
    before = targets.count
    for _ in range(120):
        ids = targets.ids.copy()
        targets.advance(2.0)
        new = ids != targets.ids
        pos, vel = targets.pos[new, :2], targets.vel[new, :2]
        w = sc.half_width_m
        side = np.argmax(np.abs(pos), axis=1)  # 0: east or west side, 1: north or south
        rows = np.arange(len(side))
        assert np.all(np.abs(pos) <= w)
        np.testing.assert_allclose(np.abs(pos[rows, side]), w)  # on the boundary ...
        assert np.all(np.sign(pos[rows, side]) * vel[rows, side] < 0)  # ... flying into the area
        speed = np.hypot(vel[:, 0], vel[:, 1])
        assert np.all((speed >= sc.speed_mps[0]) & (speed <= sc.speed_mps[1]))
    assert targets.count - before > 200
    with pytest.raises(ValueError, match="respawn"):
        replace(sc, respawn="inside")  # type: ignore[arg-type]


def test_every_part_the_breakdown_times_exists(monkeypatch: pytest.MonkeyPatch) -> None:
    """``bench_national.py --breakdown`` wraps methods by name: a method renamed or moved must
    fail here, not at the next time somebody needs the breakdown."""
    import importlib
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "bench" / "bench_national.py"
    spec = importlib.util.spec_from_file_location("bench_national_parts", path)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, bench)  # (its dataclasses look themselves up)
    monkeypatch.syspath_prepend(str(path.parent))  # (as run: its folder first, for bench/checkout.py)
    spec.loader.exec_module(bench)
    assert len(bench.BREAKDOWN) >= 5
    for module, cls_name, method in bench.BREAKDOWN:
        cls = getattr(importlib.import_module(module), cls_name)
        assert callable(getattr(cls, method, None)), (module, cls_name, method)
