"""History evidence (service/correlation/evidence.py), the joint ambiguity rule and the group
offset against their plain reference forms; the pair fields and the dense-formation gain."""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest

from service.correlation import CorrelationParams, PairCorrelator
from service.correlation.assignment import _joint_regret, assign_unambiguous
from service.correlation.base import PredictedTracks
from service.correlation.evidence import EvidenceBook, EvidenceParams
from service.correlation.group_offset import GroupOffsetParams, group_residuals
from service.geo import Site
from service.tracking.base import TrackTable
from tests.reference_forms import evidence_reference, group_offset_reference, joint_regret_reference


def _spd(rng: np.random.Generator, scale: float) -> np.ndarray:
    m = rng.normal(size=(3, 3)) * scale
    return m @ m.T + np.eye(3) * scale**2


def test_evidence_accumulation_matches_the_reference() -> None:
    rng = np.random.default_rng(1)
    prm = EvidenceParams()
    book = EvidenceBook(prm)
    looks = []
    t = 0.0
    for _ in range(12):
        t += float(rng.uniform(3.0, 40.0))
        look = (t, rng.normal(0, 200, 3), _spd(rng, 150.0), _spd(rng, 40.0))
        looks.append(look)
        book.observe(t, np.array(["A-1"]), np.array(["B-1"]), look[1][None], look[2][None], look[3][None])
        # A second look at the same time is the same update: ignored.
        book.observe(t, np.array(["A-1"]), np.array(["B-1"]), 5 * look[1][None], look[2][None], look[3][None])
        rbar, n_eff, q = evidence_reference(looks, prm.horizon_s, prm.error_correlation_s)
        assert len(book) == 1 and book.looks[0] == len(looks)
        np.testing.assert_allclose(book.rbar[0], rbar, rtol=1e-9, atol=1e-9)
        assert book.n_eff[0] == pytest.approx(n_eff, rel=1e-12)
        assert book.q[0] == pytest.approx(q, rel=1e-9)


def test_evidence_prune_and_probability() -> None:
    # Uncalibrated: the posterior over one track's hypotheses (the calibration maps it onward).
    book = EvidenceBook(EvidenceParams(calibration_slope=1.0, calibration_offset=0.0))
    s = np.broadcast_to(np.eye(3) * 100.0**2, (3, 3, 3)).copy()
    r = np.array([[10.0, 0, 0], [400.0, 0, 0], [0.0, 900.0, 0]])
    ta, tb = np.array(["A-1", "A-1", "A-2"]), np.array(["B-1", "B-2", "B-2"])
    for t in (0.0, 10.0, 20.0):
        book.observe(t, ta, tb, r, s)
    p = dict(zip(book.keys, book.probability(), strict=True))
    key = {(a, b): k for a, b, k in zip(book.track_a, book.track_b, book.keys, strict=True)}
    # A-1's close pairing beats its rival; the probabilities of one track's hypotheses sum below 1.
    assert p[key["A-1", "B-1"]] > 0.9 > p[key["A-1", "B-2"]]
    assert p[key["A-1", "B-1"]] + p[key["A-1", "B-2"]] < 1.0
    assert book.rejected().tolist() == [False, True, True]
    # Track B-2 leaves: its entries go; unobserved entries of present tracks go when asked.
    book.prune(30.0, np.array(["A-1", "A-2"]), np.array(["B-1"]))
    assert book.keys.tolist() == [key["A-1", "B-1"]]
    book.prune(30.0, np.array(["A-1"]), np.array(["B-1"]), unobserved_present=True)
    assert len(book) == 0


def test_joint_regret_matches_the_reference() -> None:
    rng = np.random.default_rng(5)
    for _ in range(200):
        na, nb = rng.integers(1, 7, 2)
        mask = rng.random((na, nb)) < 0.5
        ia, ib = np.nonzero(mask)
        if ia.size == 0:
            continue
        c = rng.normal(0, 5, ia.size)
        chosen, amb = assign_unambiguous(ia, ib, c, np.ones(ia.size, bool), 6.0, 8.3)
        assigned = chosen | amb
        got = _joint_regret(ia, ib, c, assigned, 8.3)
        want = joint_regret_reference(ia, ib, c, assigned, 8.3)
        np.testing.assert_allclose(got[assigned], want[assigned])
        np.testing.assert_array_equal(amb, assigned & (want < 6.0))


def test_joint_rule_resolves_two_close_targets_the_single_pair_rule_cannot() -> None:
    # Two targets, each pairing 4 better than its crossed one: per pair not decisive (< 6),
    # jointly the crossed assignment is 8 worse.
    ia, ib = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])
    c = np.array([0.0, 4.0, 4.0, 0.0])
    acc = np.ones(4, bool)
    single, _ = assign_unambiguous(ia, ib, c, acc, 6.0)
    joint, _ = assign_unambiguous(ia, ib, c, acc, 6.0, 8.3)
    assert not single.any()
    assert joint.tolist() == [True, False, False, True]


def _snapshot(site: Site, enu: np.ndarray, sigma: float) -> PredictedTracks:
    n = len(enu)
    cov = np.broadcast_to(np.eye(3) * sigma**2, (n, 3, 3)).copy()
    ecef = site.enu_to_ecef(enu)
    return PredictedTracks(
        track_id=np.array([f"{site.site_id}-{k}" for k in range(n)]),
        position=ecef,
        velocity=np.zeros((n, 3)),
        pos_cov=site.rotation @ cov @ site.rotation.T,
        vel_cov=cov.copy(),
        site=site,
        enu=enu,
        enu_velocity=np.zeros((n, 3)),
    )


def test_group_offset_matches_the_reference_and_finds_the_offset() -> None:
    from service.correlation.candidates import candidate_pairs
    from topofusion_lab.evaluation.correlation_scenario import make_sites

    rng = np.random.default_rng(3)
    a, b = make_sites()
    spacing, sigma = 800.0, 250.0
    grid = np.array([(i, j) for i in range(5) for j in range(5)], float) * spacing
    truth = np.column_stack([grid + rng.normal(0, 0.25 * spacing, grid.shape), np.full(25, 9_000.0)])
    truth[:, :2] += [100_000.0, 50_000.0]
    offset = np.array([700.0, -500.0, 0.0])  # A's picture displaced (B's ENU orientation)
    ecef = a.enu_to_ecef(truth)
    pos_a = ecef + offset @ b.rotation.T + rng.normal(0, sigma, ecef.shape)
    pos_b = ecef + rng.normal(0, sigma, ecef.shape)
    sa = _snapshot(a, a.ecef_to_enu(pos_a), sigma)
    sb = _snapshot(b, b.ecef_to_enu(pos_b), sigma)
    ia, ib, _ = candidate_pairs(sa.position, sb.position, 10_000.0)
    prm = GroupOffsetParams()
    ok, r, _s, cov = group_residuals(sa, sb, ia, ib, prm)
    d = (sa.position[ia] - sb.position[ib]) @ b.rotation
    s = b.rotation.T @ (sa.pos_cov[ia] + sb.pos_cov[ib]) @ b.rotation
    ref = group_offset_reference(
        d, s, sa.position, ia, prm.radius_m, prm.support_bandwidth, prm.starts, prm.iterations, prm.gate_chi2
    )
    assert ok.all()
    np.testing.assert_allclose(d[ok] - r, np.array([ref[int(i)][0] for i in ia[ok]]), atol=1e-6)
    # The offset is the displacement, not a lattice shift away from it (with the relative noise
    # near half the spacing one snapshot places it within a few hundred metres).
    est = d[ok] - r
    assert np.median(np.linalg.norm(est[:, :2] - offset[:2], axis=1)) < 0.5 * spacing
    true_pairs = ia[ok] == ib[ok]
    q = np.einsum("ki,kij,kj->k", r, np.linalg.inv(_s + cov), r)
    assert np.median(q[true_pairs]) < 4.0 < np.median(q[~true_pairs])


def _formation_correlator(
    seed: int, scans: int = 40, evidence: bool = True
) -> tuple[PairCorrelator, TrackTable, TrackTable, float]:
    """A 5 x 5 lattice at 3 cross-range errors seen by two biased radars, correlated for
    ``scans`` scans: the correlator, the last tables and the last update's time."""
    from topofusion_lab.evaluation.correlation_scenario import make_sites
    from topofusion_lab.evaluation.correlation_stream import RadarBias, RadarTrackSim, StreamScenario

    rng = np.random.default_rng(seed)
    a, b = make_sites()
    sc = StreamScenario(
        scans=scans, scan_period_s=10.0, bias_a=RadarBias(300, 0.5, 0.05), bias_b=RadarBias(-200, -0.4, -0.05)
    )
    cross = 120_000.0 * np.radians(a.azimuth_sigma_deg) * sc.track_noise_factor
    n = 25
    grid = np.array([(i, j) for i in range(5) for j in range(5)], float) * 3.0 * cross
    grid += rng.normal(0, 0.75 * cross, grid.shape)
    pos = np.column_stack([grid + np.array([100_000.0, 60_000.0]), np.full(n, 9_000.0)])
    vel = np.tile([150.0, 150.0, 0.0], (n, 1))
    ra, rb = RadarTrackSim(rng, a, sc.bias_a, n, sc), RadarTrackSim(rng, b, sc.bias_b, n, sc)
    prm = CorrelationParams()
    if not evidence:
        prm = replace(prm, evidence=replace(prm.evidence, enabled=False))
    corr = PairCorrelator("svd-topology", a, b, prm)
    for k in range(sc.scans):
        ta, tb = ra.table(a, pos, vel, 10.0 * k), rb.table(a, pos, vel, 10.0 * k)
        corr.update(ta, tb, 10.0 * k + 10.0)
    return corr, ta, tb, 10.0 * k + 10.0


def _formation_run(evidence: bool, seed: int) -> tuple[float, float, list]:
    corr, ta, tb, _ = _formation_correlator(seed, evidence=evidence)
    n = len(ta)
    truth_a = dict(zip(ta.track_id, ta.truth_id, strict=True))
    truth_b = dict(zip(tb.track_id, tb.truth_id, strict=True))
    conf = [p for p in corr.pairs() if p.status == "confirmed"]
    ok = sum(truth_a[p.track_a] == truth_b[p.track_b] for p in conf)
    return ok / n, (len(conf) - ok) / max(len(conf), 1), corr.pairs()


def test_a_formation_is_resolved_with_the_history_and_not_without() -> None:
    with_ev = [_formation_run(True, s) for s in (1, 2)]
    without = [_formation_run(False, s) for s in (1, 2)]
    assert all(c >= 0.75 and f <= 0.05 for c, f, _ in with_ev)
    assert np.mean([c for c, _, _ in with_ev]) > np.mean([c for c, _, _ in without]) + 0.5


def test_pair_fields_are_null_without_a_topology_fit() -> None:
    pairs = _formation_run(True, 1)[2]
    assert {p.basis for p in pairs} <= {"topology", "registered", "history"}
    assert any(p.basis in ("registered", "history") for p in pairs)
    for p in pairs:
        fit = np.isfinite(p.rotation_weight)
        # A topology fit reports its weight, scale and matched neighbours; no fit, none of them.
        assert fit == np.isfinite(p.scale)
        assert (p.neighbors >= 2) if fit else (p.neighbors == 0)
        if p.basis == "registered":
            assert not fit
    # The score is a probability, not a saturated hit fraction.
    scores = np.array([p.score for p in pairs])
    assert ((scores > 0) & (scores < 1)).all() and len(np.unique(scores)) > len(scores) // 2


def test_group_offset_work_is_bounded_in_a_hostile_blob() -> None:
    """Hundreds of tracks within a few hundred metres: the votes would grow with the cube of
    their number; beyond the bound no offset is estimated, quickly and without the memory."""
    from service.correlation.candidates import candidate_pairs
    from topofusion_lab.evaluation.correlation_scenario import make_sites

    rng = np.random.default_rng(9)
    a, b = make_sites()
    n = 400
    enu = np.column_stack([rng.normal(0, 150, (n, 2)) + np.array([100_000.0, 50_000.0]), np.full(n, 9_000.0)])
    sa = _snapshot(a, a.ecef_to_enu(a.enu_to_ecef(enu)), 100.0)
    sb = _snapshot(b, b.ecef_to_enu(a.enu_to_ecef(enu)), 100.0)
    ia, ib, _ = candidate_pairs(sa.position, sb.position, 10_000.0)
    assert len(ia) == n * n
    ok, r, _s, _c = group_residuals(sa, sb, ia, ib, GroupOffsetParams(max_comparisons=1_000_000))
    assert not ok.any() and len(r) == 0


def test_shifted_evidence_equals_the_looks_taken_with_the_shift() -> None:
    # A re-solved registration moves every look of a pair by the same compensation change:
    # the mean residual moves by it, and the test is taken again (the plain weighted sums).
    rng = np.random.default_rng(4)
    prm = EvidenceParams()
    book = EvidenceBook(prm)
    looks, t = [], 0.0
    for _ in range(6):
        t += float(rng.uniform(5.0, 30.0))
        look = (t, rng.normal(0, 300, 3), _spd(rng, 150.0), _spd(rng, 60.0))
        looks.append(look)
        book.observe(t, np.array(["A-1"]), np.array(["B-1"]), look[1][None], look[2][None], look[3][None])
    delta = np.array([[-700.0, 250.0, 40.0]])
    book.shift(np.array([0]), delta)
    rbar, _, q = evidence_reference([(t, r + delta[0], s, c) for t, r, s, c in looks], 300.0, 45.0)
    assert len(book) == 1
    np.testing.assert_allclose(book.rbar[0], rbar, rtol=1e-9, atol=1e-9)
    assert book.q[0] == pytest.approx(q, rel=1e-9)
    without_c = [(t, r + delta[0], s, np.zeros((3, 3))) for t, r, s, _ in looks]
    assert book.q_rel[0] == pytest.approx(evidence_reference(without_c, 300.0, 45.0)[2], rel=1e-9)


def _one_row(p: PredictedTracks, i: int) -> PredictedTracks:
    rows = {
        f.name: getattr(p, f.name)[i : i + 1]
        for f in fields(p)
        if isinstance(getattr(p, f.name), np.ndarray) and getattr(p, f.name).shape[:1] == (len(p),)
    }
    return replace(p, **rows)


def test_recompensation_matches_a_plain_reference() -> None:
    # A registered formation's evidence, moved from another estimate to the correlator's own:
    # each present pair's mean residual moves by the change of its two tracks' compensated
    # positions (track by track, in B's ENU frame), an absent track's pairs not at all.
    from service.correlation.prediction import predict_tracks
    from service.correlation.registration import BiasSolution, compensate

    corr, ta, tb, t = _formation_correlator(seed=3, scans=16)
    ev, new = corr.evidence, corr.solution
    assert ev is not None and new is not None and len(ev) > 20
    terms, cov = new.full
    was = BiasSolution.of_terms(
        new.radar_ids, terms + np.array([150.0, 2e-3, 1e-3, 0.0, 0.0]), cov, new.pairs_used
    )
    keep = np.arange(len(ta)) != 0  # A's first track has left this snapshot
    ta = ta.take(keep)
    prm = corr.params.prediction
    keys_a, keys_b = corr._keys(ta, tb)
    raw_a = predict_tracks(ta, corr.site_a, t, prm, keys_a)
    raw_b = predict_tracks(tb, corr.site_b, t, prm, keys_b)
    before = ev.rbar.copy()
    sa, sb = corr.site_a.site_id, corr.site_b.site_id
    was_a, was_b = compensate(raw_a, *was.of(sa))[0], compensate(raw_b, *was.of(sb))[0]
    corr._recompensate(was_a, was_b, raw_a, raw_b)
    moved = 0
    for e in range(len(ev)):
        ia = [i for i, k in enumerate(raw_a.keys) if k == ev.track_a[e]]
        ib = [i for i, k in enumerate(raw_b.keys) if k == ev.track_b[e]]
        if not ia or not ib:
            np.testing.assert_array_equal(ev.rbar[e], before[e])
            continue
        row_a, row_b = _one_row(raw_a, ia[0]), _one_row(raw_b, ib[0])
        da = compensate(row_a, *new.of(sa))[0].position - compensate(row_a, *was.of(sa))[0].position
        db = compensate(row_b, *new.of(sb))[0].position - compensate(row_b, *was.of(sb))[0].position
        change = ((da - db) @ corr.site_b.rotation)[0]
        np.testing.assert_allclose(ev.rbar[e] - before[e], change, atol=1e-6)
        moved += bool(np.linalg.norm(change) > 10.0)
    assert moved > 20
