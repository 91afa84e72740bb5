"""The ``gmm`` correlator on dense scenes: sigma floor, candidates and rivals, residuals, refusal."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.correlation.assignment import assign_unambiguous
from service.correlation.base import DecisionContext, PredictedTracks, Reason
from service.correlation.external import GmmCorrelator
from service.correlation.gmm import GmmParams, candidate_pairs, gmm_associate, sigma_floor_m
from tests.correlation_support import snapshot_of
from topofusion_lab.evaluation.correlation_gmm_scene import paper_scene
from topofusion_lab.evaluation.correlation_scenario import make_sites

# -- plain reference forms -------------------------------------------------------------------


def candidate_pairs_loop(
    post: np.ndarray, chi2: np.ndarray, threshold: float, rival_floor: float, gate: float
) -> tuple[list[int], list[int], list[bool]]:
    """Per pair, as :func:`candidate_pairs` describes it."""
    m, n = post.shape
    ia, ib, acc = [], [], []
    for i in range(m):
        for j in range(n):
            if post[i, j] > threshold or post[i, j] >= rival_floor or chi2[i, j] <= gate:
                ia.append(i)
                ib.append(j)
                row = any(post[i, k] > threshold for k in range(n))
                col = any(post[k, j] > threshold for k in range(m))
                acc.append(row or col)
    return ia, ib, acc


def test_candidate_pairs_match_loop() -> None:
    rng = np.random.default_rng(1)
    for _ in range(100):
        m, n = rng.integers(1, 9, 2)
        post = rng.dirichlet(np.ones(n + 1), size=m)[:, :n] ** rng.uniform(0.3, 3.0)
        chi2 = rng.exponential(8.0, (m, n))
        args = (0.5, float(rng.choice([0.0, 0.01, 0.2])), float(rng.choice([-1.0, 5.0, 13.8])))
        ia, ib, acc = candidate_pairs(post, chi2, *args)
        ra, rb, racc = candidate_pairs_loop(post, chi2, *args)
        np.testing.assert_array_equal(ia, ra)
        np.testing.assert_array_equal(ib, rb)
        np.testing.assert_array_equal(acc, racc)
        assert ia.dtype == ib.dtype == np.intp and acc.dtype == bool


def test_candidate_pairs_empty() -> None:
    ia, ib, acc = candidate_pairs(np.empty((0, 0)), np.empty((0, 0)), 0.5, 0.01, 13.8)
    assert ia.size == ib.size == acc.size == 0


def test_a_rival_is_never_chosen() -> None:
    """With costs -2 ln P, an accepted candidate that is not decisive always has a cheaper
    accepted candidate in its row or column: the assignment cannot keep it."""
    rng = np.random.default_rng(2)
    for _ in range(200):
        m, n = rng.integers(2, 8, 2)
        post = rng.dirichlet(np.full(n + 1, 0.3), size=m)[:, :n]
        ia, ib, acc = candidate_pairs(post, np.full((m, n), 99.0), 0.5, 0.01, 13.8)
        p = post[ia, ib]
        chosen, _ = assign_unambiguous(ia, ib, -2.0 * np.log(p), acc, float(rng.choice([0.0, 6.0])))
        assert np.all(p[chosen] > 0.5)


def test_sigma_floor_matches_formula() -> None:
    rng = np.random.default_rng(3)
    la, lb = rng.normal(size=(6, 2, 2)), rng.normal(size=(4, 2, 2))
    ca, cb = la @ la.transpose(0, 2, 1), lb @ lb.transpose(0, 2, 1)
    want = np.sqrt((np.mean([np.trace(c) for c in ca]) + np.mean([np.trace(c) for c in cb])) / 2.0 * 1.5)
    assert sigma_floor_m(ca, cb, GmmParams(sigma_floor_factor=1.5)) == pytest.approx(want, rel=1e-12)
    assert sigma_floor_m(None, cb, GmmParams()) == 0.0
    assert sigma_floor_m(ca, cb, GmmParams(sigma_floor_factor=0.0)) == 0.0
    assert sigma_floor_m(ca * np.nan, cb, GmmParams()) == 0.0


def test_sigma_held_to_the_tracks_errors_on_a_dense_lattice() -> None:
    """On a lattice as dense as the errors, with a quarter of the aircraft unseen by B, EM's
    sigma shrinks towards the nearest-centroid spread; the covariances bound it at the
    relative error of two tracks of one target."""
    rng = np.random.default_rng(2)
    k = np.arange(36)
    truth = 300.0 * (np.column_stack([k % 6, k // 6]) + rng.uniform(-0.25, 0.25, (36, 2)))
    seen_b = np.flatnonzero(rng.random(36) < 0.75)
    pos_a = truth + rng.normal(0.0, 150.0, truth.shape)
    pos_b = truth[seen_b] + np.array([3000.0, -2000.0]) + rng.normal(0.0, 150.0, (seen_b.size, 2))
    cov = np.broadcast_to(np.eye(2) * 150.0**2, (36, 2, 2))
    free = gmm_associate(pos_a, pos_b)
    held = gmm_associate(pos_a, pos_b, None, cov, cov[: seen_b.size])
    assert held.sigma_floor_m == pytest.approx(150.0 * np.sqrt(2.0))
    assert held.sigma_m >= held.sigma_floor_m * (1 - 1e-9)
    assert free.sigma_m < 0.8 * held.sigma_floor_m  # what the floor prevents
    assert held.posterior_matrix.shape == (36, seen_b.size)
    np.testing.assert_allclose(held.posterior_matrix[held.index_a, held.index_b], held.posterior)


# -- the stream adapter -------------------------------------------------------------------------


def two_close_targets(noise: float = 100.0) -> tuple[PredictedTracks, PredictedTracks, int]:
    """Twelve aircraft 8 km apart plus one 150 m from the last (closer than the two radars'
    relative error, ~140 m per axis): radar A and B snapshots with azimuth biases, and the
    index of the close pair's first aircraft (tracks ``k`` and ``k + 1`` in both radars)."""
    a, b = make_sites()
    rng = np.random.default_rng(5)
    k = np.arange(12)
    enu = np.column_stack([90e3 + 8e3 * (k % 4), 60e3 + 8e3 * (k // 4), np.full(12, 9000.0)])
    enu = np.vstack([enu, enu[-1] + np.array([150.0, 0.0, 0.0])])
    truth = a.enu_to_ecef(enu)
    sa = snapshot_of(a, truth, np.array([200.0, np.radians(0.4), 0.0]), rng, noise)
    sb = snapshot_of(b, truth, np.array([-150.0, np.radians(-0.3), 0.0]), rng, noise)
    return sa, sb, 11


def test_close_targets_are_refused_the_rest_decided() -> None:
    sa, sb, close = two_close_targets()
    dec = GmmCorrelator().decide(sa, sb, DecisionContext(time_s=0.0))
    chosen, _ = assign_unambiguous(dec.index_a, dec.index_b, dec.cost, dec.accepted, 6.0)
    got = set(zip(dec.index_a[chosen].tolist(), dec.index_b[chosen].tolist(), strict=True))
    assert got == {(i, i) for i in range(close)}  # every separated aircraft, nothing else
    # The close aircraft are candidates of each other's tracks (both hypotheses stay in view)
    # and the rows of their tracks are ambiguous or refused, not guessed.
    pairs = set(zip(dec.index_a.tolist(), dec.index_b.tolist(), strict=True))
    assert {(close, close), (close, close + 1), (close + 1, close), (close + 1, close + 1)} <= pairs
    rows = (dec.index_a >= close) & (dec.index_b >= close)
    assert not chosen[rows].any()
    assert np.all(dec.cost == pytest.approx(-2.0 * np.log(dec.statistic)))
    assert set(dec.reason[~dec.accepted].tolist()) <= {int(Reason.AMBIGUOUS)}


def test_paper_decision_guesses_on_close_targets() -> None:
    """Without the rivals (the paper's Eq. (27) alone, EM's sigma) the close pair is decided:
    the assignment sees one candidate per track and cannot refuse it."""
    sa, sb, close = two_close_targets()
    paper = replace(GmmParams(), report_rivals=False, sigma_floor_factor=0.0)
    dec = GmmCorrelator(paper).decide(sa, sb, DecisionContext(time_s=0.0))
    chosen, _ = assign_unambiguous(dec.index_a, dec.index_b, dec.cost, dec.accepted, 6.0)
    assert np.all(dec.accepted) and np.all(chosen)
    assert np.any(dec.index_a[chosen] >= close)


def test_degenerate_snapshot_gives_no_decisions() -> None:
    sa, sb, _ = two_close_targets()
    one = PredictedTracks(
        sb.track_id[:1],
        sb.position[:1],
        sb.velocity[:1],
        sb.pos_cov[:1],
        sb.vel_cov[:1],
        sb.site,
        sb.enu[:1],
        sb.enu_velocity[:1],
    )
    dec = GmmCorrelator().decide(sa, one, DecisionContext(time_s=0.0))
    assert len(dec) == 0


def test_kernel_width_bound_on_the_papers_scene() -> None:
    """At period 10 of the paper's scene (20 aircraft a few km apart) a kernel of beta = 2
    spreads lets the field chase the random errors; 20 km in metres gives fewer false pairs
    and no fewer correct ones."""
    rng = np.random.default_rng(11)
    scenes = [paper_scene(rng, at_period=10) for _ in range(10)]

    def count(params: GmmParams) -> tuple[int, int]:
        ok = bad = 0
        for pa, pb, ia, ib in scenes:
            r = gmm_associate(pa, pb, params)
            good = ia[r.index_a] == ib[r.index_b]
            ok, bad = ok + int(good.sum()), bad + int((~good).sum())
        return ok, bad

    ok_free, bad_free = count(GmmParams(min_kernel_width_m=0.0))
    ok, bad = count(GmmParams())
    assert ok >= ok_free
    assert bad < bad_free
