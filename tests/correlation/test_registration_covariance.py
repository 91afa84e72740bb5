"""The registration's cluster-robust covariance: rows are correlated when they share a radar (or
reference) track, also across radar pairs.

One radar track is paired with the tracks of every other radar that sees its aircraft and with
the aircraft's reference track, and its error enters every one of those rows alike.  The
covariance counts that (``service.correlation.registration._robust_covariance``): it agrees with
a plain double loop over the rows, reduces to the sandwich over track pairs where no track is in
two pairs, and on a scene with no gain and no time bias whose track errors persist over the
updates the terms come out consistent with zero within their sigma (the sandwich over track
pairs alone was optimistic there).
"""

from __future__ import annotations

import numpy as np

from service.correlation.base import PredictedTracks
from service.correlation.registration import (
    GAIN,
    N_TERMS,
    TIME,
    RegistrationMemory,
    RegistrationParams,
    solve_biases,
)
from service.geo import Site
from tests.reference_forms import registration_jacobian, registration_remove, robust_covariance_reference
from topofusion_lab.evaluation.correlation_scenario import make_sites, sample_references

#: Polar offsets of the three radars (m, rad, rad); no gain and no time bias.
OFFSETS = {
    "A": np.array([120.0, np.radians(0.10), np.radians(0.02)]),
    "B": np.array([-180.0, np.radians(-0.15), np.radians(-0.03)]),
    "C": np.array([250.0, np.radians(0.20), 0.0]),
}
#: Terms estimated whatever their significance (a gain held at zero says nothing of its sigma).
PRM = RegistrationParams(max_rows_per_update=1_000, gain_significance_sigma=0.0, outlier_chi2=1e12)


def _sites() -> dict[str, Site]:
    a, b = make_sites()
    return {"A": a, "B": b, "C": Site("C", 32.5, 119.0, 30.0)}


def _snapshot(
    site: Site | None, ids: list[str], pos: np.ndarray, vel: np.ndarray, var: float
) -> PredictedTracks:
    n = len(pos)
    cov = np.broadcast_to(np.eye(3) * var, (n, 3, 3)).copy()
    if site is None:
        return PredictedTracks(np.array(ids), pos, vel, cov, cov.copy(), None, pos, vel)
    return PredictedTracks(
        np.array(ids), pos, vel, cov, cov.copy(), site, site.ecef_to_enu(pos), vel @ site.rotation
    )


def _scene(
    seed: int, n: int, updates: int, track_m: float = 60.0, white_m: float = 20.0
) -> list[RegistrationMemory]:
    """Radars A, B, C over ``n`` aircraft (level flight, headings all round), every aircraft in
    the pairs A-B, A-C, B-C and every other one with a reference (10 m) in A, B and C.  Each
    radar track's error is a persistent part (``track_m``, drawn once: the same in every update
    and every pair of that track) plus white noise per update (``white_m``); the reported
    covariance is their sum."""
    rng = np.random.default_rng(seed)
    sites = _sites()
    truth = sample_references(rng, sites["A"], sites["B"], n)
    heading = rng.uniform(0.0, 2.0 * np.pi, n)
    speed = rng.uniform(150.0, 260.0, n)
    enu_v = np.stack([speed * np.sin(heading), speed * np.cos(heading), np.zeros(n)], axis=1)
    vel = enu_v @ sites["A"].rotation.T
    measured = {}
    for rid, site in sites.items():
        r, az, el = site.ecef_to_polar(truth)
        b = OFFSETS[rid]
        measured[rid] = site.polar_to_ecef(r + b[0], az + np.degrees(b[1]), el + np.degrees(b[2]))
    persistent = {rid: rng.normal(0.0, track_m, (n, 3)) for rid in sites}
    idx, ref = np.arange(n), np.arange(0, n, 2)
    mems = {(x, y): RegistrationMemory(sites[x], sites[y]) for x, y in (("A", "B"), ("A", "C"), ("B", "C"))}
    refs = {rid: RegistrationMemory(site, None) for rid, site in sites.items()}
    var = track_m**2 + white_m**2
    for t in range(updates):
        snaps = {
            rid: _snapshot(
                sites[rid],
                [f"{rid}-{i}" for i in range(n)],
                measured[rid] + persistent[rid] + rng.normal(0.0, white_m, (n, 3)),
                vel,
                var,
            )
            for rid in sites
        }
        reference = _snapshot(
            None, [f"R{i}" for i in range(n)], truth + rng.normal(0.0, 10.0, (n, 3)), vel, 100.0
        )
        for (x, y), m in mems.items():
            m.add(float(t), snaps[x], snaps[y], idx, idx, PRM)
        for rid, m in refs.items():
            m.add(float(t), snaps[rid], reference, ref, ref, PRM)
    return [*mems.values(), *refs.values()]


# -- a plain form of the solve's pieces ----------------------------------------------------


def _prior(prm: RegistrationParams, radars: int) -> np.ndarray:
    """The prior's information per term, radar after radar (the terms' order: TERMS)."""
    per_radar = [
        1 / prm.prior_range_m**2,
        1 / np.radians(prm.prior_azimuth_deg) ** 2,
        1 / np.radians(prm.prior_elevation_deg) ** 2,
        1 / prm.prior_range_gain_ppm**2,
        1 / prm.prior_time_bias_s**2,
    ]
    return np.tile(per_radar, radars)


def _plain_pieces(
    mems: list[RegistrationMemory], ids: tuple[str, ...], terms: np.ndarray, prm: RegistrationParams
) -> tuple[np.ndarray, list[tuple[str, ...]], list[tuple[str, ...]], np.ndarray, np.ndarray]:
    """Row by row: every row's score ``G^T W r`` in every column at the solution ``terms``, its
    two tracks and its track pair as cluster keys, the model covariance ``H^-1`` and the prior."""
    nt, n = N_TERMS, N_TERMS * len(ids)
    prior = _prior(prm, len(ids))
    h = np.diag(prior)
    scores: list[np.ndarray] = []
    tracks: list[tuple[str, ...]] = []
    pairs: list[tuple[str, ...]] = []
    for m in mems:
        ka = nt * ids.index(m.site_a.site_id)
        kb = None if m.site_b is None else nt * ids.index(m.site_b.site_id)
        for i in range(len(m)):
            w = np.linalg.inv(m.s[i])
            g = np.zeros((3, n))
            g[:, ka : ka + nt] = registration_jacobian(m.site_a, m.p_a[i], m.v[i])
            res = registration_remove(m.site_a, m.p_a[i], m.v[i], terms[ka // nt]) - m.p_b[i]
            if kb is not None and m.site_b is not None:
                g[:, kb : kb + nt] = -registration_jacobian(m.site_b, m.p_b[i], m.v[i])
                res = res + m.p_b[i] - registration_remove(m.site_b, m.p_b[i], m.v[i], terms[kb // nt])
            h += g.T @ w @ g
            scores.append(g.T @ w @ res)
            track_a, track_b = str(m.pair[i]).split("\x1f")
            site_b = "" if m.site_b is None else m.site_b.site_id
            tracks.append((f"{m.site_a.site_id}:{track_a}", f"{site_b}:{track_b}"))
            pairs.append((f"{m.site_a.site_id}:{track_a}/{site_b}:{track_b}",))
    return np.array(scores), tracks, pairs, np.linalg.inv(h), prior


def _eigenvalues(cov: np.ndarray) -> np.ndarray:
    """Eigenvalues of ``cov`` on the correlation scale (the terms' units differ by far)."""
    d = np.sqrt(np.diag(cov))
    return np.linalg.eigvalsh(cov / np.outer(d, d))


def test_robust_covariance_matches_the_plain_double_loop() -> None:
    """Three radars and a reference, 30 aircraft, 2 updates: the vectorised covariance is the
    plain form's, clusters by shared track (the reference's tracks shared by the radars)."""
    mems = _scene(11, 30, 2)
    sol = solve_biases(mems, 1.0, PRM)
    assert sol is not None and sol.terms is not None and sol.terms_covariance is not None
    assert sol.clusters == 3 * 30 + 3 * 15  # track pairs
    scores, tracks, pairs, cov, prior = _plain_pieces(mems, sol.radar_ids, sol.terms, PRM)
    plain = robust_covariance_reference(scores, tracks, cov, prior)
    assert np.all(_eigenvalues(plain) > 0)
    np.testing.assert_allclose(sol.terms_covariance, plain, rtol=1e-6, atol=0.0)
    # the sandwich over track pairs alone is not it: tracks shared across pairs add to the meat
    by_pair = robust_covariance_reference(scores, pairs, cov, prior)
    assert np.all(np.diag(plain) > 1.05 * np.diag(by_pair))


def test_a_meat_that_is_not_positive_loses_its_negative_part() -> None:
    """12 aircraft for 15 terms: the inclusion and exclusion leave the plain form a negative
    eigenvalue; the solve's covariance is that form with it set to zero (positive
    semi-definite, the rest as it was)."""
    mems = _scene(11, 12, 3)
    sol = solve_biases(mems, 2.0, PRM)
    assert sol is not None and sol.terms is not None and sol.terms_covariance is not None
    scores, tracks, _, cov, prior = _plain_pieces(mems, sol.radar_ids, sol.terms, PRM)
    plain = robust_covariance_reference(scores, tracks, cov, prior)
    assert _eigenvalues(plain).min() < 0
    assert _eigenvalues(sol.terms_covariance).min() > -1e-12
    d = np.sqrt(np.diag(plain))
    w, u = np.linalg.eigh(plain / np.outer(d, d))
    clipped = (u * np.clip(w, 0.0, None)) @ u.T * np.outer(d, d)
    np.testing.assert_allclose(sol.terms_covariance, clipped, rtol=1e-6, atol=0.0)


def test_without_tracks_in_two_pairs_it_is_the_sandwich_over_track_pairs() -> None:
    """One radar pair: no track is in two track pairs, and the covariance is the one-way
    sandwich over track pairs."""
    mems = _scene(12, 15, 3)[:1]
    sol = solve_biases(mems, 2.0, PRM)
    assert sol is not None and sol.terms is not None and sol.terms_covariance is not None
    scores, tracks, pairs, cov, prior = _plain_pieces(mems, sol.radar_ids, sol.terms, PRM)
    by_pair = robust_covariance_reference(scores, pairs, cov, prior)
    np.testing.assert_allclose(sol.terms_covariance, by_pair, rtol=1e-6, atol=0.0)
    np.testing.assert_allclose(robust_covariance_reference(scores, tracks, cov, prior), by_pair, rtol=1e-9)


def _true_covariance(
    mems: list[RegistrationMemory],
    ids: tuple[str, ...],
    prm: RegistrationParams,
    track_m: float,
    white_m: float,
) -> np.ndarray:
    """The terms' actual covariance on a :func:`_scene` (its errors' structure known): ``H^-1
    (diag(prior) + sum_i sum_j G_i^T W_i Cov(n_i, n_j) W_j G_j) H^-1`` with ``n_i`` a row's
    error, the persistent and white errors of its A track less those of its B track (the
    white ones of one update, the reference's white ones of one update)."""
    nt, n = N_TERMS, N_TERMS * len(ids)
    prior = _prior(prm, len(ids))
    h = np.diag(prior)
    gtw, key_a, key_b, time = [], [], [], []
    for m in mems:
        ka = nt * ids.index(m.site_a.site_id)
        for i in range(len(m)):
            g = np.zeros((3, n))
            g[:, ka : ka + nt] = registration_jacobian(m.site_a, m.p_a[i], m.v[i])
            if m.site_b is not None:
                kb = nt * ids.index(m.site_b.site_id)
                g[:, kb : kb + nt] = -registration_jacobian(m.site_b, m.p_b[i], m.v[i])
            w = np.linalg.inv(m.s[i])
            h += g.T @ w @ g
            gtw.append(g.T @ w)
            track_a, track_b = str(m.pair[i]).split("\x1f")
            key_a.append(f"{m.site_a.site_id}:{track_a}")
            key_b.append(f"{'' if m.site_b is None else m.site_b.site_id}:{track_b}")
            time.append(m.time[i])
    t = np.array(time)
    cov_n = np.zeros((t.size, t.size))
    for ki, si in ((np.array(key_a), 1.0), (np.array(key_b), -1.0)):
        for kj, sj in ((np.array(key_a), 1.0), (np.array(key_b), -1.0)):
            ref = np.char.startswith(ki, ":")[:, None]  # a reference track: white 10 m only
            persistent = np.where(ref, 0.0, track_m**2)
            white = np.where(ref, 100.0, white_m**2) * (t[:, None] == t[None, :])
            cov_n += si * sj * (ki[:, None] == kj[None, :]) * (persistent + white)
    m_ = np.array(gtw)  # (rows, n, 3)
    meat = np.einsum("ink,ij,jmk->nm", m_, cov_n, m_, optimize=True)
    c = np.linalg.inv(h)
    return np.asarray(c @ (np.diag(prior) + meat) @ c)


def test_no_gain_and_no_time_bias_come_out_consistent_with_zero() -> None:
    """20 scenes with no gain and no time bias, 40 aircraft, track errors persisting over the
    updates and shared by every pair of their track: the reported variance of every term is on
    average within 15 % of the actual one (:func:`_true_covariance`; the sandwich over track
    pairs alone, which counts the rows of one track in several radar pairs as independent,
    reported 0.5-0.65 of it here), and the gains and time biases come out within 2 sigma of zero."""
    ratio, z = [], []
    for seed in range(20):
        mems = _scene(100 + seed, 40, 4)
        sol = solve_biases(mems, 3.0, PRM)
        assert sol is not None and sol.terms is not None and sol.terms_covariance is not None
        actual = np.diag(_true_covariance(mems, sol.radar_ids, PRM, 60.0, 20.0))
        ratio.append(np.diag(sol.terms_covariance).reshape(-1, N_TERMS) / actual.reshape(-1, N_TERMS))
        truth = np.array([[*OFFSETS[rid], 0.0, 0.0] for rid in sol.radar_ids])
        z.append((sol.terms - truth) / sol.term_std())
    mean_ratio = np.mean(ratio, axis=(0, 1))
    assert np.all((mean_ratio > 0.85) & (mean_ratio < 1.15)), mean_ratio
    new = np.array(z)[:, :, [GAIN, TIME]]
    assert np.mean(np.abs(new) <= 2.0) >= 0.9, np.abs(new).max()
