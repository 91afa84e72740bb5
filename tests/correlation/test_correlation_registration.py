"""Bias least squares: exact recovery without noise, joint solve over radar pairs, compensation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from service.correlation.base import PredictedTracks
from service.correlation.registration import (
    RegistrationMemory,
    RegistrationParams,
    compensate,
    remove_bias,
    solve_biases,
)
from service.geo import Site
from tests.correlation_support import snapshot_of
from topofusion_lab.evaluation.correlation_scenario import make_sites, sample_references


def test_three_radars_joint_and_compensation() -> None:
    rng = np.random.default_rng(1)
    a, b = make_sites()
    c = Site("C", 32.5, 119.0, 30.0)
    truth = sample_references(rng, a, b, 300)
    biases = {
        "A": np.array([300.0, np.radians(0.4), 0.0]),
        "B": np.array([-200.0, np.radians(-0.2), 0.0]),
        "C": np.array([100.0, np.radians(0.3), 0.0]),
    }
    snaps = {s.site_id: snapshot_of(s, truth, biases[s.site_id], rng, 30.0) for s in (a, b, c)}
    idx = np.arange(300)
    prm = RegistrationParams(max_rows_per_update=300)
    mems = []
    for s1, s2 in ((a, b), (a, c), (b, c)):
        m = RegistrationMemory(s1, s2)
        m.add(0.0, snaps[s1.site_id], snaps[s2.site_id], idx, idx, prm)
        mems.append(m)
    sol = solve_biases(mems, 0.0, prm)
    assert sol is not None
    for rid in "ABC":
        est, _ = sol.of(rid)
        assert abs(est[0] - biases[rid][0]) < 0.1 * abs(biases[rid][0])
        assert abs(est[1] - biases[rid][1]) < 0.1 * abs(biases[rid][1])
    comp, extra = compensate(snaps["A"], *sol.of("A"))
    before = np.linalg.norm(snaps["A"].position - truth, axis=1).mean()
    after = np.linalg.norm(comp.position - truth, axis=1).mean()
    assert after < 0.2 * before and extra.shape == (300, 3, 3)


def test_reference_source_fixed_at_zero() -> None:
    rng = np.random.default_rng(2)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 100)
    sa = snapshot_of(a, truth, np.array([500.0, np.radians(0.6), 0.0]), rng, 10.0)
    ref = snapshot_of(b, truth, np.zeros(3), rng, 10.0)
    ref = PredictedTracks(
        ref.track_id, ref.position, ref.velocity, ref.pos_cov, ref.vel_cov, None, ref.position, ref.velocity
    )
    m = RegistrationMemory(a, None)
    idx = np.arange(100)
    m.add(0.0, sa, ref, idx, idx, RegistrationParams())
    sol = solve_biases([m], 0.0)
    assert sol is not None and sol.radar_ids == ("A",)
    assert abs(sol.bias[0, 0] - 500.0) < 50.0 and abs(np.degrees(sol.bias[0, 1]) - 0.6) < 0.06


def _repeated_updates(repeats: int, seed: int) -> tuple[RegistrationMemory, np.ndarray]:
    """40 track pairs, each with one error draw repeated over ``repeats`` updates (fully
    correlated rows, like a slowly varying track error); returns the memory and true biases."""
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 40)
    ba = np.array([100.0, np.radians(0.1), np.radians(0.1)])
    bb = np.array([-100.0, np.radians(-0.1), np.radians(-0.1)])
    sa, sb = snapshot_of(a, truth, ba, rng, 150.0), snapshot_of(b, truth, bb, rng, 150.0)
    mem = RegistrationMemory(a, b)
    idx = np.arange(40)
    for k in range(repeats):
        mem.add(float(k), sa, sb, idx, idx, RegistrationParams())
    return mem, np.concatenate([ba, bb])


def test_robust_covariance_ignores_repeated_rows_and_is_calibrated() -> None:
    """Rows of one track pair are not independent evidence: the model covariance H^-1 falls
    as 1/repeats, the cluster-robust one does not, and its sigma matches the actual error."""
    z, ratio = [], []
    for seed in range(40):
        one, truth = _repeated_updates(1, seed)
        many, _ = _repeated_updates(10, seed)
        s1, s10 = solve_biases([one], 10.0), solve_biases([many], 10.0)
        assert s1 is not None and s10 is not None and s10.model_covariance is not None
        assert s10.clusters == 40
        # equal up to the weak prior's share, which repeating the rows dilutes
        np.testing.assert_allclose(s10.bias, s1.bias, rtol=1e-3)
        np.testing.assert_allclose(s10.std(), s1.std(), rtol=1e-2)
        assert s1.model_covariance is not None
        np.testing.assert_allclose(
            np.diag(s10.model_covariance), np.diag(s1.model_covariance) / 10, rtol=1e-2
        )
        ratio.append(np.diag(s10.covariance) / np.diag(s10.model_covariance))
        z.append((s10.bias.ravel() - truth) / s10.std().ravel())
    assert np.all(np.median(ratio, axis=0) > 5.0)  # ~10 if both were exact
    rms_z = np.sqrt(np.mean(np.square(z), axis=0))
    # 40 seeds: the RMS of a unit normal is 1 +- ~0.11; the sandwich is slightly low with 40
    # clusters, the model covariance would give ~3 here.
    assert np.all((rms_z > 0.7) & (rms_z < 1.4)), rms_z


@pytest.mark.parametrize("scale", [0.1, 0.5, 1.0, 2.0])
def test_recovers_biases_of_two_radars_without_noise(scale: float) -> None:
    """From 100 m / 0.1 deg up to 2 km / 2 deg the solve converges on the exact (polar) model:
    without noise the biases come back exactly (the linear model alone was 23 m off at 1 km /
    1 deg), and compensation puts A's tracks on the truth."""
    rng = np.random.default_rng(0)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 200)
    ba = np.array([1000 * scale, np.radians(scale), np.radians(0.2 * scale)])
    bb = np.array([-600 * scale, np.radians(-0.6 * scale), np.radians(-0.1 * scale)])
    sa, sb = snapshot_of(a, truth, ba, rng, 0.0), snapshot_of(b, truth, bb, rng, 0.0)
    mem = RegistrationMemory(a, b)
    idx = np.arange(200)
    prm = RegistrationParams(
        max_rows_per_update=200, prior_range_m=1e6, prior_azimuth_deg=1e3, prior_elevation_deg=1e3
    )
    mem.add(0.0, sa, sb, idx, idx, prm)
    sol = solve_biases([mem], 0.0, prm)
    assert sol is not None
    np.testing.assert_allclose(sol.bias, np.stack([ba, bb]), rtol=1e-6, atol=1e-9)
    comp, _ = compensate(sa, *sol.of("A"))
    np.testing.assert_allclose(comp.position, truth, atol=1e-3)


def test_remove_bias_is_the_polar_inverse() -> None:
    """The rotation form of the exact bias removal against the plain polar round trip."""
    rng = np.random.default_rng(3)
    a, b = make_sites()
    pos = sample_references(rng, a, b, 500)
    for _ in range(5):
        bias = rng.uniform([-3000, -0.05, -0.05], [3000, 0.05, 0.05])
        r, az, el = a.ecef_to_polar(pos)
        plain = a.polar_to_ecef(r - bias[0], az - np.degrees(bias[1]), el - np.degrees(bias[2]))
        np.testing.assert_allclose(remove_bias(a, pos, bias), plain, rtol=0, atol=1e-6)


def _noisy_memory(seed: int) -> tuple[RegistrationMemory, RegistrationParams]:
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 120)
    ba = np.array([400.0, np.radians(0.3), np.radians(0.05)])
    bb = np.array([-250.0, np.radians(-0.2), np.radians(-0.05)])
    prm = RegistrationParams()
    mem = RegistrationMemory(a, b)
    idx = np.arange(120)
    for t in range(6):
        sa, sb = snapshot_of(a, truth, ba, rng, 80.0), snapshot_of(b, truth, bb, rng, 80.0)
        sa.position[:4] += 3_000.0  # a few outliers (mispaired tracks) for the outlier test
        mem.add(float(t), sa, sb, idx, idx, prm)
    return mem, prm


def test_warm_start_reaches_the_cold_fixed_point_in_fewer_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    import service.correlation.registration as reg

    mem, prm = _noisy_memory(12)
    calls = [0]
    residual = reg._residual

    def counted(*args):  # type: ignore[no-untyped-def]
        calls[0] += 1
        return residual(*args)

    monkeypatch.setattr(reg, "_residual", counted)
    cold = solve_biases([mem], 5.0, prm)
    cold_calls, calls[0] = calls[0], 0
    assert cold is not None and cold.model_covariance is not None
    # A previous solution nearby (as after a few more updates): perturbed by 0.3 sigma.
    sigma = np.sqrt(np.diag(cold.model_covariance)).reshape(-1, 3)
    start = reg.BiasSolution(cold.radar_ids, cold.bias + 0.3 * sigma, cold.covariance, cold.pairs_used)
    warm = solve_biases([mem], 5.0, prm, initial=start)
    assert warm is not None
    assert calls[0] < cold_calls
    assert np.all(np.abs(warm.bias - cold.bias) <= 0.02 * sigma)
    assert warm.pairs_used == cold.pairs_used  # the same rows survived the outlier test
    np.testing.assert_allclose(warm.std(), cold.std(), rtol=1e-3)


def test_rows_per_update_rotate_over_the_pairs() -> None:
    """A capped add takes evenly spread pairs, different ones on successive updates."""
    rng = np.random.default_rng(13)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 1000)
    z = np.zeros(3)
    sa, sb = snapshot_of(a, truth, z, rng, 10.0), snapshot_of(b, truth, z, rng, 10.0)
    mem = RegistrationMemory(a, b)
    idx = np.arange(1000)
    seen = []
    for t in range(10):
        mem.add(float(t), sa, sb, idx, idx, RegistrationParams(), max_rows=100)
        rows = np.array([int(p.split("\x1f")[0][1:]) for p in mem.pair[mem.time == t]])
        assert len(rows) == 100 and np.all(np.diff(rows) >= 1) and np.all(np.diff(rows) <= 20)
        seen.append(rows)
    assert len(np.unique(np.concatenate(seen))) >= 600  # fixed picks would give 100


def test_memory_buffer_holds_exactly_the_remembered_updates() -> None:
    """The column buffers (appended at the end, forgotten from the front, compacted now and then)
    against a plain list of per-update chunks, over many updates of varying size and id width."""
    rng = np.random.default_rng(14)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 400)
    z = np.zeros(3)
    prm = RegistrationParams(memory_s=30.0, max_rows=900, max_rows_per_update=400)
    mem = RegistrationMemory(a, b)
    chunks: list[tuple[float, np.ndarray, np.ndarray]] = []
    for k in range(60):
        t = 2.0 * k
        sa, sb = snapshot_of(a, truth, z, rng, 10.0), snapshot_of(b, truth, z, rng, 10.0)
        if k > 40:  # longer track ids from here on: the pair column must widen
            sb = dataclasses.replace(sb, track_id=np.char.add(sb.track_id, "-long-suffix"))
        n = int(rng.integers(0, 400))
        idx = np.sort(rng.choice(400, n, replace=False))
        mem.add(t, sa, sb, idx, idx, prm)
        pair = np.char.add(np.char.add(sa.track_id[idx], "\x1f"), sb.track_id[idx])
        chunks.append((t, sa.position[idx], pair))
        chunks = [c for c in chunks if c[0] >= t - prm.memory_s]
        while len(chunks) > 1 and sum(len(c[1]) for c in chunks) > prm.max_rows:
            chunks.pop(0)
        assert len(mem) == sum(len(c[1]) for c in chunks)
        np.testing.assert_array_equal(mem.time, np.concatenate([np.full(len(c[1]), c[0]) for c in chunks]))
        np.testing.assert_array_equal(mem.p_a, np.concatenate([c[1] for c in chunks]))
        assert mem.pair.tolist() == np.concatenate([c[2] for c in chunks]).tolist()


def test_a_wrong_warm_start_does_not_lock_a_radars_rows_out() -> None:
    """A warm start whose estimate of radar B is far off (a first solve on few rows, with
    biases of kilometres and degrees) rejected every row of B by the outlier test at it, and
    every later solve warm-started from the result did the same: B's estimate stood where no
    row supported it (pairs_used 0, 740 m / -0.77 deg against -1500 m / -1.5 deg, the picture
    split in two).  A radar none of whose rows survive is solved cold: the rows decide."""
    import service.correlation.registration as reg

    rng = np.random.default_rng(7)
    a, b = make_sites()
    truth = sample_references(rng, a, b, 40)
    biases = {
        "A": np.array([2000.0, np.radians(2.0), np.radians(0.1)]),
        "B": np.array([-1500.0, np.radians(-1.5), 0.0]),
    }
    prm = RegistrationParams(max_rows_per_update=40)
    idx = np.arange(40)
    pair, reference = RegistrationMemory(a, b), RegistrationMemory(b, None)
    for t in range(4):
        sa, sb = (snapshot_of(s, truth, biases[s.site_id], rng, 30.0) for s in (a, b))
        ref = snapshot_of(b, truth, np.zeros(3), rng, 10.0)
        ref = PredictedTracks(
            ref.track_id,
            ref.position,
            ref.velocity,
            ref.pos_cov,
            ref.vel_cov,
            None,
            ref.position,
            ref.velocity,
        )
        pair.add(float(t), sa, sb, idx, idx, prm)
        reference.add(float(t), sb, ref, idx, idx, prm)
    cold = solve_biases([pair, reference], 3.0, prm)
    assert cold is not None and cold.pairs_used["B"] > 0
    wrong = cold.bias.copy()
    wrong[cold.radar_ids.index("B")] = [740.0, np.radians(-0.77), np.radians(0.54)]
    start = reg.BiasSolution(cold.radar_ids, wrong, cold.covariance, cold.pairs_used)
    warm = solve_biases([pair, reference], 3.0, prm, initial=start)
    assert warm is not None and warm.pairs_used["B"] > 0
    est, _ = warm.of("B")
    assert abs(est[0] - biases["B"][0]) < 50.0 and abs(np.degrees(est[1] - biases["B"][1])) < 0.05
