"""Initiators on hand-built cases, and vectorised forms against plain references."""

from __future__ import annotations

import functools

import numpy as np

from service.tracking import velocity_tracks as vt
from service.tracking.clustering import velocity_cluster_published
from service.tracking.cvfit import PlotStats, fit_sets, plot_stats, residual_d2
from service.tracking.groups import Groups
from service.tracking.hough import classic_hough, pg_hough
from service.tracking.initiators import hough_velocity, local_clusters
from service.tracking.logic import logic_initiate, resolve_conflicts, velocity_support
from service.tracking.measurement import Measurements
from service.tracking.params import ClusterParams, HoughParams, LogicParams, TrackerParams
from service.tracking.velocity_tracks import drop_redundant
from tests.tracking_reference_forms import fit_set_reference, velocity_cluster_reference
from topofusion_lab.evaluation.initiation import Table1Row

HP = HoughParams(
    rho_step_m=80.0,
    cell_m=20.0,
    min_votes=5.0,
    pg_min_votes=3.0,
    member_sigma=3.0,
    member_band_m=80.0,
    min_plots=5,
    max_lines=20,
)
CP = ClusterParams(delta_v_mps=30.0, lam=1.0, eta=1.0, min_plots=5, min_span_s=2.0, min_track_score=10.0)
SIG = 30.0


def _plane(points: list[tuple[np.ndarray, np.ndarray]], rng: np.random.Generator):
    xy = np.concatenate([p for p, _ in points])
    t = np.concatenate([q for _, q in points])
    xy = xy + rng.normal(0, SIG, xy.shape)
    cov = np.tile(np.eye(2) * SIG**2, (xy.shape[0], 1, 1))
    lab = np.concatenate([np.full(q.shape[0], k) for k, (_, q) in enumerate(points)])
    return xy, cov, t, lab


def _line(x0, y0, vx, vy, t0, t1, dt=0.5):
    t = np.arange(t0, t1 + 1e-9, dt)
    return np.stack([x0 + vx * (t - t0), y0 + vy * (t - t0)], axis=1), t


def _labels(groups: Groups, lab: np.ndarray) -> list[set[int]]:
    return [set(np.unique(lab[g]).tolist()) for g in groups.to_lists()]


def _vc(xy, cov, t, hp=HP):
    prelim = pg_hough(xy, cov, hp)
    return prelim, Groups.from_lists(hough_velocity(t, xy, cov, TrackerParams(hough=hp, cluster=CP)))


def test_two_targets_on_one_line_at_different_times_are_split_by_velocity_clustering() -> None:
    rng = np.random.default_rng(3)
    xy, cov, t, lab = _plane([_line(0, 0, 300, 0, 0, 10), _line(0, 0, 300, 0, 10, 20)], rng)
    prelim, vc = _vc(xy, cov, t)
    assert prelim.count == 1 and _labels(prelim, lab) == [{0, 1}]  # Hough alone: one line
    assert sorted(map(sorted, _labels(vc, lab))) == [[0], [1]]
    assert classic_hough(xy, HP).count == 1


def test_crossing_targets_give_two_tracks() -> None:
    rng = np.random.default_rng(4)
    xy, cov, t, lab = _plane([_line(0, 0, 300, 100, 0, 10), _line(0, 1000, 300, -100, 0, 10)], rng)
    _, vc = _vc(xy, cov, t)
    labels = _labels(vc, lab)
    assert len(labels) == 2
    for g in vc.to_lists():  # each track mostly one target
        assert np.max(np.bincount(lab[g])) >= 0.8 * g.shape[0]


def test_clutter_only_gives_no_track_hough_velocity() -> None:
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 3_000, (60, 2))
    t = rng.uniform(0, 20, 60)
    cov = np.tile(np.eye(2) * SIG**2, (60, 1, 1))
    _, vc = _vc(xy, cov, t)
    assert vc.count == 0


def _meas3(xyz: np.ndarray, t: np.ndarray, sig: float) -> Measurements:
    return Measurements(t, xyz, np.tile(np.eye(3) * sig**2, (t.shape[0], 1, 1)))


def test_logic_crossing_targets_and_clutter_only() -> None:
    rng = np.random.default_rng(6)
    scan = 4.0
    t = np.array([0.0, 4.0, 8.0])
    a = np.stack([-1200 + 300 * t, 0 * t, 5000 + 0 * t], axis=1)
    b = np.stack([0 * t, -1500 + 300 * t, 5000 + 0 * t], axis=1)  # crosses a's path at t = 5 s
    xyz = np.concatenate([a, b]) + rng.normal(0, 50, (6, 3))
    g = logic_initiate(_meas3(xyz, np.concatenate([t, t]), 50.0), LogicParams(), scan)
    assert sorted(sorted(x.tolist()) for x in g.to_lists()) == [[0, 1, 2], [3, 4, 5]]
    # Clutter only: 30 plots per scan over 200 km x 200 km x 10 km, 3 scans -> nothing.
    n = 90
    cl = np.stack([rng.uniform(-1e5, 1e5, n), rng.uniform(-1e5, 1e5, n), rng.uniform(0, 1e4, n)], axis=1)
    tc = np.repeat([0.0, 4.0, 8.0], 30)
    assert logic_initiate(_meas3(cl, tc, 200.0), LogicParams(), scan).count == 0


def test_logic_two_targets_on_one_line_at_different_times() -> None:
    t = np.array([0.0, 4.0, 8.0])
    a = np.stack([300 * t, 0 * t, 0 * t + 3000], axis=1)
    b = np.stack([300 * (t + 12.0), 0 * t, 0 * t + 3000], axis=1)  # same line, 12 s later
    g = logic_initiate(
        _meas3(np.concatenate([a, b]), np.concatenate([t, t + 12.0]), 30.0), LogicParams(), 4.0
    )
    assert sorted(sorted(x.tolist()) for x in g.to_lists()) == [[0, 1, 2], [3, 4, 5]]


def _lattice_triples(seed: int, params: LogicParams) -> tuple[int, int]:
    """Three scans of 20 aircraft on a jittered 1.5 km lattice flying east at 250 m/s with 6 s
    scans (a scan's travel is the spacing: a line across the lattice is as straight as one
    aircraft's); the logic initiator's triples, and how many hold one aircraft's plots."""
    rng = np.random.default_rng(seed)
    nx, ny, spacing, speed, scan, sig = 5, 4, 1500.0, 250.0, 6.0, 150.0
    gx, gy = np.meshgrid(np.arange(nx) * spacing, np.arange(ny) * spacing)
    n = nx * ny
    start = np.stack([gx.ravel(), gy.ravel()], axis=1) + rng.uniform(-300.0, 300.0, (n, 2))
    t = np.concatenate([k * scan + rng.uniform(0.0, 0.2, n) for k in range(3)])
    owner = np.tile(np.arange(n), 3)
    xy = start[owner] + np.stack([speed * t, 0.0 * t], axis=1) + rng.normal(0.0, sig, (3 * n, 2))
    xyz = np.column_stack([xy, 9000.0 + rng.normal(0.0, sig, 3 * n)])
    order = np.argsort(t)
    meas = _meas3(xyz[order], t[order], sig)
    groups = logic_initiate(meas, params, scan).to_lists()
    own = sum(len(set(owner[order][g].tolist())) == 1 for g in groups)
    return own, len(groups)


def test_logic_in_a_formation_starts_each_aircraft_on_its_own_plots() -> None:
    """Ranked by their velocity's support, the triples follow the aircraft; by straightness
    alone most run across the formation (10 seeds)."""
    on = [_lattice_triples(seed, LogicParams()) for seed in range(10)]
    cells = [_lattice_triples(seed, LogicParams(support_max_pairs=0)) for seed in range(10)]
    off = [_lattice_triples(seed, LogicParams(support_weight=0.0)) for seed in range(10)]
    own_on, all_on = map(sum, zip(*on, strict=True))
    own_cells, all_cells = map(sum, zip(*cells, strict=True))
    own_off, all_off = map(sum, zip(*off, strict=True))
    assert own_on >= 0.9 * all_on and all_on >= 0.9 * 200  # nearly every aircraft, on its own plots
    assert own_cells >= 0.8 * all_cells and all_cells >= 0.9 * 200  # beyond the work bound: cells
    assert own_off < 0.6 * all_off  # the same scenes without the rule


def _velocity_support_reference(
    meas: Measurements, trip: np.ndarray, radius_m: float, k_sigma: float
) -> list[int]:
    t, z, R = meas.time_s, meas.enu_m, meas.covariance
    vel, sig, first = [], [], []
    for a, _, c in trip.tolist():
        dt = t[c] - t[a]
        vel.append((z[c, :2] - z[a, :2]) / dt)
        sig.append(np.sqrt(np.trace(R[a, :2, :2] + R[c, :2, :2])) / dt)
        first.append(z[a, :2])
    scale = k_sigma * float(np.median(sig))
    out = []
    for i in range(len(vel)):
        out.append(
            sum(
                bool(np.all(np.abs(first[j] - first[i]) <= radius_m))
                and bool(np.all(np.abs(vel[j] - vel[i]) <= scale))
                for j in range(len(vel))
            )
        )
    return out


def _random_triples(rng: np.random.Generator) -> tuple[Measurements, np.ndarray]:
    """60 plots over 60 km and 20 s, and up to 80 time-ordered triples of them."""
    n = 60
    t = rng.uniform(0.0, 20.0, n)
    z = np.column_stack([rng.uniform(-3e4, 3e4, (n, 2)), rng.uniform(0.0, 1e4, n)])
    trip = np.array([sorted(rng.choice(n, 3, replace=False), key=lambda k: t[k]) for _ in range(80)])
    return _meas3(z, t, 300.0), trip[t[trip[:, 2]] > t[trip[:, 0]]]


def test_velocity_support_matches_plain_reference() -> None:
    rng = np.random.default_rng(12)
    for _ in range(5):
        meas, trip = _random_triples(rng)
        got = velocity_support(meas, trip, 15_000.0, 10.0)  # supports of 1 to 4
        assert got.tolist() == _velocity_support_reference(meas, trip, 15_000.0, 10.0)


def test_velocity_support_beyond_its_work_bound_is_the_cell_count() -> None:
    """Past ``support_max_pairs`` a triple's support is the number of triples in its cell (side
    twice the reach in the scaled coordinates), as a plain count gives it."""
    meas, trip = _random_triples(np.random.default_rng(13))
    t, z = meas.time_s, meas.enu_m
    exact = velocity_support(meas, trip, 15_000.0, 10.0)
    cells = velocity_support(meas, trip, 15_000.0, 10.0, max_pairs=0)
    sig = [
        np.sqrt(np.trace(meas.covariance[a, :2, :2] + meas.covariance[c, :2, :2])) / (t[c] - t[a])
        for a, _, c in trip
    ]
    scale = 10.0 * float(np.median(sig))
    keys = []
    for a, _, c in trip.tolist():
        v = (z[c, :2] - z[a, :2]) / (t[c] - t[a])
        keys.append(tuple(int(np.floor(x / 2.0)) for x in [*(z[a, :2] / 15_000.0), *(v / scale)]))
    assert cells.tolist() == [keys.count(k) for k in keys]
    assert not np.array_equal(cells, exact)  # (the two counts differ here: the bound took effect)


def test_velocity_cluster_matches_reference() -> None:
    rng = np.random.default_rng(7)
    for trial in range(6):
        xy, _cov, t, _ = _plane([_line(0, 0, 300, 0, 0, 6, 1.0), _line(0, 500, 250, 0, 0, 6, 1.0)], rng)
        extra = rng.uniform(0, 2000, (4, 2))
        xy = np.concatenate([xy, extra])
        t = np.concatenate([t, rng.uniform(0, 6, 4)])
        delta = np.full(t.shape[0], SIG * np.sqrt(2)) * rng.uniform(0.8, 1.2, t.shape[0])
        p = ClusterParams(
            delta_v_mps=40.0, lam=1.0 + trial % 3, eta=1.0 + 0.5 * (trial % 2), merge_overlap=2 + trial % 2
        )
        fast = sorted(tuple(x.tolist()) for x in velocity_cluster_published(t, xy, delta, p))
        ref = sorted(tuple(x.tolist()) for x in velocity_cluster_reference(t, xy, delta, p))
        assert fast == ref


def test_resolve_conflicts_matches_sequential_greedy() -> None:
    rng = np.random.default_rng(8)
    for _ in range(20):
        members = rng.integers(0, 30, (40, 3))
        cost = rng.random(40)
        got = set(resolve_conflicts(members, cost, 30).tolist())
        used: set[int] = set()
        want = set()
        for k in np.lexsort((np.arange(40), cost)):
            if not used & set(members[k].tolist()):
                want.add(int(k))
                used |= set(members[k].tolist())
        assert got == want


@functools.cache
def _table1_rows() -> dict[str, Table1Row]:
    """Eight Monte Carlo runs of the Table 1 set-up (seed 0), shared by the tests below (the
    full 200 runs are in the evaluation)."""
    from topofusion_lab.evaluation.initiation import run_table1

    return {r.method: r for r in run_table1(runs=8, seed=0)}


def test_table1_fixed_clustering_beats_published_and_baselines() -> None:
    """The fixed Steps 7-8 beat the published ones and both Hough baselines on both columns."""
    rows = _table1_rows()
    vc = rows["Hough + velocity clustering"]
    for other in (
        "Hough",
        "probabilistic-grid Hough",
        "PG Hough + velocity clustering, Steps 7-8 as published",
    ):
        assert vc.accuracy > rows[other].accuracy and vc.false_ratio < rows[other].false_ratio


def test_table1_goal_hough_velocity_clustering() -> None:
    """Issue 3's goal on eight runs: accuracy >= 98 % and false tracks <= 5 % (40 targets: a
    single missed target fails it; with 25 Hough lines instead of 60 the weaker target of the
    crossing pair in run 7 had no line and this failed)."""
    vc = _table1_rows()["Hough + velocity clustering"]
    assert vc.accuracy >= 98.0 and vc.false_ratio <= 5.0


def test_cv_fit_matches_reference_and_gates() -> None:
    rng = np.random.default_rng(9)
    n = 12
    t = np.sort(rng.uniform(0, 10, n))
    xy = rng.normal(0, 500, (n, 2))
    a = rng.normal(size=(n, 2, 2))
    cov = a @ np.swapaxes(a, 1, 2) * 100.0 + np.eye(2) * 50.0
    members = rng.random((5, n)) < 0.6
    members[:, :3] = True
    stats = plot_stats(t, xy, cov, 0.0)
    fits = fit_sets(stats, members, 0.5)
    d2 = residual_d2(stats, fits, predicted=False)
    d2p = residual_d2(stats, fits, predicted=True)
    for q in range(members.shape[0]):  # plain loop reference per set
        m = members[q]
        theta, chi2 = fit_set_reference(t[m], xy[m], cov[m], 0.0)
        np.testing.assert_allclose(fits.theta[q], theta, rtol=1e-8, atol=1e-6)
        np.testing.assert_allclose(fits.chi2[q], chi2, rtol=1e-6, atol=1e-6)
        assert np.isclose(np.sum(d2[q, m]), chi2, rtol=1e-6)
        for k in range(n):
            h = np.array([[1.0, 0.0, t[k], 0.0], [0.0, 1.0, 0.0, t[k]]])
            r = xy[k] - h @ theta
            s_k = cov[k] + h @ fits.cov[q] @ h.T
            assert np.isclose(d2p[q, k], r @ np.linalg.solve(s_k, r), rtol=1e-6)


def test_drop_redundant_matches_reference() -> None:
    rng = np.random.default_rng(10)
    sets = rng.random((40, 12)) < 0.3
    sets = np.concatenate([sets, sets[:5], sets[:3] & (rng.random((3, 12)) < 0.5)])
    got = {tuple(r) for r in drop_redundant(sets).tolist()}
    rows = [tuple(r) for r in sets.tolist()]
    want = set()
    for a in rows:  # keep a unless a proper subset of, or equal to an earlier copy of, another
        sub = any(set(np.flatnonzero(a)) < set(np.flatnonzero(b)) for b in rows)
        if not sub:
            want.add(a)
    assert got == want


def test_local_clusters_split_far_plots() -> None:
    t = np.array([0.0, 4.0, 8.0, 0.0, 4.0, 8.0, 0.0])
    xyz = np.array(
        [
            [0, 0, 0],
            [1200, 0, 0],
            [2400, 0, 0],
            [80_000, 0, 0],
            [80_000, 1200, 0],
            [80_000, 2400, 0],
            [40_000, 0, 0],
        ],
        dtype=float,
    )
    clusters = local_clusters(_meas3(xyz, t, 100.0), 700.0, 3)
    assert sorted(sorted(c.tolist()) for c in clusters) == [[0, 1, 2], [3, 4, 5]]


def _select_reference(stats: PlotStats, sets: np.ndarray, p: ClusterParams) -> list[np.ndarray]:
    """Plain form of :func:`select_tracks`."""
    taken = np.zeros(stats.tau.shape[0], dtype=bool)
    out = []
    sets = sets.copy()
    for _ in range(sets.shape[0]):  # re-test every candidate in every pass
        sets &= ~taken
        ok, cost = vt._consistent(stats, sets, p)
        ok &= sets.sum(axis=1) >= min(p.min_plots, 3)
        if not ok.any():
            break
        best = int(np.flatnonzero(ok)[np.argmin(cost[ok])])
        member = sets[best].copy()
        sets = np.delete(sets, best, axis=0)
        for _ in range(p.grow_rounds):  # converge one set: refit and re-gate every round
            fits = fit_sets(stats, member[None, :], p.min_span_s)
            d2 = residual_d2(stats, fits, predicted=True)[0]
            new = ~taken & (d2 <= p.plot_gate_chi2) if fits.valid[0] else member
            if (new == member).all() or not vt._consistent(stats, new[None, :], p)[0][0]:
                break
            member = new
        ok1, cost1 = vt._consistent(stats, member[None, :], p)
        if member.sum() >= p.min_plots and ok1[0] and -cost1[0] >= p.min_track_score:
            out.append(np.flatnonzero(member))
            taken |= member
    return out


def test_select_tracks_matches_plain_reference() -> None:
    """Step 8 (re-testing only the candidates that lost plots) against the plain form that
    re-tests every candidate in every pass, on a Table 1 realisation."""
    from service.tracking.hough import pg_hough_bands
    from topofusion_lab.evaluation.initiation import TABLE1_CLUSTER, TABLE1_HOUGH
    from topofusion_lab.evaluation.initiation_bistatic import BistaticScenario, simulate_bistatic

    p = TABLE1_CLUSTER
    pl = simulate_bistatic(BistaticScenario(), np.random.default_rng([0, 7]))
    bands = pg_hough_bands(pl.xy, pl.cov, TABLE1_HOUGH)[:12]
    parts = [np.zeros((0, pl.time_s.shape[0]), dtype=bool)]
    for band, angle in bands:
        sub = vt.candidate_tracks(pl.time_s[band], pl.xy[band], pl.cov[band], p, angle)
        full = np.zeros((sub.shape[0], pl.time_s.shape[0]), dtype=bool)
        full[:, band] = sub
        parts.append(full)
    sets = vt.drop_redundant(np.concatenate(parts))
    stats = plot_stats(pl.time_s, pl.xy - pl.xy.mean(axis=0), pl.cov, float(pl.time_s.min()))
    got = vt.select_tracks(stats, sets, p)
    want = _select_reference(stats, sets, p)
    assert len(got) >= 3
    assert [g.tolist() for g in got] == [w.tolist() for w in want]
    # Step 7 (refitting only the sets updated last round) against one set at a time.
    seeds = np.concatenate(parts)[:40]
    allowed = np.ones(pl.time_s.shape[0], dtype=bool)
    both = vt.converge(stats, seeds, allowed, p)
    for q in range(seeds.shape[0]):  # plain loop over sets
        assert (vt.converge(stats, seeds[q : q + 1], allowed, p)[0] == both[q]).all()
