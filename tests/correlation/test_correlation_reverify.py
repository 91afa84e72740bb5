"""Registered pair updates in proportion to what needs a decision (svd-topology stage 3).

Once a pair is registered, its confirmed pairs are re-checked by the bias-compensated
chi-square alone; only the other tracks go through the topology match.  Tested here: the
topology decision sees only those tracks, a confirmed pair whose tracks diverge fails the
re-check and is decided afresh, and the vectorised re-check against a plain per-pair loop.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2

from service.correlation import DecisionContext, PairCorrelator, PredictedTracks
from service.correlation.svd_topology import SvdTopologyCorrelator, SvdTopologyParams
from service.tracking.base import TrackTable
from topofusion_lab.evaluation.correlation_scenario import make_sites
from topofusion_lab.evaluation.correlation_stream import RadarTrackSim, StreamScenario, make_targets

SC = StreamScenario(sparse_targets=80, cluster_targets=0, confirm_scans=1, box_m=250_000.0)


def _stream(scans: int, seed: int = 4) -> list[tuple[TrackTable, TrackTable, float]]:
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    pos0, vel = make_targets(rng, SC, a)
    ra = RadarTrackSim(rng, a, SC.bias_a, len(pos0), SC)
    rb = RadarTrackSim(rng, b, SC.bias_b, len(pos0), SC)
    times = [4.0 * k for k in range(scans)]
    return [(ra.table(a, pos0, vel, t), rb.table(a, pos0, vel, t), t + 4.0) for t in times]


class _Spy(SvdTopologyCorrelator):
    """The method as published, recording the reference rows and candidates of each decide."""

    def __init__(self, params: SvdTopologyParams) -> None:
        super().__init__(params)
        self.calls: list[tuple[int, int, int, int, set[str], set[str]]] = []

    def decide(self, a: PredictedTracks, b: PredictedTracks, context: DecisionContext):  # type: ignore[no-untyped-def]
        dec = super().decide(a, b, context)
        ref_a = set(range(len(a))) if context.reference_a is None else set(context.reference_a.tolist())
        ref_b = set(range(len(b))) if context.reference_b is None else set(context.reference_b.tolist())
        assert set(dec.index_a.tolist()) <= ref_a and set(dec.index_b.tolist()) <= ref_b
        ids_a = {str(a.track_id[i]) for i in ref_a}
        ids_b = {str(b.track_id[i]) for i in ref_b}
        self.calls.append((len(a), len(b), len(ref_a), len(ref_b), ids_a, ids_b))
        return dec


def _spied(corr: PairCorrelator) -> _Spy:
    spy = _Spy(corr.params.svd)
    corr.correlator = spy
    return spy


@pytest.fixture(scope="module")
def warmed() -> tuple[list[tuple[TrackTable, TrackTable, float]], int]:
    return _stream(14), 10


def _run(tables: list[tuple[TrackTable, TrackTable, float]], upto: int) -> PairCorrelator:
    a, b = make_sites()
    corr = PairCorrelator("svd-topology", a, b)
    for ta, tb, t in tables[:upto]:
        corr.update(ta, tb, t)
    return corr


def test_verified_pairs_skip_the_topology_decision(warmed) -> None:
    tables, upto = warmed
    corr = _run(tables, upto)
    assert corr.registered
    spy = _spied(corr)
    ta, tb, t = tables[upto]
    conf_before = {(p.track_a, p.track_b) for p in corr.pairs() if p.status == "confirmed"}
    assert len(conf_before) >= 50
    corr.update(ta, tb, t)
    ((n_a, n_b, k_a, k_b, _, _),) = spy.calls
    kept = corr.last_reverified
    assert kept >= 0.9 * len(conf_before)
    # Exactly the tracks of the kept pairs left the references; every track stayed a neighbour.
    assert k_a == n_a - kept and k_b == n_b - kept
    assert len(corr.last_decisions) >= kept
    # The kept pairs are hits of the book with the re-check's statistic and no topology values.
    by_key = {(p.track_a, p.track_b): p for p in corr.pairs()}
    confirmed_now = [by_key[k] for k in conf_before if k in by_key and by_key[k].last_time_s == t]
    assert len(confirmed_now) >= kept
    verified = [p for p in confirmed_now if np.isnan(p.rotation_weight)]
    assert len(verified) >= 0.9 * kept
    for p in verified:
        assert np.isnan(p.scale) and p.neighbors == 0 and np.isfinite(p.statistic)


def test_diverging_confirmed_pair_fails_the_recheck_and_is_redecided(warmed) -> None:
    tables, upto = warmed
    corr = _run(tables, upto)
    conf = {p.track_b: p.track_a for p in corr.pairs() if p.status == "confirmed"}
    # Two B tracks of confirmed pairs, far apart: swap their ids, so each id now carries the
    # other aircraft's state (a tracker swapping two tracks).
    ta, tb, _ = tables[upto]
    rows = [i for i, tid in enumerate(tb.track_id) if tid in conf]
    i = rows[0]
    j = max(rows, key=lambda r: float(np.linalg.norm(tb.position_ecef_m[r] - tb.position_ecef_m[i])))
    x, y = str(tb.track_id[i]), str(tb.track_id[j])
    spy = _spied(corr)

    def swapped(table: TrackTable) -> TrackTable:
        ids = table.track_id.copy()
        ii, jj = int(np.flatnonzero(ids == x)[0]), int(np.flatnonzero(ids == y)[0])
        ids[ii], ids[jj] = ids[jj], ids[ii]
        return dataclasses.replace(table, track_id=ids)

    for k in range(upto, upto + 2):
        ta, tb, t = tables[k]
        corr.update(ta, swapped(tb), t)
        n_a, n_b, k_a, k_b, ref_a, ref_b = spy.calls[-1]
        # Both pairs failed the re-check: all four tracks are references of the full decision,
        # most others were kept without it.
        assert {x, y} <= ref_b and {conf[x], conf[y]} <= ref_a
        assert k_a < n_a / 4 and k_b < n_b / 4
        pairs = {(p.track_a, p.track_b): p for p in corr.pairs()}
        for bid in (x, y):
            p = pairs.get((conf[bid], bid))
            assert p is None or p.last_time_s < t  # no hit for the swapped pair
    # ... and the full decision found the crossed pairs (tentative while the old ones live on).
    pairs = {(p.track_a, p.track_b): p for p in corr.pairs()}
    assert (conf[x], y) in pairs and (conf[y], x) in pairs
    for k in range(upto + 2, upto + 4):
        ta, tb, t = tables[k]
        corr.update(ta, swapped(tb), t)
    pairs = {(p.track_a, p.track_b): p for p in corr.pairs()}
    assert pairs[(conf[x], y)].status == "confirmed" and pairs[(conf[y], x)].status == "confirmed"
    assert (conf[x], x) not in pairs and (conf[y], y) not in pairs


def _reference_recheck(
    a: PredictedTracks,
    b: PredictedTracks,
    ia: np.ndarray,
    ib: np.ndarray,
    reg_a: np.ndarray,
    reg_b: np.ndarray,
    alpha: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Plain per-pair form of the stage 3 re-check: chi-square of the position difference with
    ``P_a + P_b + R_a + R_b`` plus that of the velocity difference with ``P_va + P_vb``."""
    q = np.zeros(len(ia))
    ok = np.zeros(len(ia), dtype=bool)
    for k, (i, j) in enumerate(zip(ia, ib, strict=True)):
        d = a.position[i] - b.position[j]
        s = a.pos_cov[i] + b.pos_cov[j] + reg_a[i] + reg_b[j]
        dv = a.velocity[i] - b.velocity[j]
        sv = a.vel_cov[i] + b.vel_cov[j]
        q[k] = d @ np.linalg.solve(s, d) + dv @ np.linalg.solve(sv, dv)
        ok[k] = q[k] <= chi2.ppf(1.0 - alpha, 6)
    return q, ok


def _random_snapshot(rng: np.random.Generator, site, n: int, ids: str) -> PredictedTracks:  # type: ignore[no-untyped-def]
    pos = site.origin_ecef + rng.normal(0, 50_000.0, (n, 3))
    vel = rng.normal(0, 200.0, (n, 3))
    la = rng.normal(size=(n, 3, 3))
    lv = rng.normal(size=(n, 3, 3))
    pcov = la @ np.swapaxes(la, 1, 2) * 200.0**2 + np.eye(3) * 100.0
    vcov = lv @ np.swapaxes(lv, 1, 2) * 5.0**2 + np.eye(3)
    return PredictedTracks(
        np.array([f"{ids}{k}" for k in range(n)]),
        pos,
        vel,
        pcov,
        vcov,
        site,
        site.ecef_to_enu(pos),
        vel @ site.rotation,
        compensated=True,
    )


def test_recheck_matches_plain_loop() -> None:
    rng = np.random.default_rng(11)
    sa, sb = make_sites()
    n = 60
    a = _random_snapshot(rng, sa, n, "a")
    b0 = _random_snapshot(rng, sb, n, "b")
    # B's pairs near A's: within a few sigma (most pass), some displaced (fail).
    shift = rng.normal(0, 1.0, (n, 3)) * 400.0
    shift[::7] *= 8.0
    b = dataclasses.replace(b0, position=a.position + shift, velocity=a.velocity + rng.normal(0, 6.0, (n, 3)))
    reg_a = np.einsum("nij,nkj->nik", g := rng.normal(size=(n, 3, 3)), g) * 30.0**2
    reg_b = np.einsum("nij,nkj->nik", h := rng.normal(size=(n, 3, 3)), h) * 30.0**2
    ia = rng.permutation(n)[:40]
    ib = ia.copy()
    ctx = DecisionContext(time_s=0.0, registered=True, registration_cov_a=reg_a, registration_cov_b=reg_b)
    prm = SvdTopologyParams()
    dec = SvdTopologyCorrelator(prm).reverify(a, b, ia, ib, ctx)
    assert dec is not None
    q_ref, ok_ref = _reference_recheck(a, b, ia, ib, reg_a, reg_b, prm.alpha_position)
    np.testing.assert_allclose(dec.statistic * 6.0, q_ref, rtol=1e-9)
    np.testing.assert_allclose(dec.cost, q_ref - 6.0, rtol=1e-9, atol=1e-9)
    assert np.array_equal(dec.accepted, ok_ref)
    assert 0 < ok_ref.sum() < len(ok_ref)
    assert np.all(np.isnan(dec.rotation_weight)) and np.all(np.isnan(dec.scale))
    assert np.all(dec.neighbors == 0)
    # Not registered (or maintain_confirmed off): no cheap path, every pair goes to decide.
    assert SvdTopologyCorrelator(prm).reverify(a, b, ia, ib, DecisionContext(time_s=0.0)) is None
    off = SvdTopologyCorrelator(dataclasses.replace(prm, maintain_confirmed=False))
    assert off.reverify(a, b, ia, ib, ctx) is None


def test_other_methods_have_no_cheap_path(warmed) -> None:
    tables, _ = warmed
    a, b = make_sites()
    for method in ("basic-topology", "nearest"):
        corr = PairCorrelator(method, a, b)
        for ta, tb, t in tables[:5]:
            corr.update(ta, tb, t)
        assert corr.last_reverified == 0
