"""The two-model filter (:mod:`service.tracking.imm`): its vectorised cycle against the plain
textbook form, the one-model case against the Kalman filter, and what it is for in the
tracker: a turn held, straight legs tighter than with one model."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.geo import enu_to_polar
from service.tracking import imm, kalman, make_tracker
from service.tracking.base import PlotColumns
from service.tracking.params import FilterParams, ManagerParams, TrackerParams
from tests.tracking_reference_forms import imm_cycle_reference
from topofusion_lab.evaluation.initiation_monostatic import SITE

MODELS = imm.Models((1.0, 100.0), (120.0, 30.0))


def _random_states(rng: np.random.Generator, k: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    x = rng.normal(size=(k, m, 6)) * np.array([500.0] * 3 + [30.0] * 3) + np.array(
        [5e4, 3e4, 9e3, 200, -50, 0]
    )
    a = rng.normal(size=(k, m, 6, 6))
    P = a @ np.swapaxes(a, -1, -2) * 50.0 + np.eye(6) * np.array([1e4] * 3 + [100.0] * 3)
    return x, P


def test_transition_is_the_chain_exponential() -> None:
    from scipy.linalg import expm

    dt = np.array([0.0, 4.0, 12.0, 1e5])
    p = MODELS.transition(dt)
    gen = np.array([[-1 / 120.0, 1 / 120.0], [1 / 30.0, -1 / 30.0]])
    for k, d in enumerate(dt):
        np.testing.assert_allclose(p[k], expm(gen * d), atol=1e-12)
    np.testing.assert_allclose(p.sum(axis=2), 1.0)
    np.testing.assert_allclose(p[-1, 0], MODELS.stationary)  # long gaps forget the model
    np.testing.assert_allclose(MODELS.stationary, [0.8, 0.2])


def test_vectorised_cycle_matches_the_plain_form() -> None:
    rng = np.random.default_rng(3)
    k = 40
    xm, pm = _random_states(rng, k, 2)
    mu = rng.dirichlet([2.0, 2.0], size=k)
    dt = rng.uniform(-1.0, 12.0, size=k)  # (a plot older than the state too)
    z = xm[:, 0, :3] + rng.normal(size=(k, 3)) * 300.0
    b = rng.normal(size=(k, 3, 3))
    R = b @ np.swapaxes(b, -1, -2) * 100.0 + np.eye(3) * 4e4
    xp, pp, cw = imm.predict(xm, pm, mu, dt, MODELS)
    y, S = kalman.innovation(*imm.combine(cw, xp, pp), z, R)
    x, P, xm1, pm1, mu1 = imm.update(xp, pp, cw, z, R)
    rx, rp, rmu, rd2 = imm_cycle_reference(xm, pm, mu, dt, z, R, MODELS.psd, MODELS.sojourn_s)  # type: ignore[arg-type]
    np.testing.assert_allclose(kalman.mahalanobis2(y, S), rd2, rtol=1e-7)
    np.testing.assert_allclose(mu1, rmu, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(x, rx, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(P, rp, rtol=1e-7, atol=1e-6)
    assert xm1.shape == (k, 2, 6) and pm1.shape == (k, 2, 6, 6)


def test_one_model_is_the_kalman_filter_number_for_number() -> None:
    rng = np.random.default_rng(4)
    one = imm.Models((25.0,), (1.0,))
    xm, pm = _random_states(rng, 30, 1)
    dt = rng.uniform(0.0, 8.0, size=30)
    z = xm[:, 0, :3] + rng.normal(size=(30, 3)) * 200.0
    R = np.broadcast_to(np.eye(3) * 4e4, (30, 3, 3))
    xp, pp, cw = imm.predict(xm, pm, np.ones((30, 1)), dt, one)
    kx, kp = kalman.predict(xm[:, 0], pm[:, 0], dt, 25.0)
    assert np.array_equal(xp[:, 0], kx) and np.array_equal(pp[:, 0], kp)
    assert np.array_equal(imm.combine(cw, xp, pp)[0], kx)
    x, P, *_ = imm.update(xp, pp, cw, z, R)
    ux, up = kalman.update_state(kx, kp, z, R)
    assert np.array_equal(x, ux) and np.array_equal(P, up)


def test_models_must_be_one_or_two_with_positive_sojourns() -> None:
    with pytest.raises(ValueError, match="one or two"):
        imm.Models((1.0, 2.0, 3.0), (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="sojourn"):
        imm.Models((1.0, 2.0), (0.0, 1.0))
    assert imm.models_of(replace(FilterParams(), imm=False)).psd == (FilterParams().process_noise_psd,)


# -- in the tracker ---------------------------------------------------------------------------
SCAN_S = 4.0
TURN_AT_S = 30 * SCAN_S  # straight for 30 scans, then a rate-one turn (3 deg/s) through 90 deg
TURN_RATE = np.radians(3.0)
TURN_S = 30.0
SPEED = 220.0


def _truth(t: np.ndarray, n: int) -> np.ndarray:
    """ENU positions of ``n`` aircraft 60 km out on a ring, each flying across its bearing, at
    each one's time ``t``."""
    bearing = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    heading = bearing + np.pi / 2
    straight = np.minimum(t, TURN_AT_S)
    e = 60e3 * np.sin(bearing) + SPEED * straight * np.sin(heading)
    north = 60e3 * np.cos(bearing) + SPEED * straight * np.cos(heading)
    u = np.clip(t - TURN_AT_S, 0.0, TURN_S)
    r = SPEED / TURN_RATE
    e = e + r * (np.cos(heading) - np.cos(heading + TURN_RATE * u))
    north = north + r * (np.sin(heading + TURN_RATE * u) - np.sin(heading))
    after = np.maximum(t - TURN_AT_S - TURN_S, 0.0)
    h2 = heading + TURN_RATE * u
    return np.stack(
        [e + SPEED * after * np.sin(h2), north + SPEED * after * np.cos(h2), np.full_like(e, 9e3)], 1
    )


def _fly(imm_on: bool, seed: int, n: int = 12, scans: int = 70) -> tuple[np.ndarray, list[list[str]]]:
    """Each scan's horizontal error of each aircraft's nearest confirmed track, and that
    track's id."""
    rng = np.random.default_rng(seed)
    # (deletion by the radar's Pd off: every aircraft turns at once here, and the misses of the
    # one-model tracks in the turn read as a radar that misses often, so they would coast
    # through it; this compares the filters alone)
    params = replace(
        TrackerParams(),
        filter=replace(FilterParams(), imm=imm_on),
        manager=replace(ManagerParams(), deletion_miss_probability=0.0),
    )
    m = make_tracker(SITE, params=params)
    errors = np.full((scans, n), np.nan)
    ids: list[list[str]] = []
    for k in range(scans):
        _, az, _ = enu_to_polar(_truth(np.full(n, k * SCAN_S), n))
        t = k * SCAN_S + np.mod(az, 360.0) / 360.0 * SCAN_S  # when the beam passes each
        rng_m, az, _ = enu_to_polar(_truth(t, n))
        rng_m = rng_m + rng.normal(size=n) * SITE.range_sigma_m
        az = np.mod(az + rng.normal(size=n) * SITE.azimuth_sigma_deg, 360.0)
        o = np.argsort(t)
        names = np.array([f"a{i}" for i in o], dtype=object)
        m.update(
            PlotColumns(t[o], rng_m[o], az[o], np.full(n, np.nan), np.full(n, 9e3), names), (k + 1) * SCAN_S
        )
        tab = m.tracks()
        tab = tab.take(tab.confirmed)
        if len(tab) == 0:
            ids.append([""] * n)
            continue
        enu = (tab.position_ecef_m - SITE.origin_ecef) @ SITE.rotation
        truth = np.stack([_truth(np.full(n, s), n) for s in tab.time_s])  # (tracks, aircraft, 3)
        d = np.linalg.norm(truth[:, :, :2] - enu[:, None, :2], axis=2)
        nearest = np.argmin(d, axis=0)
        errors[k] = d[nearest, np.arange(n)]
        ids.append([str(tab.track_id[j]) for j in nearest])
    return errors, ids


def test_imm_holds_turns_better_and_straight_legs_tighter_than_one_model() -> None:
    """The reason the filter has two models: against the one constant-velocity model, fewer
    track-number changes through rate-one turns and a smaller error on straight legs (5 seeds
    of 12 aircraft)."""
    changes = {True: 0, False: 0}
    straight = {True: [], False: []}  # type: dict[bool, list[float]]
    for on in (False, True):
        for seed in range(1, 6):
            errors, ids = _fly(on, seed)
            changes[on] += sum(
                ids[k][i] != ids[k - 1][i] for k in range(12, len(ids)) for i in range(12) if ids[k - 1][i]
            )
            straight[on].append(float(np.nanmean(errors[15:30] ** 2)))
    assert changes[True] < 0.8 * changes[False]
    assert np.sqrt(np.mean(straight[True])) < 0.9 * np.sqrt(np.mean(straight[False]))


def test_other_models_serve_their_rows_only() -> None:
    """``predict`` with a second set of models for some rows: those rows are what the second
    set alone gives, the others what the first alone gives, number for number."""
    rng = np.random.default_rng(8)
    k = 30
    xm, pm = _random_states(rng, k, 2)
    mu = rng.dirichlet([2.0, 2.0], size=k)
    dt = rng.uniform(-1.0, 12.0, size=k)
    other = imm.Models((0.1, 100.0), (3600.0, 30.0))
    use = rng.random(k) < 0.5
    got = imm.predict(xm, pm, mu, dt, MODELS, other, use)
    first = imm.predict(xm, pm, mu, dt, MODELS)
    second = imm.predict(xm, pm, mu, dt, other)
    for g, f, s in zip(got, first, second, strict=True):
        np.testing.assert_array_equal(g[use], s[use])
        np.testing.assert_array_equal(g[~use], f[~use])
    assert use.any() and (~use).any()
