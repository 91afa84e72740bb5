"""System tracks (service/fusion/system_tracks.py): groups, numbers and fused states, against
plain reference forms and on cases whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from service.fusion.system_tracks import Members, SystemTracker, SystemTrackParams, diverged, fuse, groups
from tests.reference_forms import diverged_reference, fuse_reference, system_groups_reference


def members(
    source: list[str], track: list[str], reference: list[bool] | None = None, seed: int = 0
) -> Members:
    rng = np.random.default_rng(seed)
    n = len(source)
    a = rng.normal(size=(n, 3, 3))
    # (errors of a few hundred metres, as radar tracks have: members 100 m apart agree)
    cov = a @ np.swapaxes(a, 1, 2) * 1e4 + np.eye(3) * 5e3
    return Members(
        source=np.array(source, dtype=str),
        track_id=np.array(track, dtype=str),
        reference=np.array(reference or [False] * n, dtype=bool),
        confirmed=np.ones(n, dtype=bool),
        position=rng.normal(size=(n, 3)) * 100.0,
        velocity=rng.normal(size=(n, 3)) * 10.0,
        pos_cov=cov,
        vel_cov=cov / 100.0,
    )


def test_groups_equal_the_plain_form_on_random_graphs() -> None:
    rng = np.random.default_rng(1)
    for _ in range(200):
        n = int(rng.integers(1, 25))
        source = rng.integers(0, 4, n)
        m = int(rng.integers(0, 2 * n))
        a, b = rng.integers(0, n, m), rng.integers(0, n, m)
        keep = source[a] != source[b]  # links join tracks of two sources
        a, b = a[keep], b[keep]
        score = rng.choice([0.5, 0.7, 0.9, 0.99], a.shape[0])  # ties too
        got = groups(n, source.astype(np.int64), a.astype(np.int64), b.astype(np.int64), score)
        want = system_groups_reference(
            n, source.tolist(), list(zip(a.tolist(), b.tolist(), score.tolist(), strict=True))
        )
        assert got.tolist() == want


def test_a_chain_through_two_tracks_of_one_radar_loses_its_weakest_link() -> None:
    # A1 - B1 - A2: B1 goes with the stronger of its two links
    got = groups(3, np.array([0, 1, 0]), np.array([0, 1]), np.array([1, 2]), np.array([0.6, 0.95]))
    assert got.tolist() == [0, 1, 1]


def test_fusion_equals_the_plain_form() -> None:
    m = members(
        ["A", "B", "C", "ads", "A", "B"],
        ["1", "1", "1", "x", "2", "2"],
        [False, False, False, True, False, False],
    )
    group = np.array([0, 0, 0, 0, 1, 1])
    pos, vel, pos_cov, vel_cov = fuse(m, group, 2)
    for g in range(2):
        rows = np.flatnonzero(group == g)
        ref = [bool(m.reference[k]) for k in rows]
        x, p = fuse_reference([m.position[k] for k in rows], [m.pos_cov[k] for k in rows], ref)
        np.testing.assert_allclose(pos[g], x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(pos_cov[g], p, rtol=1e-9, atol=1e-9)
        v, pv = fuse_reference([m.velocity[k] for k in rows], [m.vel_cov[k] for k in rows], ref)
        np.testing.assert_allclose(vel[g], v, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(vel_cov[g], pv, rtol=1e-9, atol=1e-9)


def test_covariance_intersection_is_consistent_with_correlated_members() -> None:
    """Two radars whose errors share a common part (correlation 0.8): the CI covariance covers
    the real error of the fused state, where information-form fusion would not."""
    rng = np.random.default_rng(2)
    sigma, rho, n = 100.0, 0.8, 20_000
    common = rng.normal(size=(n, 3)) * sigma * np.sqrt(rho)
    own = rng.normal(size=(2, n, 3)) * sigma * np.sqrt(1 - rho)
    err = common[None] + own  # (2, n, 3): each radar's error
    cov = np.eye(3) * sigma**2
    m = Members(
        source=np.array(["A", "B"] * n),
        track_id=np.arange(2 * n).astype(str),
        reference=np.zeros(2 * n, dtype=bool),
        confirmed=np.ones(2 * n, dtype=bool),
        position=np.swapaxes(err, 0, 1).reshape(-1, 3),
        velocity=np.zeros((2 * n, 3)),
        pos_cov=np.broadcast_to(cov, (2 * n, 3, 3)).copy(),
        vel_cov=np.broadcast_to(cov, (2 * n, 3, 3)).copy(),
    )
    pos, _, pos_cov, _ = fuse(m, np.repeat(np.arange(n), 2), n)
    nees = np.einsum("ni,nij,nj->n", pos, np.linalg.inv(pos_cov), pos).mean() / 3.0
    assert nees <= 1.05  # consistent (information form: (1 + rho) = 1.8)


def test_numbers_follow_the_aircraft_and_are_never_reused() -> None:
    tracker = SystemTracker()
    m1 = members(["A", "B", "A"], ["1", "7", "2"])
    s1 = tracker.update(m1, np.array([0]), np.array([1]), np.array([0.9]))
    assert s1.number.tolist() == [1, 2]  # {A1, B7}, {A2}
    assert s1.member_group.tolist() == [0, 0, 1]
    # B7 is now seen with A2, A1 is gone, a C track joins: numbers stay with their members
    m2 = members(["B", "A", "C"], ["7", "2", "3"])
    s2 = tracker.update(m2, np.array([0, 0]), np.array([1, 2]), np.array([0.9, 0.9]))
    # {B7, A2, C3}: B7 had 1, A2 had 2 -> tie, the oldest (1) stays; 2 is not reused later
    assert s2.number.tolist() == [1]
    m3 = members(["A", "B"], ["2", "9"])
    s3 = tracker.update(m3, np.array([], dtype=np.int64), np.array([], dtype=np.int64), np.array([]))
    assert s3.number.tolist() == [1, 3]  # A2 keeps 1; B9 is new: 3, not 2
    m4 = members(["A", "B", "C"], ["2", "9", "4"])
    s4 = tracker.update(m4, np.array([], dtype=np.int64), np.array([], dtype=np.int64), np.array([]))
    assert s4.number.tolist() == [1, 3, 4]  # C4 is new: the next number, 4


def test_a_split_keeps_the_number_with_the_larger_part() -> None:
    tracker = SystemTracker()
    m = members(["A", "B", "C"], ["1", "1", "1"])
    tracker.update(m, np.array([0, 1]), np.array([1, 2]), np.array([0.9, 0.9]))
    s = tracker.update(m, np.array([0]), np.array([1]), np.array([0.9]))  # C1 leaves the group
    assert s.number.tolist() == [1, 2]
    assert s.member_group.tolist() == [0, 0, 1]


def test_a_reference_alone_is_no_system_track_and_status_follows_members() -> None:
    tracker = SystemTracker()
    m = members(["A", "ads", "ads"], ["1", "x", "y"], [False, True, True])
    m = Members(**{**m.__dict__, "confirmed": np.array([False, True, True])})
    s = tracker.update(m, np.array([0]), np.array([1]), np.array([0.9]))
    assert s.member_group.tolist() == [0, 0, -1]
    assert s.confirmed.tolist() == [True]
    assert s.position_sigma_m()[0] == pytest.approx(np.sqrt(np.trace(s.pos_cov[0]) / 3))


def test_no_members_or_only_unlinked_references_give_no_system_track() -> None:
    tracker = SystemTracker()
    empty = np.empty(0, dtype=np.int64)
    for m in (members([], []), members(["ads", "ads"], ["x", "y"], [True, True])):
        s = tracker.update(m, empty, empty, np.empty(0))
        assert len(s) == 0 and s.member_group.tolist() == [-1] * len(m)


def test_a_young_lone_track_near_a_system_track_without_its_radar_waits() -> None:
    """A radar's new track of an aircraft another system track holds stays tentative until it
    is linked or has stood alone ``solo_hold_s``; a lone track elsewhere, or next to a system
    track that has a track of its radar, is confirmed at once."""
    tracker = SystemTracker(SystemTrackParams(solo_hold_s=60.0, solo_gate_m=5_000.0))
    m = members(["A", "B", "C", "C", "A"], ["1", "1", "1", "2", "2"])
    pos = np.array([[0.0, 0, 0], [100, 0, 0], [1_000, 0, 0], [50_000, 0, 0], [-4_500, 0, 0]])
    m = Members(**{**m.__dict__, "position": pos})
    link = (np.array([0]), np.array([1]), np.array([0.9]))
    s = tracker.update(m, *link, time_s=0.0)
    # groups: {A1, B1}, {C1} near it without C -> held, {C2} far -> confirmed, {A2} near but A there
    by_member = {
        k: bool(s.confirmed[g]) for k, g in zip(["A1", "B1", "C1", "C2", "A2"], s.member_group, strict=True)
    }
    assert by_member == {"A1": True, "B1": True, "C1": False, "C2": True, "A2": True}
    s = tracker.update(m, *link, time_s=59.0)
    assert not s.confirmed[s.member_group[2]]
    s = tracker.update(m, *link, time_s=60.0)  # stood alone long enough
    assert s.confirmed[s.member_group[2]]


def test_two_young_lone_tracks_of_one_new_aircraft_do_not_hold_each_other_back() -> None:
    tracker = SystemTracker(SystemTrackParams(solo_hold_s=60.0, solo_gate_m=5_000.0))
    m = members(["A", "B"], ["1", "1"])
    m = Members(**{**m.__dict__, "position": np.array([[0.0, 0, 0], [800.0, 0, 0]])})
    empty = np.empty(0, dtype=np.int64)
    s = tracker.update(m, empty, empty, np.empty(0), time_s=100.0)
    assert s.confirmed.tolist() == [True, False]  # one stands (the lower group), one waits


def test_diverged_links_equal_the_plain_form() -> None:
    rng = np.random.default_rng(5)
    m = members([f"S{k % 4}" for k in range(40)], [str(k) for k in range(40)], seed=5)
    m = Members(**{**m.__dict__, "position": rng.normal(size=(40, 3)) * 600.0})  # some apart
    a, b = rng.integers(0, 40, 300), rng.integers(0, 40, 300)
    got = diverged(m, a.astype(np.int64), b.astype(np.int64), 1e-6)
    want = diverged_reference(m.position, m.pos_cov, list(zip(a.tolist(), b.tolist(), strict=True)), 1e-6)
    assert got.tolist() == want and 0 < sum(want) < len(want)
    assert not diverged(m, a.astype(np.int64), b.astype(np.int64), 0.0).any()  # the rule off


def test_a_system_track_whose_members_diverge_splits() -> None:
    """A1-B1 and A2-B2 fused; then B2 is 5 km from A2 (a track swapped onto another aircraft,
    its pair not yet dropped): the system track splits at that update, A2 keeping its number
    (a tie of one member each: the lower member row), B2 taking a new one; with the rule off it
    stays fused."""
    base = members(["A", "B", "A", "B"], ["1", "1", "2", "2"])
    cov = np.broadcast_to(np.eye(3) * 200.0**2, (4, 3, 3)).copy()  # 200 m per axis
    together = np.array([[0.0, 0, 0], [150, 0, 0], [10_000, 0, 0], [10_100, 0, 0]])
    apart = together + np.array([[0.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 5_000, 0]])
    links = (np.array([0, 2]), np.array([1, 3]), np.array([0.95, 0.95]))
    for alpha, groups_after in ((1e-6, 3), (0.0, 2)):
        tracker = SystemTracker(SystemTrackParams(split_alpha=alpha))
        s = tracker.update(Members(**{**base.__dict__, "position": together, "pos_cov": cov}), *links)
        assert s.number.tolist() == [1, 2]
        s = tracker.update(Members(**{**base.__dict__, "position": apart, "pos_cov": cov}), *links)
        assert len(s) == groups_after
        if alpha:
            assert s.member_group[2] != s.member_group[3]
            assert s.number[s.member_group[0]] == s.number[s.member_group[1]] == 1
            assert (s.number[s.member_group[2]], s.number[s.member_group[3]]) == (2, 3)
