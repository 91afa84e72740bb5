"""Tracks in formations: ``Track.quality`` (the clarity of associations), duplicate tracks, and
the formation's quiet model.

The vectorised clarity is checked against a plain loop over the candidates, and the manager
against hand-made plot streams: two plots close together, then one aircraft whose plots
alternate between two places a scan (the pattern that feeds two tracks in turn), beside
isolated aircraft whose associations are never in doubt.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from service.config import engine_config_from
from service.tracking import make_tracker
from service.tracking.assignment import assign, clarity, weighted_covariance
from service.tracking.base import PlotColumns
from service.tracking.duplicates import duplicate_losers, shared_plot_pairs
from service.tracking.formation import (
    common_velocity,
    formation_groups,
    manoeuvring,
    velocity_gate,
    velocity_update,
)
from service.tracking.manager import TrackManager
from service.tracking.params import FormationParams, TrackerParams
from topofusion_lab.evaluation.initiation_monostatic import SITE

SCAN_S = SITE.scan_period_s
#: Isolated aircraft at these azimuths (degrees) make every batch a whole scan, so that every
#: track is looked at in every batch.
ANCHORS_DEG = (10.0, 100.0, 190.0, 280.0)


def _candidates(rng: np.random.Generator, n_tracks: int, n_plots: int, n: int) -> tuple[np.ndarray, ...]:
    pairs = rng.choice(n_tracks * n_plots, size=n, replace=False)
    rows, cols = np.divmod(pairs, n_plots)
    return rows.astype(np.intp), cols.astype(np.intp), rng.uniform(0.0, 16.0, n)


def test_clarity_against_a_plain_loop() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        rows, cols, d2 = _candidates(rng, 7, 9, int(rng.integers(1, 30)))
        chosen = assign(rows, cols, d2, 16.27)
        got = clarity(rows, cols, d2, chosen)
        for k, c in enumerate(chosen):
            own = math.exp(-d2[c] / 2)
            rivals = sum(
                math.exp(-d2[j] / 2)
                for j in range(len(rows))
                if j != c and (rows[j] == rows[c] or cols[j] == cols[c])
            )
            assert abs(got[k] - own / (own + rivals)) < 1e-12
        alone = (np.bincount(rows)[rows[chosen]] == 1) & (np.bincount(cols)[cols[chosen]] == 1)
        assert np.all(got[alone] == 1.0) and np.all((got > 0) & (got <= 1))


def test_shared_plot_pairs_against_a_plain_loop() -> None:
    rng = np.random.default_rng(6)
    for _ in range(20):
        rows, cols, _ = _candidates(rng, 6, 5, int(rng.integers(0, 25)))
        a, b = shared_plot_pairs(rows, cols)
        n = len(rows)
        want = sorted(
            {
                (min(rows[i], rows[j]), max(rows[i], rows[j]))
                for i in range(n)
                for j in range(n)
                if i != j and cols[i] == cols[j]
            }
        )
        assert list(zip(a.tolist(), b.tolist(), strict=True)) == want


def test_duplicate_losers_against_a_plain_loop() -> None:
    rng = np.random.default_rng(7)
    n = 10
    x = np.zeros((n, 6))
    x[:, 0] = rng.choice([0.0, 50.0, 5_000.0], n)  # some close, some far
    x[:, 3] = 100.0
    P = np.broadcast_to(np.diag([100.0**2] * 3 + [10.0**2] * 3), (n, 6, 6)).copy()
    t = np.full(n, 10.0)
    hits = rng.integers(0, 1 << 6, n).astype(np.int64)
    looks = rng.integers(2, 12, n).astype(np.int64)
    plots = rng.integers(3, 6, n).astype(np.int64)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    a = np.array([p[0] for p in pairs], dtype=np.intp)
    b = np.array([p[1] for p in pairs], dtype=np.intp)
    got = duplicate_losers(a, b, x, P, t, hits, looks, plots, 10.0, 25.0, 16.81, 4)
    want = set()
    for i, j in pairs:
        d = x[i] - x[j]
        if d @ np.linalg.solve(P[i] + P[j], d) > 16.81:
            continue
        if looks[i] < 4 or looks[j] < 4 or hits[i] & hits[j] & 0b1111:
            continue
        # the loser: fewer plots, on a tie the younger (the later row)
        want.add(i if plots[i] < plots[j] else j if plots[j] < plots[i] else max(i, j))
    assert got.tolist() == sorted(want)
    assert len(want) > 0  # the draw holds duplicates


def _plots(t: float, azimuths: list[float], ranges: list[float], names: list[str]) -> PlotColumns:
    n = len(azimuths)
    return PlotColumns(
        np.full(n, t),
        np.array(ranges),
        np.array(azimuths),
        np.full(n, np.nan),
        np.full(n, 9_000.0),
        np.array(names, dtype=object),
    )


def _near_mask(m: TrackManager) -> np.ndarray:
    """The confirmed tracks within 2 deg of the split aircraft."""
    tab = m.tracks()
    enu = (tab.position_ecef_m - SITE.origin_ecef) @ SITE.rotation
    az = np.degrees(np.arctan2(enu[:, 0], enu[:, 1]))
    return np.asarray(tab.confirmed & (np.abs(az - 45.2) < 2.0))


def _near_x(m: TrackManager) -> int:
    return int(np.count_nonzero(_near_mask(m)))


def _stream(m: TrackManager, scans: int, split_deg: float = 0.4, start: int = 0) -> list[np.ndarray]:
    """An aircraft flying outwards at 45 deg that shows two plots ``split_deg`` apart for 8
    scans (two close aircraft to the radar), then one plot a scan alternating between the two
    places (one aircraft feeding two tracks in turn); four isolated aircraft around.  Returns
    the quality column after each scan, rows in track-id order."""
    out = []
    for k in range(start, start + scans):
        t = 1_000.0 + k * SCAN_S
        r = 60_000.0 + 150.0 * (t - 1_000.0)
        if k < 8:
            az, rg = [45.0, 45.0 + split_deg], [r, r]
        else:
            az, rg = [45.0 + split_deg * (k % 2)], [r]
        az += list(ANCHORS_DEG)
        rg += [80_000.0 - 100.0 * (t - 1_000.0)] * len(ANCHORS_DEG)
        m.update(_plots(t, az, rg, ["X"] * (len(az) - len(ANCHORS_DEG)) + ["A"] * len(ANCHORS_DEG)), t)
        tab = m.tracks()
        out.append(tab.quality[np.argsort(tab.track_id)])
    return out


def test_quality_marks_the_ambiguous_tracks_only() -> None:
    m = make_tracker(SITE)
    qualities = _stream(m, 8)
    tab = m.tracks()
    assert _near_x(m) == 2  # two confirmed tracks on the two close plots
    near = _near_mask(m)
    # the isolated aircraft: every plot clearly theirs; the close pair: each plot in both gates
    assert np.all(tab.quality[~near] == 1.0)
    assert np.all((tab.quality[near] > 0.3) & (tab.quality[near] < 0.8))
    assert np.all(np.isnan(qualities[0])) or len(qualities[0]) == 0  # no association yet
    assert np.all((tab.quality >= 0) & (tab.quality <= 1))


def test_quality_memory_is_the_named_parameter() -> None:
    """A shorter memory follows the clarity of the latest associations more closely."""
    fast = make_tracker(
        SITE, params=replace(TrackerParams(), formation=FormationParams(quality_memory_looks=1.0))
    )
    _stream(fast, 8)
    slow = make_tracker(SITE)
    _stream(slow, 8)
    qf, qs = fast.tracks().quality[_near_mask(fast)], slow.tracks().quality[_near_mask(slow)]
    # the two tracks draw apart as their filters settle, so each association is clearer than
    # the one before: with memory 1 the quality is the last (the clearest) association's, and
    # above the average with memory 5, which still holds the earlier ones
    assert np.all(qf > qs + 0.03)


def test_one_aircraft_feeding_two_tracks_in_turn_ends_with_one_track() -> None:
    """The duplicate pattern: after 8 scans of two close plots, one plot a look alternating
    between the two places.  Each track is hit every other look, so neither ever reaches its
    deletion count of misses: without the rule both live on; with it the younger twin is
    dropped once the two have had ``duplicate_looks`` looks without a common plot, and the
    survivor's quality recovers."""
    on = make_tracker(SITE)
    off = make_tracker(SITE, params=replace(TrackerParams(), formation=FormationParams.off()))
    fm = FormationParams()
    for m in (on, off):
        _stream(m, 8 + fm.duplicate_looks - 1)
    assert _near_x(on) == 2 and _near_x(off) == 2  # not yet: fewer looks than the rule needs
    for m in (on, off):
        _stream(m, 3, start=8 + fm.duplicate_looks - 1)
    assert _near_x(off) == 2
    assert _near_x(on) == 1
    kept, both = on.tracks(), off.tracks()
    # the survivor is the older twin; the isolated aircraft keep their tracks
    twins = sorted(both.track_id[_near_mask(off)].tolist(), key=lambda s: int(s.split("-")[1]))
    assert kept.track_id[_near_mask(on)].tolist() == twins[:1]
    assert len(kept) == len(both) - 1
    _stream(on, 10, start=8 + fm.duplicate_looks + 2)
    assert _near_x(on) == 1 and on.tracks().quality[_near_mask(on)][0] > 0.9


def test_formation_groups_against_a_plain_loop() -> None:
    rng = np.random.default_rng(7)
    radius, speed, nearest = 3_000.0, 50.0, 4
    seen = set()
    for _ in range(20):
        n = int(rng.integers(0, 40))
        pos = np.column_stack([rng.uniform(0.0, 20_000.0, (n, 2)), rng.uniform(8_000.0, 10_000.0, n)])
        vel = rng.normal(size=(n, 3)) * 40.0 + np.array([200.0, 50.0, 0.0])
        got = formation_groups(pos, vel, radius, speed, nearest)
        # i -> j: j among i's ``nearest`` nearest others within the radius, at an alike velocity
        edge = [[False] * n for _ in range(n)]
        for i in range(n):
            others = sorted((math.dist(pos[i], pos[j]), j) for j in range(n) if j != i)
            for d, j in others[:nearest]:
                if d <= radius and math.dist(vel[i], vel[j]) <= speed:
                    edge[i][j] = edge[j][i] = True
        # the formations: the connected groups of such neighbours, by a plain flood fill
        want = [-1] * n
        for start in range(n):
            if want[start] >= 0 or not any(edge[start]):
                continue
            want[start], todo = start, [start]
            while todo:
                i = todo.pop()
                for j in range(n):
                    if edge[i][j] and want[j] < 0:
                        want[j] = start
                        todo.append(j)
        assert [g >= 0 for g in got.tolist()] == [w >= 0 for w in want]
        for i in range(n):  # the same partition (labels may differ)
            for j in range(n):
                if want[i] >= 0 and want[j] >= 0:
                    assert (got[i] == got[j]) == (want[i] == want[j])
        seen.update(w >= 0 for w in want)
    assert seen == {True, False}  # the draws hold both kinds


def test_a_crowd_of_alike_tracks_is_one_formation() -> None:
    """Two thousand tracks within a few hundred metres, all alike: each looks at its 8 nearest
    only (every pair within the radius would be two million), and they still make one
    formation, joined through their nearest."""
    rng = np.random.default_rng(11)
    n = 2_000
    pos = rng.uniform(0.0, 300.0, size=(n, 3))
    vel = np.tile([200.0, 0.0, 0.0], (n, 1))
    got = formation_groups(pos, vel, 3_000.0, 50.0, 8)
    assert np.all(got == got[0]) and got[0] >= 0


def test_manoeuvring_against_a_plain_loop() -> None:
    rng = np.random.default_rng(9)
    flagged = 0
    for _ in range(40):
        k = int(rng.integers(0, 25))
        label = rng.integers(0, 4, size=k).astype(np.intp)
        b = rng.normal(size=(k, 3, 3))
        S = b @ np.swapaxes(b, -1, -2) + np.eye(3)
        common = rng.normal(size=(4, 3)) * rng.uniform(0.0, 3.0)  # each group's common deviation
        y = rng.normal(size=(k, 3)) + common[label]
        got = manoeuvring(label, y, S, 11.34, 3)
        want = []
        for g in sorted(set(label.tolist())):
            rows = [i for i in range(k) if label[i] == g]
            if len(rows) < 3:
                continue
            own = [float(y[i] @ np.linalg.solve(S[i], y[i])) for i in rows]
            rows.pop(own.index(max(own)))  # the member that deviates most on its own
            total = sum(y[i] for i in rows)
            cov = sum(S[i] for i in rows)
            if float(total @ np.linalg.solve(cov, total)) > 11.34:
                want.append(g)
        assert got.tolist() == want
        flagged += len(want)
    assert flagged > 0


def test_one_track_astray_is_not_a_manoeuvre_of_its_formation() -> None:
    """Five members on their aircraft and one on a neighbour's plot far off: the sum of all
    six would pass for a manoeuvre, the sum without the one that deviates most does not; all
    six off the same way do."""
    S = np.repeat(np.eye(3)[None] * 100.0**2, 6, axis=0)
    y = np.zeros((6, 3))
    y[5] = [900.0, 0.0, 0.0]
    label = np.zeros(6, dtype=np.intp)
    assert manoeuvring(label, y, S, 11.34, 1_000).size == 0  # too few members: no test
    assert manoeuvring(label, y, S, 11.34, 3).size == 0
    assert manoeuvring(label, y + np.array([200.0, 0.0, 0.0]), S, 11.34, 3).tolist() == [0]


def _abreast(m: TrackManager, scans: int) -> None:
    """Two aircraft flying outwards side by side, 1 deg (about 1 km) apart, and the four
    isolated aircraft around (every plot exactly where its aircraft is)."""
    for k in range(scans):
        t = 1_000.0 + k * SCAN_S
        r = 60_000.0 + 150.0 * (t - 1_000.0)
        az = [45.0, 46.0, *ANCHORS_DEG]
        rg = [r, r] + [80_000.0 - 100.0 * (t - 1_000.0)] * len(ANCHORS_DEG)
        m.update(_plots(t, az, rg, ["X", "Y"] + ["A"] * len(ANCHORS_DEG)), t)


def test_tracks_in_formation_predict_with_the_formation_quiet_model() -> None:
    """Two aircraft abreast are a formation (a neighbour within ``formation_radius_m`` at the
    same velocity): their tracks settle to a smaller velocity uncertainty than with the
    filter's own quiet model (``hold_formations`` off); the isolated aircraft's tracks are
    the same number for number either way."""
    on = make_tracker(SITE)
    off = make_tracker(
        SITE, params=replace(TrackerParams(), formation=FormationParams(hold_formations=False))
    )
    for m in (on, off):
        _abreast(m, 25)
    a, b = on.tracks(), off.tracks()
    assert a.track_id.tolist() == b.track_id.tolist() and len(a) == 2 + len(ANCHORS_DEG)
    enu = (a.position_ecef_m - SITE.origin_ecef) @ SITE.rotation
    pair = np.abs(np.degrees(np.arctan2(enu[:, 0], enu[:, 1])) - 45.5) < 2.0
    assert np.count_nonzero(pair) == 2 and np.all(a.confirmed)
    vel_var_on = np.trace(a.covariance[:, 3:, 3:], axis1=1, axis2=2)
    vel_var_off = np.trace(b.covariance[:, 3:, 3:], axis1=1, axis2=2)
    assert np.all(vel_var_on[pair] < 0.7 * vel_var_off[pair])
    np.testing.assert_array_equal(a.covariance[~pair], b.covariance[~pair])
    np.testing.assert_array_equal(a.position_ecef_m[~pair], b.position_ecef_m[~pair])


# -- the formation's common velocity ------------------------------------------------------------
def test_common_velocity_against_a_plain_loop() -> None:
    rng = np.random.default_rng(11)
    n = 40
    label = rng.integers(0, 6, n)
    label[-1] = 99  # alone in its formation
    vel = rng.normal(size=(n, 2)) * 30.0 + np.array([200.0, -40.0])
    var = rng.uniform(4.0, 400.0, n)
    mean, mean_var = common_velocity(label, vel, var)
    for i in range(n):
        others = [j for j in range(n) if j != i and label[j] == label[i]]
        if not others:
            assert np.all(np.isnan(mean[i])) and np.isnan(mean_var[i])
            continue
        w = sum(1.0 / var[j] for j in others)
        want = sum(vel[j] / var[j] for j in others) / w
        np.testing.assert_allclose(mean[i], want, rtol=1e-12)
        assert math.isclose(mean_var[i], 1.0 / w, rel_tol=1e-12)


def test_velocity_update_against_the_plain_kalman_form() -> None:
    rng = np.random.default_rng(12)
    k = 25
    a = rng.normal(size=(k, 6, 6))
    P = a @ np.swapaxes(a, 1, 2) + np.eye(6)
    x = rng.normal(size=(k, 6)) * 100.0
    v = rng.normal(size=(k, 2)) * 100.0
    r = rng.uniform(1.0, 50.0, k)
    got_x, got_p = velocity_update(x, P, v, r)
    gate = velocity_gate(x, P, v, r)
    H = np.zeros((2, 6))
    H[0, 3] = H[1, 4] = 1.0
    for i in range(k):
        R = r[i] * np.eye(2)
        S = H @ P[i] @ H.T + R
        K = P[i] @ H.T @ np.linalg.inv(S)
        y = v[i] - H @ x[i]
        np.testing.assert_allclose(got_x[i], x[i] + K @ y, rtol=1e-9, atol=1e-9)
        ikh = np.eye(6) - K @ H
        np.testing.assert_allclose(got_p[i], ikh @ P[i] @ ikh.T + K @ R @ K.T, rtol=1e-9, atol=1e-9)
        assert math.isclose(gate[i], float(y @ np.linalg.solve(S, y)), rel_tol=1e-9)


def _abreast_apart(m: TrackManager, scans: int, faster: float) -> np.ndarray:
    """Three aircraft flying outwards abreast 1 km apart (the middle one ``faster`` m/s
    faster), plots exactly where they are, and the four isolated aircraft around; returns
    the aircraft's radial speeds."""
    speed = np.array([150.0, 150.0 + faster, 150.0])
    for k in range(scans):
        t = 1_000.0 + k * SCAN_S
        rg = 60_000.0 + speed * (t - 1_000.0)
        az = [44.0, 45.0, 46.0, *ANCHORS_DEG]
        others = [80_000.0 - 100.0 * (t - 1_000.0)] * len(ANCHORS_DEG)
        m.update(_plots(t, az, [*rg, *others], ["X", "Y", "Z"] + ["A"] * len(ANCHORS_DEG)), t)
    return speed


def _radial_speeds(m: TrackManager) -> np.ndarray:
    """The confirmed tracks' speeds near azimuth 45 deg, by azimuth."""
    tab = m.tracks()
    enu = (tab.position_ecef_m - SITE.origin_ecef) @ SITE.rotation
    az = np.degrees(np.arctan2(enu[:, 0], enu[:, 1]))
    near = tab.confirmed & (np.abs(az - 45.0) < 3.0)
    speed = np.linalg.norm((tab.velocity_ecef_mps @ SITE.rotation)[near, :2], axis=1)
    return speed[np.argsort(az[near])]


_NO_COMMON_VELOCITY = replace(
    TrackerParams(), formation=replace(FormationParams(), formation_velocity_sigma_mps=0.0)
)


def test_a_member_flying_otherwise_comes_back_to_its_own_velocity() -> None:
    """Abreast with two others (a formation: within ``formation_speed_mps``), an aircraft
    flying 40 m/s faster: only the formation's quiet model takes the others' mean, so its
    plots put its track on the manoeuvre model, which kept its own velocity, and the mean is
    kept out of its quiet model once its velocity lies beyond the gate.  After 40 scans every
    track's speed is within 1 m/s of the tracker's without the rule; the other two fly one
    velocity and are alike either way."""
    got = {}
    for on in (True, False):
        m = make_tracker(SITE, params=None if on else _NO_COMMON_VELOCITY)
        _abreast_apart(m, 40, 40.0)
        got[on] = _radial_speeds(m)
    assert got[True].shape == (3,) and got[False].shape == (3,)
    assert got[False][1] - got[False][0] > 35.0  # the plots do say 40 m/s faster
    np.testing.assert_allclose(got[True], got[False], atol=1.0)


# -- the weighted update of a member of a formation -----------------------------------------------
def test_weighted_covariance_against_a_plain_loop() -> None:
    rng = np.random.default_rng(17)
    cov = rng.normal(size=(40, 3, 3))
    cov = cov @ cov.transpose(0, 2, 1) + np.eye(3)
    clear = rng.uniform(0.01, 1.0, 40)
    clear[:5] = 1.0
    for floor in (0.1, 0.25, 0.9):
        got = weighted_covariance(cov, clear, floor)
        for k in range(40):
            np.testing.assert_allclose(got[k], cov[k] / max(clear[k], floor), rtol=1e-14)
    assert weighted_covariance(cov, clear, 1.0) is cov  # the floor at 1: the plain update


def _track_azimuths(m: TrackManager) -> tuple[np.ndarray, np.ndarray]:
    """Each track's azimuth (deg) and quality, rows in track-id order."""
    tab = m.tracks()
    order = np.argsort(tab.track_id)
    enu = (tab.position_ecef_m[order] - SITE.origin_ecef) @ SITE.rotation
    return np.degrees(np.arctan2(enu[:, 0], enu[:, 1])), tab.quality[order]


def test_a_contested_plot_pulls_a_member_of_a_formation_less() -> None:
    """Two aircraft abreast 1 deg apart (a formation), then one scan in which the left one's plot
    lies halfway to the right one, in both tracks' gates: it moves its track less
    with the weighted update (the default ``update_clarity_floor``) than with the plain one
    (1); the isolated aircraft's tracks move exactly alike."""
    weighted = make_tracker(SITE)
    plain = make_tracker(
        SITE, params=replace(TrackerParams(), formation=FormationParams(update_clarity_floor=1.0))
    )
    moves, contested = [], []
    for m in (weighted, plain):
        _abreast(m, 20)
        before, _ = _track_azimuths(m)
        t = 1_000.0 + 20 * SCAN_S
        r = 60_000.0 + 150.0 * (t - 1_000.0)
        az = [45.5, 46.0, *ANCHORS_DEG]
        rg = [r, r] + [80_000.0 - 100.0 * (t - 1_000.0)] * len(ANCHORS_DEG)
        m.update(_plots(t, az, rg, ["X", "Y"] + ["A"] * len(ANCHORS_DEG)), t)
        after, quality = _track_azimuths(m)
        assert len(after) == 2 + len(ANCHORS_DEG)
        moves.append(after - before)
        contested.append(quality)
    left = int(np.argmin(np.abs(before - 45.0)))
    pair = np.abs(before - 45.5) < 2.0
    assert np.count_nonzero(pair) == 2
    # the plot was in both gates: its clarity about a half drew the quality (memory 5) down
    assert contested[0][left] < 0.95 and contested[1][left] < 0.95
    assert 0.0 < moves[0][left] < 0.7 * moves[1][left]  # towards the plot, less far
    np.testing.assert_array_equal(moves[0][~pair], moves[1][~pair])


def test_the_update_clarity_floor_is_a_setting_above_zero() -> None:
    got = engine_config_from({"tracking": {"formation": {"update_clarity_floor": 1.0}}})
    assert got.tracking.formation.update_clarity_floor == 1.0
    for bad in (0, -0.5):
        with pytest.raises(ValueError, match="update_clarity_floor"):
            engine_config_from({"tracking": {"formation": {"update_clarity_floor": bad}}})
