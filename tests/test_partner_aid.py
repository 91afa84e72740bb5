"""The aid of association by the correlation's confirmed partners (service/tracking/aid.py,
service/correlation/partner_view.py, service/pipeline/partner_aid.py): each vectorised form
against a plain one, and the aid's determinism through the engine, with one worker and N."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from service.config import with_aid, without_aid
from service.correlation.partner_view import into_view, view_with_covariance
from service.engine import Engine, EngineConfig
from service.fusion.members import Links
from service.geo import Site
from service.pipeline.partition import Partition
from service.pipeline.partner_aid import PartnerAid
from service.pipeline.shared_links import Crossing, PairRegistration, SharedLinks
from service.pipeline.tracking_stage import TrackedRadar, TrackingStage
from service.tracking.aid import aided_d2, moved
from service.tracking.base import TrackTable
from service.tracking.params import AidParams
from service.wire.keys import Keys
from service.wire.models import RadarSite
from tests.scenario_helpers import interleaved, run_engine, run_one, run_partitioned

A = Site("A", 50.0, 5.0, 100.0)
B = Site("B", 51.0, 6.5, 200.0)
#: Realistic terms (m, rad, rad, ppm, s): A's five, then B's.
TERMS = np.array(
    [30.0, np.radians(0.3), np.radians(0.05), 20.0, 1.5, -50.0, np.radians(-0.2), 0.0, 0.0, -2.0]
)
SIGMAS = np.array([20.0, 1e-4, 1e-4, 5.0, 0.3] * 2)


def _positions(site: Site, n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    enu = np.column_stack(
        [rng.uniform(-150e3, 150e3, n), rng.uniform(-150e3, 150e3, n), rng.uniform(3e3, 11e3, n)]
    )
    ecef = site.enu_to_ecef(enu)
    vel = site.enu_to_ecef(rng.normal(0.0, 150.0, (n, 3)) * [1, 1, 0]) - site.enu_to_ecef(np.zeros((n, 3)))
    cov = np.array([np.diag(rng.uniform(50.0, 300.0, 3) ** 2) for _ in range(n)])
    return ecef, vel, cov


def _plain_view(
    source: Site, target: Site, p: np.ndarray, v: np.ndarray, pc: np.ndarray, terms: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One position at a time, the Jacobian by central finite differences of the transform."""
    c = c.copy()
    held = terms == 0.0
    c[held, :] = 0.0
    c[:, held] = 0.0

    def at(t: np.ndarray) -> np.ndarray:
        return target.ecef_to_enu(into_view(source, target, p[None], v[None], t[5:], t[:5]))[0]

    jac = np.zeros((3, 10))
    for j, step in enumerate([1.0, 1e-6, 1e-6, 1.0, 0.01] * 2):
        d = np.zeros(10)
        d[j] = step
        jac[:, j] = (at(terms + d) - at(terms - d)) / (2 * step)
    r = target.rotation.T
    return at(terms), r @ pc @ r.T + jac @ c @ jac.T


def test_the_vectorised_view_matches_a_plain_one_position_at_a_time() -> None:
    ecef, vel, cov = _positions(B, 25)
    c = np.diag(SIGMAS**2)
    pos, total, reg = view_with_covariance(B, A, ecef, vel, cov, TERMS, c)
    for k in range(ecef.shape[0]):
        want_pos, want_cov = _plain_view(B, A, ecef[k], vel[k], cov[k], TERMS, c)
        np.testing.assert_allclose(pos[k], want_pos, rtol=0, atol=1e-6)
        # first order in the terms (0.3 deg, 20 ppm): within half a percent of the exact form
        np.testing.assert_allclose(total[k], want_cov, rtol=0, atol=5e-3 * np.abs(want_cov).max())
    assert np.all(np.sqrt(np.trace(reg[:, :2, :2], axis1=1, axis2=2)) > 10.0)  # (it counts)


def test_a_term_held_at_zero_adds_no_error() -> None:
    ecef, vel, cov = _positions(B, 5)
    terms = TERMS.copy()
    terms[[3, 4, 8, 9]] = 0.0  # (no gain, no time bias: held by the solution)
    c = np.diag(SIGMAS**2)
    _, _, reg = view_with_covariance(B, A, ecef, vel, cov, terms, c)
    c[[3, 4, 8, 9], [3, 4, 8, 9]] = 0.0
    _, _, want = view_with_covariance(B, A, ecef, vel, cov, terms, c)
    np.testing.assert_allclose(reg, want)


def test_aided_d2_matches_a_plain_loop() -> None:
    rng = np.random.default_rng(3)
    n = 12
    z, ref = rng.normal(0, 500, (n, 3)), rng.normal(0, 500, (n, 3))
    ref[[2, 7]] = np.nan

    def spd() -> np.ndarray:
        m = rng.normal(size=(n, 3, 3))
        return m @ np.swapaxes(m, 1, 2) * 1e4 + np.eye(3) * 100.0

    cz, cr = spd(), spd()
    got = aided_d2(z, cz, ref, cr)
    for k in range(n):
        if np.isnan(ref[k, 0]):
            assert np.isnan(got[k])
        else:
            y = z[k] - ref[k]
            assert got[k] == pytest.approx(float(y @ np.linalg.inv(cz[k] + cr[k]) @ y), rel=1e-9)


def test_moved_matches_the_constant_velocity_prediction_one_state_at_a_time() -> None:
    rng = np.random.default_rng(5)
    n = 9
    pos, vel = rng.normal(0, 1e5, (n, 3)), rng.normal(0, 200, (n, 3))
    m = rng.normal(size=(n, 6, 6))
    cov = m @ np.swapaxes(m, 1, 2) * 100.0
    dt = rng.uniform(-2.0, 25.0, n)
    got_pos, got_cov = moved(pos, vel, cov, dt, 4.0)
    for k in range(n):
        f = np.eye(6)
        f[:3, 3:] = dt[k] * np.eye(3)
        q = np.zeros((6, 6))  # Bar-Shalom Eq. 6.2.2-12, per axis [[dt^3/3, dt^2/2], [dt^2/2, dt]]
        q[:3, :3] = 4.0 * abs(dt[k]) ** 3 / 3 * np.eye(3)
        want = f @ cov[k] @ f.T + q
        np.testing.assert_allclose(got_pos[k], pos[k] + vel[k] * dt[k])
        np.testing.assert_allclose(got_cov[k], want[:3, :3], rtol=1e-12, atol=1e-9)


def _table(site: Site, ids: list[str], seed: int, spread_m: float, time_s: float = 100.0) -> TrackTable:
    """Tracks of ``spread_m`` 1-sigma per axis, 3 m/s in velocity, the two correlated by 0.5."""
    ecef, vel, _ = _positions(site, len(ids), seed)
    cov = np.zeros((len(ids), 6, 6))
    cov[:, :3, :3] = np.eye(3) * spread_m**2
    cov[:, 3:, 3:] = np.eye(3) * 9.0
    cov[:, :3, 3:] = cov[:, 3:, :3] = np.eye(3) * 0.5 * spread_m * 3.0
    return TrackTable(
        np.array(ids),
        np.ones(len(ids), bool),
        np.full(len(ids), time_s),
        ecef,
        vel,
        cov,
        np.full(len(ids), 5, dtype=np.int64),
    )


def _links(a: str, b: str, pairs: list[tuple[str, str]], reg: PairRegistration | None) -> SharedLinks:
    ta = np.array([p[0] for p in pairs])
    tb = np.array([p[1] for p in pairs])
    return SharedLinks((a, b), 88.0, a, Links(a, b, ta, tb, np.ones(len(pairs))), reg)


def test_references_take_the_most_precise_registered_partner_as_a_plain_loop_does() -> None:
    sites = {"A": A, "B": B, "C": Site("C", 50.5, 7.0, 50.0)}
    stage = TrackingStage(lambda site, rid: None)  # type: ignore[arg-type,return-value]
    spreads = {"A": 400.0, "B": 60.0, "C": 90.0}
    ids = {r: [f"{r}-{k}" for k in range(1, 9)] for r in sites}
    for r, site in sites.items():
        radar = TrackedRadar(
            RadarSite(radar_id=r, latitude_deg=site.latitude_deg, longitude_deg=site.longitude_deg), site
        )
        radar.table = _table(site, ids[r], seed=ord(r), spread_m=spreads[r], time_s=88.0)
        stage.tracked[r] = radar
    tight = np.diag((SIGMAS / 4) ** 2)  # (within 50 m at every track)
    views = {
        ("A", "B"): _links(
            "A",
            "B",
            [(f"A-{k}", f"B-{k}") for k in (1, 2, 3, 5)],
            PairRegistration(("A", "B"), TERMS.reshape(2, 5), tight),
        ),
        ("C", "A"): _links(
            "C",
            "A",
            [(f"C-{k}", f"A-{k}") for k in (2, 4, 6)],
            PairRegistration(("A", "C"), TERMS.reshape(2, 5), tight),
        ),
    }
    params = AidParams(enabled=True, lag_s=10.0, registration_sigma_m=50.0)
    aid = PartnerAid(params, stage)
    for r, radar in stage.tracked.items():  # (the tables at the crossing; a later one is not read)
        aid.record(r, 88.0, radar.table)
        aid.record(r, 91.0, _table(sites[r], ids[r], seed=7, spread_m=1.0, time_s=91.0))
    aid.crossed(Crossing((90.0, "B"), tuple(views.values())))
    assert aid.references("A", 95.0) is None  # (crossings up to 85 s: none yet)
    refs = aid.references("A", 100.0)
    assert refs is not None
    cand = np.array(["A-1", "A-2", "A-2", "A-4", "A-6", "A-7", "A-5"])
    times = np.linspace(100.0, 102.0, cand.shape[0])
    own = np.full(cand.shape[0], 2 * spreads["A"] ** 2)
    own[-1] = 1.0  # (A-5 is more precise than any partner: no aid)
    ref, cov = refs(cand, times, own)
    # the plain form: each candidate, each partner, the most precise within the registration limit
    for k, tid in enumerate(cand):
        best = (own[k], None)
        for (ra, rb), view in views.items():
            mine, theirs = (view.links.track_a, view.links.track_b)[:: 1 if ra == "A" else -1]
            other = rb if ra == "A" else ra
            hit = np.flatnonzero(mine == tid)
            if not hit.shape[0]:
                continue
            pid = theirs[hit[0]]
            reg = view.registration
            assert reg is not None
            order = [reg.radar_ids.index(x) for x in ("A", other)]
            terms = np.concatenate([reg.terms[i] for i in order])
            idx = np.concatenate([np.arange(5 * i, 5 * i + 5) for i in order])
            t = stage.tracked[other].table
            i = int(np.flatnonzero(t.track_id == pid)[0])
            dt = times[k] - t.time_s[i]
            p = t.position_ecef_m[i] + t.velocity_ecef_mps[i] * dt
            f = np.block([[np.eye(3), dt * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
            pc = (f @ t.covariance[i] @ f.T)[:3, :3] + params.reference_psd * dt**3 / 3 * np.eye(3)
            pos, c, r = view_with_covariance(
                sites[other],
                A,
                p[None],
                t.velocity_ecef_mps[i][None],
                pc[None],
                terms,
                reg.covariance[np.ix_(idx, idx)],
            )
            spread = float(np.trace(c[0, :2, :2]))
            if np.sqrt(np.trace(r[0, :2, :2])) <= 50.0 and spread < best[0]:
                best = (spread, (pos[0], c[0]))
        if best[1] is None:
            assert np.isnan(ref[k]).all(), tid
        else:
            np.testing.assert_allclose(ref[k], best[1][0])
            np.testing.assert_allclose(cov[k], best[1][1])
    aided = ~np.isnan(ref[:, 0])
    assert aided.tolist() == [True, True, True, True, True, False, False]  # no pair; A-5: own)
    # A-2 has partners on B (60 m) and C (90 m): B's, the more precise
    assert np.trace(cov[1, :2, :2]) < np.trace(cov[3, :2, :2])
    # a registration looser than the limit aids nothing
    strict = PartnerAid(replace(params, registration_sigma_m=5.0), stage)
    for r, radar in stage.tracked.items():
        strict.record(r, 88.0, radar.table)
    strict.crossed(Crossing((90.0, "B"), tuple(views.values())))
    got = strict.references("A", 100.0)
    assert got is not None and np.isnan(got(cand, times, own)[0]).all()
    # a radar dropped since (its site removed): its pairs aid nothing, the others go on
    del stage.tracked["C"]
    ref, _ = refs(cand, times, own)
    assert (~np.isnan(ref[:, 0])).tolist() == [True, True, True, False, False, False, False]


def _aided(config: EngineConfig, **changes: Any) -> EngineConfig:
    return with_aid(config, **changes)


def test_the_aid_needs_a_lag() -> None:
    with pytest.raises(ValueError, match="lag above zero"):
        Engine(_aided(EngineConfig(), lag_s=0.0))
    with pytest.raises(ValueError, match="lag above zero"):
        Engine(replace(_aided(EngineConfig(), lag_s=0.0), partition=Partition(1, 2)))
    Engine(replace(_aided(EngineConfig()), partition=Partition(1, 2))).close()  # (partitioned: fine)


@pytest.fixture(scope="module")
def formation_in_traffic() -> list[tuple[str, bytes]]:
    """A formation of 12 at twice the cross-range error among 32 other aircraft, 180 s: the
    registration is known within the aid's limit before the end."""
    from topofusion_lab.evaluation import formation
    from topofusion_lab.scenarios.simulator import wire_messages

    point = next(p for p in formation.POINTS if p.label == "2x in traffic")
    return list(wire_messages(formation.scenario(point, 180.0, 12), 1))


@pytest.mark.slow
def test_the_aid_is_the_same_in_a_child_process_and_in_any_arrival_order(
    formation_in_traffic: list[tuple[str, bytes]],
) -> None:
    # a lag of one second: shorter than the batches of a burst of releases and than the child
    # process takes to answer, so without the engine's wait the aid would differ at every turn
    aided = _aided(EngineConfig(), lag_s=1.0)
    here, out_here = run_engine(formation_in_traffic, config=aided)
    plain, out_plain = run_engine(formation_in_traffic, config=without_aid(EngineConfig()))
    # the aid does something here: some plots went to other tracks, so other tracks and pairs;
    # /status counts the associations it decided, per radar
    assert here["tracks"] != plain["tracks"] and out_here != out_plain
    assert sum(r["aided_associations"] for r in here["radars"]) > 0
    assert all(r["aided_associations"] == 0 for r in plain["radars"])
    assert any(ps["pairs"] for ps in here["pairs"])
    # radars' batches interleaved otherwise on arrival, in bursts of some 20 s of data (within
    # the lag the release waits for, ``sequencer.max_lag_s``; longer than the aid's lag): the
    # engine correlates and waits for the answers through each batch's lag inside a burst, so
    # tracks and every output are the same, in the same order, here and with the correlation
    # in its own process (which answers later)
    sites = [m for m in formation_in_traffic if m[0].endswith("/site")]
    plots = [m for m in formation_in_traffic if m[0].endswith("/plots")]
    assert len(sites) + len(plots) == len(formation_in_traffic)
    shuffled = sites + [m for i in range(0, len(plots), 60) for m in interleaved(plots[i : i + 60], 3)]
    assert shuffled != formation_in_traffic
    again, out_again = run_engine(shuffled, config=aided)
    assert again == here and out_again == out_here
    child, out_child = run_engine(shuffled, process=True, config=aided)
    assert child == here and out_child == out_here


@pytest.mark.parametrize("process", [False, True])
def test_every_aided_batch_waits_for_the_answers_through_its_lag(
    formation_in_traffic: list[tuple[str, bytes]], process: bool
) -> None:
    # radar C silent for 20 s: the release holds the others until C's next batch, then lets
    # 20 s of them through at once, longer than the lag
    start = json.loads(formation_in_traffic[-1][1])["time_s"] - 180.0
    gap = [
        m
        for m in formation_in_traffic
        if not (m[0].endswith("C/plots") and 100.0 <= json.loads(m[1])["time_s"] - start < 120.0)
    ]
    assert len(gap) < len(formation_in_traffic)
    engine = Engine(_aided(EngineConfig()), correlation_process=process)
    try:
        aid = engine.aid
        assert aid is not None
        answered = aid.references
        seen: list[float] = []

        def checked(radar_id: str, time_s: float) -> Any:
            # every table up to the batch's lag is correlated and its answer taken
            through = engine.outputs_time_s
            assert through is not None and through >= aid.due_s(time_s), (radar_id, time_s)
            seen.append(time_s)
            return answered(radar_id, time_s)

        aid.references = checked  # type: ignore[method-assign]
        for key, payload in gap:
            engine.ingest(key, payload, receive_time_s=0.0)
        engine.flush()
        assert len(seen) > 100
    finally:
        engine.close()


def test_the_command_line_refuses_an_aid_without_a_lag_and_takes_it_partitioned() -> None:
    env = {
        **os.environ,
        "TOPOFUSION_ENGINE__TRACKING__AID__ENABLED": "true",
        "TOPOFUSION_PARTITION": "1/2",
    }
    got = subprocess.run(
        [sys.executable, "-m", "service", "config"], capture_output=True, text=True, env=env, timeout=60
    )
    assert got.returncode == 0, got.stderr
    env["TOPOFUSION_ENGINE__TRACKING__AID__LAG_S"] = "0"
    got = subprocess.run(
        [sys.executable, "-m", "service", "config"], capture_output=True, text=True, env=env, timeout=60
    )
    assert got.returncode == 2
    assert "tracking.aid.lag_s: 0.0 s; the aid needs a lag above zero" in got.stderr


def test_a_restarted_engine_aids_again_from_its_restored_registration() -> None:
    """The aid keeps no state of its own across a restart: the restored correlation (its
    registration memories) confirms pairs on the new tracks, and once answered they aid (in
    this formation in traffic, 300 s restarted at 150 s: from about 60 s after the restart,
    as from 140 s in the run without one)."""
    from topofusion_lab.evaluation import formation
    from topofusion_lab.scenarios.simulator import wire_messages

    point = next(p for p in formation.POINTS if p.label == "2x in traffic")
    stream = list(wire_messages(formation.scenario(point, 300.0, 12), 1))
    aided = _aided(EngineConfig())
    half = len(stream) // 2
    first = Engine(aided)
    try:
        for key, payload in stream[:half]:
            first.ingest(key, payload, receive_time_s=0.0)
        state = first.export_state()
    finally:
        first.close()
    again = Engine(aided)
    try:
        again.restore_state(state, 1)
        out = []
        for key, payload in stream[half:]:
            out += again.ingest(key, payload, receive_time_s=0.0)
        out += again.flush()
        assert not [o for o in out if o.key.endswith("/errors")]
        assert sum(r["aided_associations"] for r in again.snapshot().status()["radars"]) > 0
    finally:
        again.close()


@pytest.mark.slow
@pytest.mark.parametrize(("n", "seed", "lagging"), [(2, 0, None), (3, 1, 3)])
def test_partitioned_workers_aid_their_tracks_as_one_worker_does(
    formation_in_traffic: list[tuple[str, bytes]], n: int, seed: int, lagging: int | None
) -> None:
    """Each worker's trackers read every pair's links and registration, its own and the other
    workers', as one worker's do: every pair update is one worker's, also when one worker
    falls far behind (the others hold their batches until it has sent its links)."""
    aided = _aided(EngineConfig())
    one, single = run_one(formation_in_traffic, config=aided)
    plain, _ = run_one(formation_in_traffic, config=without_aid(EngineConfig()))
    assert one != plain  # (the aid changes the pairs here)
    assert sum(r["aided_associations"] for r in single.snapshot().status()["radars"]) > 0
    many, publishers, engines = run_partitioned(formation_in_traffic, n, seed, lagging=lagging, config=aided)
    assert sorted(many) == sorted(one)
    for key in one:
        assert len(publishers[key]) == 1
        # (at the end of the input the newest update of a pair may still be held back)
        assert len(one[key]) - 1 <= len(many[key]) <= len(one[key]), key
        assert many[key] == one[key][: len(many[key])], key
    owners = {Partition(1, n).owner(r) for r in "ABC"}
    assert len(owners) > 1  # (two workers track radars of one pair)
    aided_by = [sum(r["aided_associations"] for r in e.snapshot().status()["radars"]) for e in engines]
    assert sum(aided_by) > 0
    for engine in engines:
        assert engine.rejected == {}
        assert engine.peers.progress()["reordered"] == 0
    single.close()
    for engine in engines:
        engine.close()


def test_every_radar_is_read_as_it_was_at_the_crossing_in_release_order() -> None:
    """A radar's table, this worker's or another's: the latest recorded at or before the
    crossing read (data time, then radar id, as one worker releases them), whatever came since;
    before any, none."""
    stage = TrackingStage(lambda site, rid: None)  # type: ignore[arg-type,return-value]
    aid = PartnerAid(AidParams(enabled=True, lag_s=10.0), stage)
    sent = [(10.0, _table(B, ["B-1"], 1, 50.0)), (12.0, _table(B, ["B-2"], 2, 50.0))]
    sent += [(12.0, _table(B, ["B-3"], 3, 50.0)), (15.0, _table(B, ["B-4"], 4, 50.0))]
    for time_s, table in sent:
        aid.record("B", time_s, table)  # (all of them there before the batches: a worker ahead)
    crossings = [(9.0, "A"), (10.0, "A"), (10.0, "C"), (12.0, "A"), (12.0, "C"), (14.0, "Z"), (16.0, "A")]
    for crossing in crossings:
        aid.crossed(Crossing(crossing, ()))
    for batch_s in [19.0, 20.0, 21.0, 22.0, 23.9, 24.0, 26.0]:
        refs = aid.references("A", batch_s)
        assert refs is not None
        crossing = refs.crossing  # type: ignore[attr-defined]
        assert crossing == [c for c in crossings if c[0] <= batch_s - 10.0][-1]
        before = [t for time_s, t in sent if (time_s, "B") <= crossing]
        got = aid.table("B", crossing)[0]
        want = before[-1].track_id.tolist() if before else []
        assert got.track_id.tolist() == want, crossing
    aid.forget("B")
    assert len(aid.table("B", crossings[-1])[0]) == 0


@pytest.mark.parametrize("late_s", [0.0, 3.0])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_tables_kept_give_every_crossing_what_all_of_them_would(seed: int, late_s: float) -> None:
    """Tables recorded at every release of three radars, the crossings the first release of
    each cell of the grid (as the system stage finds them): at every batch, each radar's table
    read at its crossing is the latest of all that were recorded at or before it, although only
    each cell's last and its crossing's own are kept once the crossing is known, and the reads
    move on.  ``late_s``: radar C's tables come that much data time late, after their cell's
    crossing (another worker's, as sent), but within the lag."""
    rng = np.random.default_rng(seed)
    stage = TrackingStage(lambda site, rid: None)  # type: ignore[arg-type,return-value]
    aid = PartnerAid(AidParams(enabled=True, lag_s=5.0), stage, grid_s=2.0)
    times = np.sort(rng.uniform(0.0, 60.0, 300).round(1))  # (ties between radars too)
    releases = sorted({(float(t), str(rng.choice(["A", "B", "C"]))) for t in times})  # (one batch a place)
    recorded: list[tuple[tuple[float, str], str]] = []
    late: list[tuple[float, str, str, int]] = []
    next_cell = -np.inf
    read = kept = 0
    for k, (time_s, radar) in enumerate(releases):
        while late and late[0][0] <= time_s - late_s:
            t, other, name, j = late.pop(0)
            aid.record(other, t, _table(B, [name], j, 50.0, t))
        if k % 7 == 3:  # a batch of this radar asks before it is tracked
            refs = aid.references(radar, time_s)
            if refs is not None:
                crossing = refs.crossing  # type: ignore[attr-defined]
                for other in "ABC":
                    before = [name for place, name in recorded if place <= crossing and place[1] == other]
                    got = aid.table(other, crossing)[0].track_id.tolist()
                    assert got == before[-1:], (k, other, crossing)
                read += 1
        aid.passed((time_s, radar))
        name = f"{radar}-{k}"
        if radar == "C" and late_s > 0:
            late.append((time_s, radar, name, k))
        else:
            aid.record(radar, time_s, _table(B, [name], k, 50.0, time_s))
        recorded.append(((time_s, radar), name))
        if np.floor(time_s / 2.0) * 2.0 >= next_cell:  # (the system stage's rule)
            next_cell = np.floor(time_s / 2.0) * 2.0 + 2.0
            aid.crossed(Crossing((time_s, radar), ()))
        kept = max(kept, sum(len(q) for q in aid._tables.values()))
    assert read > 30
    # (what a read may still need: about one table per radar and cell over lag_s and a grid
    # step, 3 radars x 5 cells, and a cell's first while its crossing is unknown; every
    # cell's first and last, as kept before: 22-26)
    assert kept <= 20, kept


def test_a_worker_waits_for_the_others_only_through_its_lag(
    formation_in_traffic: list[tuple[str, bytes]],
) -> None:
    """Partitioned, a batch at ``t`` waits for the other workers' tables and links through
    ``t - lag_s`` only, not up to ``t``: the workers track up to ``lag_s`` apart, not in step."""
    engine = Engine(replace(_aided(EngineConfig()), partition=Partition(1, 2)))
    lag = engine.config.tracking.aid.lag_s
    key = Keys("fusion").worker_progress(2)
    told = -np.inf
    try:
        for k, (topic, payload) in enumerate(formation_in_traffic):
            if topic.endswith("/plots") and k % 25 == 0:
                told = json.loads(payload)["time_s"] - lag - 5.0  # (worker 2: 5 s short of it)
                body = {"partition": "2/2", "released_s": told, "correlated_s": told}
                engine.ingest(key, json.dumps(body).encode())
            engine.ingest(topic, payload, receive_time_s=0.0)
        assert engine.rejected == {}
        asking = [r for r in engine._held if engine._asks_aid(r)]
        assert asking, "no batch waits"  # (the aid is asked for here)
        # a batch waits only while its lag reaches past what worker 2 said ...
        assert all(r.time_s - lag > told for r in asking)
        # ... and batches after the place worker 2 has reached were tracked all the same
        tracked = [r.time_s for r in engine.tracking.tracked.values() if r.time_s is not None]
        assert max(tracked) > told + 0.5 * lag
    finally:
        engine.close()


def test_a_partitioned_worker_holds_its_batches_until_the_others_are_through_or_gone(
    formation_in_traffic: list[tuple[str, bytes]],
) -> None:
    """No other worker's progress yet: the batches wait, counted in ``/status``, and the
    progress says so; the other worker gone, they are tracked."""
    engine = Engine(replace(_aided(EngineConfig()), partition=Partition(1, 2)))
    try:
        out = []
        for key, payload in formation_in_traffic[:200]:
            out += engine.ingest(key, payload, receive_time_s=0.0)
        progress = engine.peers.progress()
        assert progress["aid_held"] > 0 and engine.snapshot().progress == progress
        sent = [json.loads(o.payload) for o in out if o.key == Keys("fusion").worker_progress(1)]
        held = engine._held[0]
        assert sent and sent[-1]["held"] == [held.time_s, held.source_id]
        assert sent[-1]["released_s"] < held.time_s
        tracked_before = sum(len(r.table) for r in engine.tracking.tracked.values())
        engine.wait_for({1})
        assert engine.peers.progress()["aid_held"] == 0
        assert sum(len(r.table) for r in engine.tracking.tracked.values()) > tracked_before
    finally:
        engine.close()


def test_a_worker_holds_a_bounded_number_of_batches_for_a_worker_that_does_not_progress(
    formation_in_traffic: list[tuple[str, bytes]], monkeypatch: pytest.MonkeyPatch
) -> None:
    import service.engine

    monkeypatch.setattr(service.engine, "MAX_AID_HELD", 8)
    engine = Engine(replace(_aided(EngineConfig()), partition=Partition(1, 2)))
    try:
        for key, payload in formation_in_traffic[:300]:
            engine.ingest(key, payload, receive_time_s=0.0)
            assert engine.peers.progress()["aid_held"] <= 8
        progress = engine.peers.progress()
        assert progress["aid_forced"] > 0 and progress["aid_held"] == 8
        assert sum(len(r.table) for r in engine.tracking.tracked.values()) > 0
    finally:
        engine.close()


def test_only_a_batch_that_may_ask_waits_and_every_batch_that_asks_was_waited_for(
    formation_in_traffic: list[tuple[str, bytes]],
) -> None:
    """A batch waits for what the aid reads only if its tracker may ask (a track in a
    formation, or the search for formations due): every batch whose tracker asked had said
    so before it, and the others go through without waiting."""
    engine = Engine(_aided(EngineConfig()))
    stage = engine.tracking
    wanted: list[bool] = []
    asked: list[bool] = []
    update = stage.update

    def watched(radar_id: str, plots: Any, time_s: float, aid: Any = None) -> Any:
        wanted.append(stage.wants_aid(radar_id, time_s))
        calls = [0]

        def counted(track_ids: Any, times_s: Any, spread: Any) -> Any:
            calls[0] += 1
            if aid is not None:
                return aid(track_ids, times_s, spread)
            n = track_ids.shape[0]  # (not asked for: a tracker that asks anyway is caught here)
            return np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)

        out = update(radar_id, plots, time_s, counted)
        asked.append(calls[0] > 0)
        return out

    stage.update = watched  # type: ignore[method-assign]
    try:
        for key, payload in formation_in_traffic:
            engine.ingest(key, payload, receive_time_s=0.0)
    finally:
        engine.close()
    assert sum(asked) > 20 and all(w for w, a in zip(wanted, asked, strict=True) if a)
    assert 0 < sum(wanted) < len(wanted)
    # the rule itself: a batch at which the search for formations is due may ask whatever the
    # formations were (the search comes before the assignment); between searches, only a
    # tracker with a track in a formation
    tracker = stage.tracked["A"].tracker
    inner = getattr(tracker, "inner", tracker)
    scan_s = inner.scan_period_s * inner.params.formation.formation_interval_scans
    last = inner._formations_s
    tracks = inner._tracks
    assert len(tracks)
    inner._tracks = replace(tracks, formation=np.full(len(tracks), -1))
    assert tracker.wants_aid(last + scan_s) and not tracker.wants_aid(last + 0.5 * scan_s)
    inner._tracks = replace(tracks, formation=np.where(np.arange(len(tracks)) == 0, 3, -1))
    assert tracker.wants_aid(last + 0.5 * scan_s)
    # with the formation rule off no tracker ever asks: a partitioned worker holds nothing,
    # though no other worker has said how far it is
    rule = replace(EngineConfig().tracking.formation, hold_formations=False)
    tracking = replace(EngineConfig().tracking, formation=rule)
    off = Engine(replace(_aided(replace(EngineConfig(), tracking=tracking)), partition=Partition(1, 2)))
    try:
        for key, payload in formation_in_traffic[:300]:
            off.ingest(key, payload, receive_time_s=0.0)
        assert off.peers.progress()["aid_held"] == 0
        assert sum(len(r.table) for r in off.tracking.tracked.values()) > 0
    finally:
        off.close()
