"""Single decisions of svd-topology and basic-topology on the paper's scenario and degenerate inputs."""

from __future__ import annotations

import warnings

import numpy as np

from service.correlation.base import NO_DECISION_REASONS, Reason
from service.correlation.basic_topology import BasicTopologyParams, basic_match, search_grid
from service.correlation.svd_topology import SvdTopologyParams, svd_match
from topofusion_lab.evaluation.correlation_scenario import Biases, make_sites, single_match_batch
from topofusion_lab.evaluation.correlation_single import Setting, fig2_false_vs_spacing


def _batch(n: int, trials: int = 300, seed: int = 0, pd: float = 1.0, bias_deg: float = 0.1):
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    ba = Biases.random_sign(rng, trials, 1000 * bias_deg, bias_deg)
    bb = Biases.random_sign(rng, trials, 1000 * bias_deg, bias_deg)
    return single_match_batch(rng, a, b, n, trials, ba, bb, pd_neighbour=pd)[0]


def test_true_pairs_accepted() -> None:
    m = _batch(6)
    r = svd_match(m.pa, m.ca, m.ma, m.pb, m.cb, m.mb, m.m0)
    assert r.accepted.mean() > 0.9
    ok = r.accepted
    assert np.all(r.rotation_weight[ok] >= 0.92)
    assert np.all(np.isfinite(r.statistic[ok]))


def test_large_bias_still_matched() -> None:
    m = _batch(6, bias_deg=2.0, seed=3)
    r = svd_match(m.pa, m.ca, m.ma, m.pb, m.cb, m.mb, m.m0)
    assert r.accepted.mean() > 0.85


def test_unequal_sequences_handled() -> None:
    m = _batch(8, pd=0.8, seed=4)
    r = svd_match(m.pa, m.ca, m.ma, m.pb, m.cb, m.mb, m.m0)
    rb = basic_match(m.pa, m.ca, m.ma, m.pb, m.cb, m.mb, m.m0)
    assert r.accepted.mean() > 0.85
    assert rb.accepted.mean() < r.accepted.mean() - 0.3
    assert np.any(rb.reason == Reason.UNEQUAL_LENGTH)


def test_wrong_reference_rejected() -> None:
    m = _batch(6, seed=5)
    perm = np.roll(np.arange(len(m.pa)), 1)  # B's sequences of other targets
    r = svd_match(m.pa, m.ca, m.ma, m.pb[perm], m.cb[perm], m.mb[perm], m.m0)
    assert r.accepted.mean() < 0.02


def test_degenerate_inputs_give_no_decision() -> None:
    m = _batch(4, trials=6, seed=6)
    pa, pb = m.pa.copy(), m.pb.copy()
    ca, cb = m.ca.copy(), m.cb.copy()
    ma, mb = m.ma.copy(), m.mb.copy()
    # 0: collinear neighbours (and their images): all on one line through the reference.
    for k in range(1, 5):
        pa[0, k] = pa[0, 0] + k * np.array([1000.0, 0.0, 0.0])
        pb[0, k] = pb[0, 0] + k * np.array([1000.0, 0.0, 0.0])
    # 1: only 1 neighbour in each sequence; 2: coincident neighbours.
    ma[1, 2:] = mb[1, 2:] = False
    pa[2, 1:] = pa[2, 0]
    pb[2, 1:] = pb[2, 0]
    # 3: NaN-free but singular covariances.
    ca[3] = 0.0
    cb[3] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = svd_match(pa, ca, ma, pb, cb, mb, m.m0)
        rf = svd_match(pa, ca, ma, pb, cb, mb, m.m0, SvdTopologyParams(rotation_model="full"))
        rb = basic_match(pa, ca, ma, pb, cb, mb, m.m0)
    for res in (r, rf):
        for p in (1, 2, 3):
            assert res.reason[p] in NO_DECISION_REASONS, (p, res.reason[p])
            assert not res.accepted[p]
    assert rf.reason[0] in NO_DECISION_REASONS  # collinear: 3-D rotation undetermined
    assert not rb.accepted[3] and rb.reason[3] in NO_DECISION_REASONS


def test_two_neighbours_yaw_decides_full_does_not() -> None:
    m = _batch(2, seed=7)
    r = svd_match(m.pa, m.ca, m.ma, m.pb, m.cb, m.mb, m.m0)
    rf = svd_match(m.pa, m.ca, m.ma, m.pb, m.cb, m.mb, m.m0, SvdTopologyParams(rotation_model="full"))
    assert r.accepted.mean() > 0.8
    assert np.all(rf.reason == Reason.TOO_FEW_NEIGHBOURS)


def test_false_rate_low_at_all_spacings() -> None:
    f2 = fig2_false_vs_spacing(300, 8, Setting(), (100.0, 1000.0, 2000.0))
    assert max(f2["svd-topology"]["false"]) <= 0.05
    assert f2["svd-topology"]["correct"][-1] > 0.4


def test_basic_grid() -> None:
    az, rr = search_grid(BasicTopologyParams(max_azimuth_bias_deg=1.0, max_range_bias_m=100.0))
    np.testing.assert_allclose(az, [-1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(rr, [-100.0, -50.0, 0.0, 50.0, 100.0])
