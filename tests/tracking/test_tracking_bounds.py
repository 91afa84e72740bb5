"""Bounded memory and work per update: pair search, window cap, all-or-nothing updates, and
contract-size batches (100 000 plots) through a whole tracker."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

import service.tracking.manager as manager_module
from service.evaluation.truth import TruthLabelledTracker
from service.tracking import make_tracker
from service.tracking.base import PlotColumns
from service.tracking.initiators import local_clusters
from service.tracking.logic import _pairs, logic_initiate
from service.tracking.measurement import Measurements, plots_to_measurements
from service.tracking.pairs import time_gated_pairs
from service.tracking.params import BoundParams, LogicParams, TrackerParams
from service.tracking.window import PlotWindow
from topofusion_lab.evaluation.initiation_monostatic import SITE, MonostaticScenario, simulate

ROOT = Path(__file__).resolve().parents[2]
#: Bounds that force the blockwise search on any input of more than one plot.
TINY = BoundParams(block=1)


def _meas(rng: np.random.Generator, n: int, extent_m: float, times: np.ndarray) -> Measurements:
    xyz = np.stack(
        [rng.uniform(-extent_m, extent_m, n), rng.uniform(-extent_m, extent_m, n), rng.uniform(0, 1e4, n)],
        axis=1,
    )
    sig = rng.uniform(50.0, 400.0, n)
    return Measurements(rng.choice(times, n), xyz, sig[:, None, None] ** 2 * np.eye(3))


def _all_pairs_reference(meas: Measurements, p: LogicParams, scan_period_s: float) -> set[tuple[int, int]]:
    """The all-pairs form used before the bounds: one ``query_pairs`` over the whole window,
    pairs oriented earlier -> later (ties: lower index first), then the time and speed gates."""
    dt_min, dt_max = p.min_dt_scans * scan_period_s, p.max_dt_scans * scan_period_s
    sig = np.sqrt(np.trace(meas.covariance, axis1=1, axis2=2))
    radius = p.max_speed_mps * dt_max + 6.0 * float(sig.max())
    pr = cKDTree(meas.enu_m).query_pairs(radius, output_type="ndarray")
    out = set()
    for a, b in pr.tolist():
        i, j = (b, a) if meas.time_s[a] > meas.time_s[b] else (a, b)
        dt = meas.time_s[j] - meas.time_s[i]
        dist = float(np.linalg.norm(meas.enu_m[j] - meas.enu_m[i]))
        slack = 3.0 * float(np.hypot(sig[i], sig[j]))
        if dt_min <= dt <= dt_max and p.min_speed_mps * dt - slack <= dist <= p.max_speed_mps * dt + slack:
            out.add((i, j))
    return out


@pytest.mark.parametrize("min_dt_scans", [0.5, 0.0])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_blockwise_pairs_equal_the_all_pairs_form(seed: int, min_dt_scans: float) -> None:
    rng = np.random.default_rng(seed)
    # Four looks with ties (equal times), dense enough for many pairs across cell borders.
    meas = _meas(rng, 400, 40_000.0, np.array([0.0, 3.9, 4.0, 8.0, 8.0, 12.5]))
    p = LogicParams(min_dt_scans=min_dt_scans)
    want = _all_pairs_reference(meas, p, 4.0)
    assert len(want) > 500
    for bounds in (BoundParams(), TINY, BoundParams(block=97)):
        i, j = _pairs(meas, p, 4.0, bounds)
        got = list(zip(i.tolist(), j.tolist(), strict=True))
        assert set(got) == want and len(got) == len(want)
    # The blockwise form gives them in (time, index) order of the first, then second plot.
    i, j = _pairs(meas, p, 4.0, TINY)
    key = np.lexsort((j, meas.time_s[j], i, meas.time_s[i]))
    np.testing.assert_array_equal(key, np.arange(i.shape[0]))


def test_blockwise_logic_and_local_clusters_give_the_same_candidates() -> None:
    rng = np.random.default_rng(3)
    scn = MonostaticScenario(n_targets=60, clutter_per_scan=300, scans=3, sectors=1)
    batches, _, _ = simulate(scn, rng)
    plots = PlotColumns.concat([b for b, _ in batches])
    meas = plots_to_measurements(SITE, plots, TrackerParams().measurement)
    full = logic_initiate(meas, LogicParams(), 4.0)
    tiny = logic_initiate(meas, LogicParams(), 4.0, TINY)
    assert full.count >= 40
    assert sorted(map(tuple, full.to_lists())) == sorted(map(tuple, tiny.to_lists()))
    a = local_clusters(meas, 700.0, 3)
    b = local_clusters(meas, 700.0, 3, TINY)
    assert sorted(map(tuple, a)) == sorted(map(tuple, b)) and len(a) >= 10


def test_pair_search_holds_its_work_and_memory_bounds() -> None:
    """``keep`` sees every candidate: never more than ``block`` plus one plot's at once, and
    at most ``max_pairs`` in all; the least crowded cells are searched first."""
    rng = np.random.default_rng(4)
    n, n_sparse = 4000, 1500
    crowd = rng.uniform(0, 2_000.0, (n - n_sparse, 2))
    xy = np.concatenate([crowd, rng.uniform(0, 200_000.0, (n_sparse, 2))])
    t = rng.uniform(0.0, 10.0, n)
    seen: list[int] = []

    def keep(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        seen.append(i.shape[0])
        return np.linalg.norm(xy[j] - xy[i], axis=1) <= 5_000.0

    per_plot_max = n  # one plot's candidates are at most the other plots
    i, j = time_gated_pairs(t, xy, 5_000.0, 0.0, 10.0, keep, max_pairs=200_000, block=500)
    assert sum(seen) <= 200_000 and max(seen) <= 500 + per_plot_max
    assert len(seen) >= 5  # it did run in blocks
    # The crowded cell does not fit; the sparse plots away from it form all their pairs.
    sparse = np.flatnonzero(np.max(xy, axis=1) > 10_000.0)
    full = cKDTree(xy[sparse]).query_pairs(5_000.0, output_type="ndarray")
    got = {(int(a), int(b)) for a, b in zip(i.tolist(), j.tolist(), strict=True)}
    ends = [(int(sparse[a]), int(sparse[b])) for a, b in full.tolist()]
    want = {tuple(sorted(e, key=lambda q: (t[q], q))) for e in ends}
    assert want and want <= got
    # Deterministic.
    again = time_gated_pairs(t, xy, 5_000.0, 0.0, 10.0, keep, max_pairs=200_000, block=500)
    np.testing.assert_array_equal(again[0], i)
    np.testing.assert_array_equal(again[1], j)


def test_association_in_chunks_and_blocks_gives_the_same_tracks() -> None:
    scn = MonostaticScenario(n_targets=80, clutter_per_scan=200, scans=6)
    batches, _, _ = simulate(scn, np.random.default_rng(8))
    one = make_tracker(SITE)
    many = make_tracker(SITE, params=TrackerParams(bounds=BoundParams(gate_block=7)))
    for plots, tb in batches:
        one.update(plots, tb)
        many.update(plots, tb)
        a, b = one.tracks(), many.tracks()
        np.testing.assert_array_equal(a.track_id, b.track_id)
        np.testing.assert_array_equal(a.position_ecef_m, b.position_ecef_m)
        np.testing.assert_array_equal(a.covariance, b.covariance)
        np.testing.assert_array_equal(one._window.plots.time_s, many._window.plots.time_s)
    assert one.tracks().confirmed.sum() >= 60


def _plots(times: list[float]) -> PlotColumns:
    n = len(times)
    return PlotColumns(
        np.array(times),
        np.arange(n, dtype=float),
        np.zeros(n),
        np.zeros(n),
        np.full(n, np.nan),
        np.array([f"p{k}" for k in range(n)], dtype=object),
    )


def test_window_evicts_the_oldest_plots_beyond_its_cap() -> None:
    w = PlotWindow(100.0, max_plots=4)
    w.extend(_plots([5.0, 1.0, 3.0]), 5.0)
    assert len(w) == 3 and w.evicted == 0
    b = _plots([2.0, 1.0, 6.0])
    b = PlotColumns(b.time_s, b.range_m + 10, b.azimuth_deg, b.elevation_deg, b.altitude_m, b.truth_id)
    w.extend(b, 6.0)
    # Oldest first (1.0 from the first batch before 1.0 from the second: arrival order).
    assert len(w) == 4 and w.evicted == 2
    assert sorted(w.plots.time_s.tolist()) == [2.0, 3.0, 5.0, 6.0]
    w.extend(_plots([9.0, 9.0, 9.0, 9.0, 9.0]), 9.0)
    assert len(w) == 4 and w.evicted == 7 and w.plots.time_s.tolist() == [9.0] * 4
    assert w.plots.range_m.tolist() == [1.0, 2.0, 3.0, 4.0]  # equal times: the first arrived go
    unbounded = PlotWindow(100.0)
    unbounded.extend(_plots([1.0] * 10), 1.0)
    assert len(unbounded) == 10 and unbounded.evicted == 0


def test_tracker_counts_window_evictions() -> None:
    scn = MonostaticScenario(n_targets=20, clutter_per_scan=400, scans=3)
    batches, _, _ = simulate(scn, np.random.default_rng(5))
    params = TrackerParams(bounds=BoundParams(max_window_plots=150))
    tr = TruthLabelledTracker(make_tracker(SITE, params=params))
    for plots, tb in batches:
        tr.update(plots, tb)
        assert tr.window_plots <= 150
    assert tr.window_evicted > 0 and tr.window_evicted == tr.inner.window_evicted
    assert make_tracker(SITE).window_evicted == 0


def _state(tr: manager_module.TrackManager) -> tuple[object, ...]:
    tab = tr.tracks()
    w = tr._window
    return (
        tab.track_id.tolist(),
        tab.confirmed.tolist(),
        tab.time_s.tobytes(),
        tab.position_ecef_m.tobytes(),
        tab.velocity_ecef_mps.tobytes(),
        tab.covariance.tobytes(),
        tab.plots.tolist(),
        w.plots.time_s.tobytes(),
        w.plots.range_m.tobytes(),
        w.newest_time_s,
        w.evicted,
        tr._next_uid,
        tr.last_time_s,
        [(u.tolist(), p.time_s.tobytes()) for u, p in tr.joined],
    )


@pytest.mark.parametrize("step", ["assign", "initiator", "fit_groups"])
def test_a_failing_batch_changes_nothing(step: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """An exception part-way through an update (after association, life cycle or window
    changes were computed) leaves the tracker exactly as before, and the run goes on as if
    that batch had never come."""
    scn = MonostaticScenario(n_targets=30, clutter_per_scan=60, scans=6)
    batches, _, _ = simulate(scn, np.random.default_rng(6))
    params = TrackerParams(bounds=BoundParams(max_window_plots=200))  # evictions happen too
    tr = make_tracker(SITE, params=params)
    twin = make_tracker(SITE, params=params)
    bad = len(batches) // 2
    for plots, tb in batches[:bad]:
        tr.update(plots, tb)
        twin.update(plots, tb)
    assert len(tr.tracks()) > 0 and tr.window_evicted > 0

    def boom(*args: object, **kwargs: object) -> None:
        raise RuntimeError("injected")

    with monkeypatch.context() as m:
        if step == "initiator":
            m.setattr(tr, "_initiate", boom)
        else:
            m.setattr(manager_module, step, boom)
        for k in range(bad, len(batches)):  # the step runs only when it has something to do
            before = _state(tr)
            try:
                tr.update(*batches[k])
            except RuntimeError as exc:
                assert str(exc) == "injected"
                break
            twin.update(*batches[k])
        else:
            pytest.fail(f"{step} never ran")
    assert _state(tr) == before
    for plots, tb in batches[k + 1 :]:
        tr.update(plots, tb)
        twin.update(plots, tb)
        assert _state(tr) == _state(twin)
    assert len(tr.tracks()) > 0


#: Runs contract-size batches through one tracker in a fresh interpreter (so that only this
#: work counts in its peak RSS) and prints the figures as JSON.
_BIG = r"""
import json, resource, sys, time
import numpy as np
from topofusion_lab.evaluation.initiation_monostatic import SITE, MonostaticScenario, simulate
from service.tracking import make_tracker
from service.tracking.base import PlotColumns
from service.tracking.params import BoundParams, TrackerParams

cfg = {"targets": 1000, "range_m": [30_000.0, 120_000.0], "filler_from": 0, **json.loads(sys.argv[1])}
# Safety net: an unbounded regression fails here with MemoryError instead of taking the box.
resource.setrlimit(resource.RLIMIT_AS, (cfg["address_limit"], cfg["address_limit"]))
rng = np.random.default_rng(cfg["seed"])
t0, scan = 1_763_769_600.0, 4.0
params = TrackerParams(bounds=BoundParams(max_window_plots=cfg["max_window_plots"]))
tr = make_tracker(SITE, params=params)
lo, hi = cfg["range_m"]
scn = MonostaticScenario(n_targets=cfg["targets"], clutter_per_scan=200, scans=cfg["batches"], sectors=1,
                         range_min_m=lo, range_max_m=hi, t0_s=t0)
real, _, _ = simulate(scn, rng)
total, times = 0, []
for b, (rp, tb) in enumerate(real):
    k = cfg["plots"] - len(rp) if b >= cfg["filler_from"] else 0
    if cfg["dense"]:  # every plot in a 10 km x 10 deg patch
        r, az = rng.uniform(50_000.0, 60_000.0, k), rng.uniform(40.0, 50.0, k)
    else:  # uniform over the coverage
        r, az = np.sqrt(rng.uniform(1_000.0**2, 160_000.0**2, k)), rng.uniform(0.0, 360.0, k)
    el = rng.uniform(0.0, 10.0, k)
    clutter = PlotColumns(t0 + b * scan + az / 360.0 * scan, r, az, el, np.full(k, np.nan),
                          np.full(k, None, dtype=object))
    plots = PlotColumns.concat([rp, clutter])
    total += len(plots)
    s = time.perf_counter()
    tr.update(plots, tb)
    times.append(time.perf_counter() - s)
# This process's own peak (VmHWM): Linux's ru_maxrss carries the forking parent's peak over
# the exec, and the parent is the test run, whatever it holds by then.
with open("/proc/self/status") as status:
    peak_kb = next(int(line.split()[1]) for line in status if line.startswith("VmHWM:"))
print(json.dumps({
    "rss_mb": peak_kb / 1024.0,
    "window": tr.window_plots, "evicted": tr.window_evicted, "plots": total,
    "tracks": len(tr.tracks()), "seconds": times,
}))
"""

#: "Well under 3 GB": the unbounded search peaked at 2.2 GB on one such batch and passed
#: 8 GB on the second.
RSS_LIMIT_MB = 1024.0


def _run_big(**cfg: object) -> dict[str, object]:
    conf = {
        "seed": 1,
        "batches": 1,
        "plots": 100_000,
        "dense": False,
        "max_window_plots": BoundParams().max_window_plots,
        "address_limit": 6 << 30,
        **cfg,
    }
    proc = subprocess.run(
        [sys.executable, "-c", _BIG, json.dumps(conf)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out: dict[str, object] = json.loads(proc.stdout.strip().splitlines()[-1])
    return out


def test_one_contract_size_batch_stays_bounded() -> None:
    cap = BoundParams().max_window_plots
    r = _run_big()
    assert r["rss_mb"] < RSS_LIMIT_MB, r  # type: ignore[operator]
    assert r["window"] == cap and r["evicted"] == 100_000 - cap, r


@pytest.mark.parametrize("dense", [False, True])
def test_contract_size_batches_in_a_row_stay_bounded(dense: bool) -> None:
    cap = BoundParams().max_window_plots
    r = _run_big(batches=3, dense=dense)
    assert r["rss_mb"] < RSS_LIMIT_MB, r  # type: ignore[operator]
    assert r["window"] <= cap and r["evicted"] >= r["plots"] - cap - 3_000, r  # type: ignore[operator]


@pytest.mark.parametrize("dense", [False, True])
def test_a_window_of_several_full_batches_hits_the_pair_bounds(dense: bool) -> None:
    """With a window cap above the batch size the initiator gets three scans of 100 000 plots:
    its pair and triple bounds, not the window, keep it in memory and time."""
    r = _run_big(batches=3, dense=dense, max_window_plots=400_000)
    assert r["rss_mb"] < RSS_LIMIT_MB, r  # type: ignore[operator]
    assert r["evicted"] == 0 and r["window"] > 250_000, r  # type: ignore[operator]
    assert max(r["seconds"]) < 10.0, r  # type: ignore[arg-type]


@pytest.mark.slow
def test_a_dense_batch_over_many_tracks_keeps_association_bounded() -> None:
    """2 000 targets in a 10 km wide annulus make tracks over four scans; then 100 000 plots
    fall in a 10 km x 10 deg patch of it.  The unbounded association search formed every
    (track, plot) pair within the pre-gate radius at once and ran out of memory."""
    r = _run_big(batches=5, targets=2000, range_m=[50_000.0, 60_000.0], filler_from=4, dense=True)
    assert r["rss_mb"] < RSS_LIMIT_MB, r  # type: ignore[operator]
    assert r["tracks"] > 1000, r  # type: ignore[operator]
