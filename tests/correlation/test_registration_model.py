"""The whole registration model: range offset and gain, angle offsets and time-stamp bias.

The solve recovers every term where the geometry determines it (radar-radar pairs and an ADS-B
style reference), leaves unobservable terms at the prior's zero with the prior's sigma, agrees
with a plain per-row form of the same least squares, compensates as the plain per-track form
does, and takes a state kept by the three-term version.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from service.correlation.base import PredictedTracks
from service.correlation.registration import (
    GAIN,
    N_TERMS,
    PPM,
    TIME,
    RegistrationMemory,
    RegistrationParams,
    compensate,
    model_jacobian,
    remove_bias,
    solution_from_state,
    solve_biases,
    to_estimates,
)
from service.geo import Site
from tests.reference_forms import registration_jacobian, registration_remove
from topofusion_lab.evaluation.correlation_scenario import make_sites, sample_references

#: Five terms per radar (m, rad, rad, ppm, s), the study's levels.
TERMS = {
    "A": np.array([120.0, np.radians(0.10), np.radians(0.02), 800.0, 0.6]),
    "B": np.array([-180.0, np.radians(-0.15), np.radians(-0.03), -600.0, -0.4]),
    "C": np.array([250.0, np.radians(0.20), 0.0, 400.0, 1.0]),
}


def _velocities(rng: np.random.Generator, site: Site, n: int) -> np.ndarray:
    """ECEF velocities of level flight, headings all round, 150-260 m/s."""
    heading = rng.uniform(0.0, 2.0 * np.pi, n)
    speed = rng.uniform(150.0, 260.0, n)
    enu = np.stack([speed * np.sin(heading), speed * np.cos(heading), np.zeros(n)], axis=1)
    return np.asarray(enu @ site.rotation.T)


def _observed(
    site: Site,
    truth: np.ndarray,
    vel: np.ndarray,
    terms: np.ndarray,
    rng: np.random.Generator,
    noise: float,
) -> PredictedTracks:
    """What a radar with ``terms`` reports at (its) time ``t`` of targets truly at ``truth``
    then: the polar model applied to where they were at ``t - tau``, plus white noise."""
    r, az, el = site.ecef_to_polar(truth - terms[TIME] * vel)
    pos = site.polar_to_ecef(
        r * (1.0 + terms[GAIN] * PPM) + terms[0], az + np.degrees(terms[1]), el + np.degrees(terms[2])
    )
    pos = pos + rng.normal(0.0, noise, pos.shape)
    n = len(pos)
    cov = np.broadcast_to(np.eye(3) * max(noise, 1.0) ** 2, (n, 3, 3)).copy()
    ids = np.array([f"{site.site_id}{i}" for i in range(n)])
    return PredictedTracks(
        ids, pos, vel.copy(), cov, cov.copy(), site, site.ecef_to_enu(pos), vel @ site.rotation
    )


def _reference(truth: np.ndarray, vel: np.ndarray) -> PredictedTracks:
    """A bias-free reference (ADS-B) of the same aircraft, 10 m errors."""
    n = len(truth)
    cov = np.broadcast_to(np.eye(3) * 100.0, (n, 3, 3)).copy()
    return PredictedTracks(
        np.array([f"R{i}" for i in range(n)]), truth, vel, cov, cov.copy(), None, truth, vel
    )


def _network(
    seed: int,
    n: int,
    noise: float,
    terms: dict[str, np.ndarray],
    reference_every: int | None,
    updates: int = 1,
) -> list[RegistrationMemory]:
    """Memories of the radar pairs A-B, A-C, B-C (and A, B with a reference on every
    ``reference_every``-th aircraft), ``updates`` draws of the noise each."""
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    c = Site("C", 32.5, 119.0, 30.0)
    sites = {"A": a, "B": b, "C": c}
    truth = sample_references(rng, a, b, n)
    vel = _velocities(rng, a, n)
    prm = RegistrationParams(max_rows_per_update=n)
    idx = np.arange(n)
    links = [("A", "B"), ("A", "C"), ("B", "C")]
    mems = {k: RegistrationMemory(sites[k[0]], sites[k[1]]) for k in links}
    refs = {k: RegistrationMemory(sites[k], None) for k in ("A", "B")} if reference_every else {}
    for t in range(updates):
        snaps = {k: _observed(s, truth, vel, terms[k], rng, noise) for k, s in sites.items()}
        for (x, y), m in mems.items():
            m.add(float(t), snaps[x], snaps[y], idx, idx, prm)
        for k, m in refs.items():
            pick = idx[:: reference_every or 1]
            m.add(float(t), snaps[k], _reference(truth, vel), pick, pick, prm)
    return [*mems.values(), *refs.values()]


def test_solve_recovers_gain_and_time_bias_with_a_reference() -> None:
    """Without noise every term of every radar comes back (the reference fixes the clock)."""
    mems = _network(0, 300, 0.0, TERMS, reference_every=3)
    sol = solve_biases(mems, 0.0, RegistrationParams(max_rows_per_update=300))
    assert sol is not None and sol.terms is not None
    for k, rid in enumerate(sol.radar_ids):
        np.testing.assert_allclose(sol.terms[k], TERMS[rid], rtol=1e-5, atol=1e-7)
    assert sol.relative_covariance is None  # a reference reaches every radar: nothing to condition


def test_noisy_estimates_lie_within_their_sigma() -> None:
    """With 100 m noise, 10 updates of 200 aircraft: every term within 4 sigma, and the
    gains and time biases within the study's goals (max(25 %, 100 ppm), max(20 %, 0.1 s))."""
    mems = _network(1, 200, 100.0, TERMS, reference_every=2, updates=10)
    sol = solve_biases(mems, 9.0)
    assert sol is not None and sol.terms is not None
    std = sol.term_std()
    for k, rid in enumerate(sol.radar_ids):
        err = sol.terms[k] - TERMS[rid]
        assert np.all(np.abs(err) <= 4.0 * std[k]), (rid, err / std[k])
        assert abs(err[GAIN]) <= max(0.25 * abs(TERMS[rid][GAIN]), 100.0)
        assert abs(err[TIME]) <= max(0.2 * abs(TERMS[rid][TIME]), 0.1)


def test_time_bias_common_to_all_radars_is_not_observable() -> None:
    """Radar pairs only: differences of time biases come back, their common part does not --
    its estimate is the prior's zero, its sigma the prior's, and the relative covariance that
    compensation uses has none of it."""
    mems = _network(2, 300, 0.0, TERMS, reference_every=None)
    prm = RegistrationParams(max_rows_per_update=300)
    sol = solve_biases(mems, 0.0, prm)
    assert sol is not None and sol.terms is not None and sol.relative_covariance is not None
    tau = sol.terms[:, TIME]
    truth = np.array([TERMS[rid][TIME] for rid in sol.radar_ids])
    np.testing.assert_allclose(tau - tau.mean(), truth - truth.mean(), atol=1e-6)
    assert abs(tau.mean()) < 1e-6
    # the other terms do not depend on the clock
    for k, rid in enumerate(sol.radar_ids):
        np.testing.assert_allclose(sol.terms[k, :TIME], TERMS[rid][:TIME], rtol=1e-5, atol=1e-7)
    e = np.zeros(N_TERMS * 3)
    e[N_TERMS * np.arange(3) + TIME] = 1.0
    _, cov = sol.full
    assert e @ cov @ e == pytest.approx(3 * prm.prior_time_bias_s**2, rel=1e-6)
    assert abs(e @ sol.relative_covariance @ e) < 1e-9
    sigma = sol.term_std()[:, TIME]
    np.testing.assert_allclose(sigma, prm.prior_time_bias_s / np.sqrt(3.0), rtol=1e-4)


def test_terms_the_geometry_does_not_see_shrink_to_zero() -> None:
    """Targets that do not move say nothing of time biases: the estimates stay at zero with
    the prior's sigma; switched-off terms are zero, not estimated (null in /biases)."""
    rng = np.random.default_rng(3)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 200)
    still = np.zeros_like(truth)
    terms = {k: v.copy() for k, v in TERMS.items()}
    mem = RegistrationMemory(a, b)
    idx = np.arange(200)
    prm = RegistrationParams(max_rows_per_update=200)
    for t in range(3):
        mem.add(
            float(t),
            _observed(a, truth, still, terms["A"], rng, 30.0),
            _observed(b, truth, still, terms["B"], rng, 30.0),
            idx,
            idx,
            prm,
        )
    sol = solve_biases([mem], 2.0, prm)
    assert sol is not None and sol.terms is not None
    np.testing.assert_array_equal(sol.terms[:, TIME], 0.0)
    np.testing.assert_allclose(sol.term_std()[:, TIME], prm.prior_time_bias_s, rtol=1e-9)
    off = dataclasses.replace(prm, estimate_range_gain=False, estimate_time_bias=False)
    sol3 = solve_biases([mem], 2.0, off)
    assert sol3 is not None and sol3.terms is not None
    np.testing.assert_array_equal(sol3.terms[:, GAIN:], 0.0)
    for est in to_estimates(sol3, 2.0):
        assert est.range_gain_ppm is None and est.time_bias_s is None and est.time_bias_sigma_s is None
    for est in to_estimates(sol, 2.0):
        assert est.range_gain_ppm is not None and est.time_bias_sigma_s is not None


# -- plain reference forms ----------------------------------------------------------------


def _plain_solve(mem: RegistrationMemory, prm: RegistrationParams, iterations: int) -> np.ndarray:
    """Weighted least squares of one radar pair, one row at a time: the first iteration the
    linear model's solution, later ones Gauss-Newton steps on the exact residual."""
    a, b = mem.site_a, mem.site_b
    assert b is not None
    prior = np.tile(
        [
            1 / prm.prior_range_m**2,
            1 / np.radians(prm.prior_azimuth_deg) ** 2,
            1 / np.radians(prm.prior_elevation_deg) ** 2,
            1 / prm.prior_range_gain_ppm**2,
            1 / prm.prior_time_bias_s**2,
        ],
        2,
    )
    rows = []
    for i in range(len(mem)):
        g = np.hstack(
            [registration_jacobian(a, mem.p_a[i], mem.v[i]), -registration_jacobian(b, mem.p_b[i], mem.v[i])]
        )
        rows.append((g, np.linalg.inv(mem.s[i]), mem.p_a[i], mem.p_b[i], mem.v[i]))
    h = np.diag(prior)
    for g, w, *_ in rows:
        h += g.T @ w @ g
    bias = np.zeros(2 * N_TERMS)
    for _ in range(iterations):
        grad = -prior * bias
        for g, w, pa, pb, v in rows:
            res = registration_remove(a, pa, v, bias[:N_TERMS]) - registration_remove(
                b, pb, v, bias[N_TERMS:]
            )
            grad += g.T @ w @ res
        bias = bias + np.linalg.solve(h, grad)
    return bias.reshape(2, N_TERMS)


def test_vectorised_solve_matches_the_plain_form() -> None:
    rng = np.random.default_rng(4)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 60)
    vel = _velocities(rng, a, 60)
    prm = RegistrationParams(outlier_chi2=1e12)
    mem = RegistrationMemory(a, b)
    idx = np.arange(60)
    for t in (0.0, 5.0, 10.0):
        mem.add(
            t,
            _observed(a, truth, vel, TERMS["A"], rng, 50.0),
            _observed(b, truth, vel, TERMS["B"], rng, 50.0),
            idx,
            idx,
            prm,
        )
    for i in range(0, len(mem), 17):
        np.testing.assert_allclose(
            model_jacobian(a, mem.p_a[i : i + 1], mem.v[i : i + 1])[0],
            registration_jacobian(a, mem.p_a[i], mem.v[i]),
            rtol=1e-8,
            atol=1e-6,
        )
    linear = solve_biases([mem], 10.0, dataclasses.replace(prm, max_iterations=1))
    assert linear is not None and linear.terms is not None
    np.testing.assert_allclose(linear.terms, _plain_solve(mem, prm, 1), rtol=1e-6, atol=1e-9)
    sol = solve_biases([mem], 10.0, prm)
    assert sol is not None and sol.terms is not None and sol.model_covariance is not None
    fixed = _plain_solve(mem, prm, 10)
    assert np.all(np.abs(sol.terms - fixed) <= 0.02 * sol.term_std() + 1e-9)


def test_compensation_matches_the_plain_per_track_form() -> None:
    rng = np.random.default_rng(5)
    site, other = make_sites()
    truth = sample_references(rng, site, other, 40)
    vel = _velocities(rng, site, 40)
    snap = _observed(site, truth, vel, TERMS["A"], rng, 0.0)
    half = rng.normal(size=(N_TERMS, N_TERMS)) * np.array([10.0, 1e-4, 1e-4, 50.0, 0.05])
    bias_cov = half @ half.T
    out, extra = compensate(snap, TERMS["A"], bias_cov)
    dth, scale = -TERMS["A"][1], 1.0 + TERMS["A"][GAIN] * PPM  # turned back by the azimuth offset
    turn = np.array([[np.cos(dth), np.sin(dth), 0.0], [-np.sin(dth), np.cos(dth), 0.0], [0.0, 0.0, 1.0]])
    for k in range(len(snap)):
        v_enu = turn @ snap.enu_velocity[k] / scale
        v = site.rotation @ v_enu
        np.testing.assert_allclose(out.velocity[k], v, atol=1e-9)
        np.testing.assert_allclose(
            out.position[k], registration_remove(site, snap.position[k], v, TERMS["A"]), atol=1e-6
        )
        g = registration_jacobian(site, snap.position[k], snap.velocity[k])
        np.testing.assert_allclose(extra[k], g @ bias_cov @ g.T, rtol=1e-8, atol=1e-8)
    # without noise, compensation puts the tracks on the truth (up to the speed change of the
    # velocity estimate's own bias, second order: well under a metre here)
    assert np.abs(out.position - truth).max() < 1.0
    np.testing.assert_allclose(
        remove_bias(site, snap.position, TERMS["A"], out.velocity), out.position, atol=1e-6
    )


# -- a state kept by the three-term version ---------------------------------------------------


def test_a_three_term_solution_and_memory_load_as_the_whole_model() -> None:
    rng = np.random.default_rng(6)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 50)
    vel = _velocities(rng, a, 50)
    mem = RegistrationMemory(a, b)
    idx = np.arange(50)
    mem.add(
        0.0,
        _observed(a, truth, vel, TERMS["A"], rng, 30.0),
        _observed(b, truth, vel, TERMS["B"], rng, 30.0),
        idx,
        idx,
        RegistrationParams(),
    )
    # the previous version's solution_state: three terms per radar, no gain, no time bias
    old = {
        "radar_ids": ["A", "B"],
        "bias": np.array([[100.0, 1e-3, 2e-4], [-50.0, -1e-3, 0.0]]),
        "covariance": np.eye(6) * 4.0,
        "pairs_used": {"A": 50, "B": 50},
        "model_covariance": np.eye(6),
        "clusters": 50,
    }
    sol = solution_from_state(old)
    assert sol.terms is not None and sol.terms.shape == (2, N_TERMS)
    np.testing.assert_array_equal(sol.terms[:, :3], old["bias"])
    np.testing.assert_array_equal(sol.terms[:, GAIN:], 0.0)
    terms, cov = sol.of("A")
    assert terms.shape == (N_TERMS,) and cov.shape == (N_TERMS, N_TERMS) and cov[TIME, TIME] == 0.0
    [ea, _] = to_estimates(sol, 1.0)
    assert ea.range_bias_m == 100.0 and ea.range_gain_ppm is None and ea.time_bias_s is None
    # it warm-starts a solve of the whole model
    assert solve_biases([mem], 0.0, initial=sol) is not None
    # the previous version's memory export had no velocity column: rows load with zero velocity
    state = {k: v for k, v in mem.export().items() if k != "v"}
    back = RegistrationMemory.restored(a, b, state)
    assert len(back) == len(mem) and not back.v.any()
    np.testing.assert_array_equal(back.p_a, mem.p_a)
    with pytest.raises(ValueError):
        solution_from_state({**old, "terms": np.zeros((2, 3))})


def test_a_state_file_of_the_three_term_version_restores(tmp_path: Path) -> None:
    """A whole state file as the previous version wrote it (no terms, no velocity column): the
    engine takes it, serves its biases with null gain and time bias, and goes on solving."""
    from service.engine import Engine, EngineConfig
    from service.state import StateKeeper
    from service.state.fileformat import decode, encode
    from tests.scenario_helpers import scenario_messages

    stream = scenario_messages("two-radar", duration_s=90.0)
    cut = len(stream) * 2 // 3
    first = Engine(EngineConfig())
    keeper = StateKeeper(tmp_path, "fusion", "1/1")
    keeper.restore(first)
    for key, payload in stream[:cut]:
        first.ingest(key, payload, receive_time_s=0.0)
    keeper.save(first)
    path = tmp_path / "state.bin"
    header, tree = decode(path.read_bytes(), "fusion", "1/1")
    joint = tree["correlation"]["joint"]
    assert joint is not None and "terms" in joint
    for name in ("terms", "terms_covariance", "relative_covariance"):
        joint.pop(name)
    for memory in tree["correlation"]["memories"]:
        memory["rows"].pop("v")
    path.write_bytes(encode(header, tree))
    engine = Engine(EngineConfig())
    StateKeeper(tmp_path, "fusion", "1/1").restore(engine)
    biases = engine.snapshot().biases()
    assert {b["radar_id"] for b in biases} == {"A", "B"}
    assert all(b["range_gain_ppm"] is None and b["time_bias_s"] is None for b in biases)
    for key, payload in stream[cut:]:
        engine.ingest(key, payload, receive_time_s=0.0)
    engine.flush()
    biases = engine.snapshot().biases()
    assert all(b["range_gain_ppm"] is not None and b["time_bias_sigma_s"] is not None for b in biases)


def test_simulated_radar_applies_gain_and_time_bias() -> None:
    """The simulator's gain scales each plot's range, the time bias moves its stamp (and its
    batch's); zero changes nothing."""
    from topofusion_lab.scenarios.catalog import get_scenario
    from topofusion_lab.scenarios.simulator import generate

    base = dataclasses.replace(get_scenario("two-radar"), duration_s=8.0)
    biased = dataclasses.replace(
        base,
        radars=(dataclasses.replace(base.radars[0], range_gain_ppm=1000.0, time_bias_s=0.5), base.radars[1]),
    )
    zero = dataclasses.replace(
        base,
        radars=(dataclasses.replace(base.radars[0], range_gain_ppm=0.0, time_bias_s=0.0), base.radars[1]),
    )
    plain = [m.body for m in generate(base, 3) if m.kind == "plots" and m.radar_id == "A"]
    assert plain == [m.body for m in generate(zero, 3) if m.kind == "plots" and m.radar_id == "A"]
    moved = [m.body for m in generate(biased, 3) if m.kind == "plots" and m.radar_id == "A"]
    for p, q in zip(plain, moved, strict=True):
        assert q["time_s"] == pytest.approx(p["time_s"] + 0.5, abs=1e-6)
        np.testing.assert_allclose(q["plots"]["time_s"], np.add(p["plots"]["time_s"], 0.5), atol=2e-4)
        r_true = np.asarray(p["plots"]["range_m"]) - base.radars[0].range_bias_m
        r_moved = np.asarray(q["plots"]["range_m"]) - base.radars[0].range_bias_m
        # both carry the same noise draw (n ~ 200 m), which the gain scales too: eps n < 1 m
        np.testing.assert_allclose(r_moved, r_true * (1.0 + 1000.0 * PPM), atol=1.0)


def test_a_gain_the_data_do_not_show_is_held_at_zero() -> None:
    """Two radars, no reference, 40 aircraft: gain and range offset hardly separate.  Without a
    gain in the data the gains are held at zero (reported 0 with their sigma) and the range
    offsets are as precise as the three-term model's; a real gain of several sigma stays."""
    rng = np.random.default_rng(8)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 40)
    vel = _velocities(rng, a, 40)
    idx = np.arange(40)
    prm = RegistrationParams()
    for gains, held in (((0.0, 0.0), True), ((3000.0, -3000.0), False)):
        mem = RegistrationMemory(a, b)
        for t in range(10):
            ta, tb = TERMS["A"].copy(), TERMS["B"].copy()
            ta[GAIN], tb[GAIN] = gains
            mem.add(
                float(t),
                _observed(a, truth, vel, ta, rng, 150.0),
                _observed(b, truth, vel, tb, rng, 150.0),
                idx,
                idx,
                prm,
            )
        sol = solve_biases([mem], 9.0, prm)
        three = solve_biases([mem], 9.0, dataclasses.replace(prm, estimate_range_gain=False))
        assert sol is not None and sol.terms is not None and three is not None
        std = sol.term_std()
        if held:
            np.testing.assert_array_equal(sol.terms[:, GAIN], 0.0)
            assert np.all(std[:, GAIN] > 0.0)
            np.testing.assert_allclose(sol.std()[:, 0], three.std()[:, 0], rtol=1e-6)
            assert all(e.range_gain_ppm == 0.0 and e.range_gain_sigma_ppm for e in to_estimates(sol, 9.0))
        else:
            assert np.all(np.abs(sol.terms[:, GAIN]) > prm.gain_significance_sigma * std[:, GAIN])
            assert np.all(np.abs(sol.terms[:, GAIN] - np.array(gains)) <= 4.0 * std[:, GAIN])


def test_reference_rows_take_the_reference_velocity_not_the_tracks() -> None:
    """A radar track's velocity error follows its position error (a filter pulls both towards
    each plot).  A reference row's time column made of the track's velocity would correlate
    with the row's noise and bias every radar's time bias alike (-0.04 s in the study); the
    reference's own velocity does not: with no terms in the data the time biases come out
    within 2 sigma of zero."""
    rng = np.random.default_rng(11)
    a, b = make_sites()
    n = 200
    truth = sample_references(rng, a, b, n)
    vel = _velocities(rng, a, n)
    idx = np.arange(n)
    prm = RegistrationParams(max_rows_per_update=n)
    zero = np.zeros(N_TERMS)
    #: velocity error per metre of position error (1/s): a track's pull towards its plots
    pull = 0.3
    mems = {k: RegistrationMemory(s, None) for k, s in (("A", a), ("B", b))}
    sites = {"A": a, "B": b}
    for t in range(10):
        for k, m in mems.items():
            obs = _observed(sites[k], truth, vel, zero, rng, 100.0)
            v_track = vel + pull * (obs.position - truth)
            track = dataclasses.replace(obs, velocity=v_track, enu_velocity=v_track @ sites[k].rotation)
            rows = m.add(float(t), track, _reference(truth, vel), idx, idx, prm)
            assert rows.v is not None
            np.testing.assert_array_equal(rows.v, vel)  # the reference's, not the track's
    sol = solve_biases(list(mems.values()), 9.0, prm)
    assert sol is not None and sol.terms is not None
    tau, sigma = sol.terms[:, TIME], sol.term_std()[:, TIME]
    assert np.all(np.abs(tau) <= 2.0 * sigma), tau / sigma
