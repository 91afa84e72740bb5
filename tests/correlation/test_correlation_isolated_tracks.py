"""Tracks without any neighbour in one radar's picture (sparse traffic, the first scans of a
stream, a neighbour only one radar sees) are a normal case for every method: an update gives
"no decision" values, never an exception; and aircraft alone in both pictures are paired
before any registration (the lone rule, ``SvdTopologyParams.lone_pairs``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.correlation import METHODS, PairCorrelator
from service.correlation.candidates import candidate_pairs
from service.correlation.correlator import CorrelationParams
from service.correlation.prediction import predict_tracks
from service.correlation.svd_topology import SvdTopologyParams, lone_candidates
from service.geo import Site
from service.tracking.base import TrackTable
from tests.reference_forms import lone_reference
from topofusion_lab.evaluation.correlation_scenario import make_sites, sample_references


def _table(
    site: Site,
    truth: np.ndarray,
    prefix: str,
    velocity: np.ndarray | None = None,
    bias: float = 0.1,
    time_s: float = 0.0,
) -> TrackTable:
    n = len(truth)
    r, az, el = site.ecef_to_polar(truth)
    pos = site.polar_to_ecef(r + 100.0, az + bias, el)  # a bias, no noise
    cov = np.broadcast_to(np.diag([200.0**2] * 3 + [10.0**2] * 3), (n, 6, 6)).copy()
    return TrackTable(
        np.array([f"{prefix}{i}" for i in range(n)]),
        np.ones(n, dtype=bool),
        np.full(n, time_s),
        pos,
        np.zeros((n, 3)) if velocity is None else np.broadcast_to(velocity, (n, 3)).copy(),
        cov,
        np.full(n, 10, dtype=np.int64),
        np.full(n, None, dtype=object),
    )


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("count", [1, 2])
def test_isolated_common_tracks_do_not_raise(method: str, count: int) -> None:
    a, b = make_sites()
    rng = np.random.default_rng(4)
    truth = sample_references(rng, a, b, 50)[:: 50 // count][:count]  # far apart: no neighbours
    # radar A also sees a neighbour 3 km east of each target that B misses: A's sequences have
    # one element, B's none
    east = a.rotation[:, 0]
    seen_by_a = np.concatenate([truth, truth + 3_000.0 * east])
    corr = PairCorrelator(method, a, b)
    for k in range(3):
        corr.update(_table(a, seen_by_a, "a"), _table(b, truth, "b"), 1.0 + k)
    for p in corr.pairs():  # whatever was decided is one-to-one and well formed
        assert p.track_a.startswith("a") and p.track_b.startswith("b")


def _lone_scene(count: int) -> tuple[Site, Site, np.ndarray, np.ndarray, np.ndarray]:
    """``count`` aircraft far apart (no neighbour within the topology's reach) in the overlap
    of two radars, flying east at 220 m/s; radar A also sees a second aircraft 4 km east of the
    first that B misses."""
    a, b = make_sites()
    rng = np.random.default_rng(7)
    refs = sample_references(rng, a, b, 400)
    truth = [refs[0]]
    for p in refs[1:]:  # greedy: every aircraft at least 70 km from the others
        if len(truth) < count and all(np.linalg.norm(p - q) > 70_000.0 for q in truth):
            truth.append(p)
    truth_arr = np.array(truth)
    assert len(truth_arr) == count
    east = a.rotation[:, 0]
    seen_by_a = np.concatenate([truth_arr, truth_arr[:1] + 4_000.0 * east])
    return a, b, truth_arr, seen_by_a, 220.0 * east


@pytest.mark.parametrize("lone", [True, False])
def test_lone_aircraft_are_paired_before_any_registration(lone: bool) -> None:
    """Aircraft tens of km apart have no neighbourhood for the topology match, and before a
    registration nothing else decides them: the lone rule pairs each aircraft that is the only
    candidate of its two tracks with no other track of either radar near it, not in the pair's
    first ``lone_after_scans`` scans (the tables may still be filling), then after the book's M
    of N (never at the first look), and not the one next to a track only radar A sees.  Off,
    none is paired."""
    a, b, truth, seen_by_a, vel = _lone_scene(4)
    params = CorrelationParams(svd=replace(SvdTopologyParams(), lone_pairs=lone))
    wait_s = params.svd.lone_after_scans * max(a.scan_period_s, b.scan_period_s)
    corr = PairCorrelator("svd-topology", a, b, params)
    confirmed: dict[float, set[tuple[str, str]]] = {}
    for k in range(12):
        t = 100.0 + 0.5 * a.scan_period_s * k
        ta = _table(a, seen_by_a + vel * t, "a", vel, time_s=t)
        corr.update(ta, _table(b, truth + vel * t, "b", vel, bias=-0.15, time_s=t), t)
        confirmed[t - 100.0] = {(p.track_a, p.track_b) for p in corr.pairs() if p.status == "confirmed"}
    assert not corr.registered
    if lone:
        assert confirmed[max(confirmed)] == {(f"a{i}", f"b{i}") for i in range(1, len(truth))}
        waited = [t for t in confirmed if t >= wait_s]
        assert waited and not any(confirmed[t] for t in confirmed if t <= waited[0])
        for p in corr.pairs():  # as published: the topology's basis, no fit to report
            assert p.basis == "topology" and p.neighbors == 0, p
            assert np.isnan(p.rotation_weight) and np.isnan(p.scale), p
    else:
        assert all(c == set() for c in confirmed.values())


def test_lone_rule_needs_agreeing_velocities() -> None:
    """An aircraft alone in both pictures whose two tracks fly different headings is not one
    aircraft: not paired (the velocity gate, before any decision)."""
    a, b, truth, _, vel = _lone_scene(3)
    north = a.rotation[:, 1]
    corr = PairCorrelator("svd-topology", a, b)
    for k in range(12):
        t = 100.0 + 0.5 * a.scan_period_s * k
        ta = _table(a, truth + vel * t, "a", vel, time_s=t)
        corr.update(ta, _table(b, truth + vel * t, "b", 220.0 * north, time_s=t), t)
    assert [p for p in corr.pairs() if p.status == "confirmed"] == []


def test_lone_candidates_match_the_plain_form() -> None:
    """The vectorised geometry of the lone rule against a loop, in a scene with lone aircraft,
    pairs and crowds, half of them flying north and half east (a track of another velocity is
    no rival); with few tracks (all distances) and with many (a k-d tree)."""
    a, b = make_sites()
    rng = np.random.default_rng(11)
    east, north = a.rotation[:, 0], a.rotation[:, 1]
    wants, ones = [], []
    for n in (12, 400):
        base = sample_references(rng, a, b, n)
        pos_a = base + rng.normal(0.0, 3_000.0, base.shape)
        pos_b = base + rng.normal(0.0, 3_000.0, base.shape)
        heading = rng.integers(0, 2, n)[:, None]
        vel = 220.0 * np.where(heading == 1, east, north)
        ta, tb = _table(a, pos_a, "a", vel), _table(b, pos_b, "b", vel)
        pa = predict_tracks(ta, a, 0.0)
        pb = predict_tracks(tb, b, 0.0)
        gate, radius = 10_000.0, 20_000.0
        prm = replace(SvdTopologyParams(), lone_radius_m=radius)
        ia, ib, _ = candidate_pairs(pa.position, pb.position, gate)
        # (each with a neighbour its topology fit paired: the geometry alone decides)
        got = lone_candidates(pa, pb, ia, ib, np.ones(len(ia), dtype=np.int64), prm)
        pairs = list(zip(ia.tolist(), ib.tolist(), strict=True))
        want = lone_reference(
            pa, pb, pairs, gate, radius, prm.max_bias_rotation_deg, prm.velocity_prefilter_alpha
        )
        assert got.tolist() == want
        wants += want
        # the same geometry if every velocity could be every other's
        ones += lone_reference(pa, pb, pairs, gate, radius, 180.0, 1e-300)
    assert any(wants) and not all(wants)
    assert wants != ones  # (the velocities decided some)


def _run_pair(seen_a: np.ndarray, seen_b: np.ndarray, vel: np.ndarray, tentative_a: int | None = None) -> set:
    """The confirmed pairs after 14 updates a scan apart (past the lone rule's wait) of radar A
    seeing ``seen_a`` and B ``seen_b`` (row ``tentative_a`` of A tentative), not registered."""
    a, b = make_sites()
    corr = PairCorrelator("svd-topology", a, b)
    for k in range(14):
        t = 100.0 + a.scan_period_s * k
        ta = _table(a, seen_a + vel * t, "a", vel, time_s=t)
        if tentative_a is not None:
            confirmed = np.ones(len(seen_a), dtype=bool)
            confirmed[tentative_a] = False
            ta = replace(ta, confirmed=confirmed)
        corr.update(ta, _table(b, seen_b + vel * t, "b", vel, bias=-0.15, time_s=t), t)
    assert not corr.registered
    return {(p.track_a, p.track_b) for p in corr.pairs() if p.status == "confirmed"}


def test_two_neighbourhoods_with_nothing_in_common_are_not_one_lone_aircraft() -> None:
    """Aircraft X seen by A only and Y, 6 km from it at its velocity, by B only: each is the
    other's only candidate, but each radar also sees two aircraft 25-45 km away that the other
    does not, so the topology compares two neighbourhoods and finds not one neighbour in
    common: evidence against the pair, which the lone rule must not override (nor can it
    tell X seen by both radars there: the rule's price).  With one aircraft 20 km away that
    both radars see, X seen by both is paired (the fit pairs that neighbour, too few to
    decide) and X against Y is not (6 km off, the neighbour does not pair)."""
    a, b = make_sites()
    r0 = sample_references(np.random.default_rng(7), a, b, 400)[0]
    east, north = a.rotation[:, 0], a.rotation[:, 1]
    only_a = [r0 - 25_000 * north, r0 - 40_000 * north + 5_000 * east]
    only_b = [r0 + 30_000 * north, r0 + 45_000 * north - 5_000 * east]
    vel = 220.0 * east
    x, y = r0, r0 + 6_000 * north
    assert ("a0", "b0") not in _run_pair(np.array([x, *only_a]), np.array([y, *only_b]), vel)
    assert ("a0", "b0") not in _run_pair(np.array([x, *only_a]), np.array([x, *only_b]), vel)
    both = r0 + 20_000 * east
    assert ("a0", "b0") not in _run_pair(np.array([x, both, *only_a]), np.array([y, both, *only_b]), vel)
    assert ("a0", "b0") in _run_pair(np.array([x, both, *only_a]), np.array([x, both, *only_b]), vel)


@pytest.mark.parametrize("crossing", [True, False])
def test_two_aircraft_a_few_km_apart_are_each_alone_when_their_velocities_differ(crossing: bool) -> None:
    """Two aircraft 5 km apart (2-8 km through the run), both seen by both radars, no third
    within the topology's reach (one neighbour: too few for a fit).  Flying headings 30 deg
    apart, each track's only velocity-compatible candidate is its aircraft's other track and
    no track of its own radar flies with it: both are paired by the lone rule.  Flying one
    velocity, either track of one radar could be either aircraft's before a registration:
    neither pair."""
    a, b = make_sites()
    r0 = sample_references(np.random.default_rng(7), a, b, 400)[0]
    east, north = a.rotation[:, 0], a.rotation[:, 1]
    turned = np.cos(np.radians(30.0)) * east + np.sin(np.radians(30.0)) * north
    vel = np.array([220.0 * east, 220.0 * (turned if crossing else east)])
    mid_s = 100.0 + 6.5 * a.scan_period_s  # (the middle of _run_pair's updates)
    seen = np.array([r0, r0 + 5_000.0 * north]) - vel * mid_s
    pairs = _run_pair(seen, seen, vel)
    assert pairs == ({("a0", "b0"), ("a1", "b1")} if crossing else set())


def test_a_tentative_track_near_a_lone_one_holds_its_pair_back() -> None:
    """The method sees confirmed tracks only: a tentative track of radar A 6 km from a lone
    aircraft's A track (a second aircraft being confirmed) keeps the pair undecided; the other
    lone aircraft are paired."""
    _, _, truth, _, vel = _lone_scene(3)
    a, _ = make_sites()
    seen_a = np.concatenate([truth, truth[:1] + 6_000.0 * a.rotation[:, 1]])
    held = _run_pair(seen_a, truth, vel, tentative_a=len(truth))
    assert held == {(f"a{i}", f"b{i}") for i in range(1, len(truth))}
    assert ("a0", "b0") in _run_pair(truth, truth, vel)  # without it, paired


@pytest.mark.parametrize("min_track_pairs", [10, 0])
def test_thin_traffic_registers_from_aircraft_seen_one_after_another(min_track_pairs: int) -> None:
    """Aircraft far apart, at most three in both pictures at once, a new one every 40 s for
    eight minutes: the radar pair never holds ``registration.min_pairs`` (6) confirmed pairs at
    once, yet its memory gathers the rows of a dozen aircraft.  With
    ``registration.min_track_pairs`` (10 distinct track pairs among the rows its solve kept) it
    registers, and the aircraft after that are decided by the compensated test (published
    ``basis`` ``registered`` or ``history``, no longer ``topology``); with 0 it never does."""
    a, b = make_sites()
    refs = sample_references(np.random.default_rng(3), a, b, 600)
    spots: list[np.ndarray] = []
    for p in refs:  # greedy: every aircraft at least 70 km from the others
        if len(spots) < 14 and all(np.linalg.norm(p - q) > 70_000.0 for q in spots):
            spots.append(p)
    assert len(spots) == 14
    vel = 220.0 * a.rotation[:, 0]
    params = CorrelationParams()
    params = replace(params, registration=replace(params.registration, min_track_pairs=min_track_pairs))
    corr = PairCorrelator("svd-topology", a, b, params)
    seen_registered = None
    for k in range(130):
        t = 100.0 + a.scan_period_s * k
        live = [i for i in range(len(spots)) if 40.0 * i <= t - 100.0 < 40.0 * i + 120.0]
        truth = np.array([spots[i] for i in live]) + vel * (t - 100.0)
        ids_a = np.array([f"a{i}" for i in live])
        ids_b = np.array([f"b{i}" for i in live])
        ta = replace(_table(a, truth, "a", vel, time_s=t), track_id=ids_a)
        tb = replace(_table(b, truth, "b", vel, bias=-0.15, time_s=t), track_id=ids_b)
        corr.update(ta, tb, t)
        confirmed = [p for p in corr.pairs() if p.status == "confirmed"]
        assert len(confirmed) <= 3
        assert all(p.track_a[1:] == p.track_b[1:] for p in confirmed)  # never a false pair
        if corr.registered and seen_registered is None:
            seen_registered = t
    last = [p for p in corr.pairs() if p.status == "confirmed"]
    assert last
    if min_track_pairs:
        assert seen_registered is not None and seen_registered < 100.0 + 40.0 * 11
        assert all(p.basis in ("registered", "history") for p in last)
    else:
        assert seen_registered is None
        assert all(p.basis == "topology" for p in last)
