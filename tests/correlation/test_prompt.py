"""Clear decisions (service/correlation/prompt.py): the vectorised rules against plain loops,
and a clear new pair confirmed at its first update while an ambiguous one waits."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.correlation.correlator import _within
from service.correlation.pairs import PairBook
from service.correlation.prompt import DENSE_PAIRS, clear_of_rivals, isolated
from service.geo import Site
from service.tracking.base import TrackTable
from tests.reference_forms import clear_reference, isolated_reference, within_reference


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(0, 4),
            st.integers(0, 4),
            st.one_of(st.floats(-10, 40), st.just(float("inf"))),
            st.booleans(),
        ),
        max_size=12,
        unique_by=lambda t: (t[0], t[1]),
    ),
    st.sampled_from([0.0, 6.0, 12.0]),
)
def test_clear_of_rivals_equals_the_loop(cands: list[tuple[int, int, float, bool]], margin: float) -> None:
    ia = np.array([c[0] for c in cands], dtype=np.intp)
    ib = np.array([c[1] for c in cands], dtype=np.intp)
    cost = np.array([c[2] for c in cands], dtype=float)
    ok = np.array([c[3] for c in cands], dtype=bool)
    got = clear_of_rivals(ia, ib, cost, ok, margin)
    assert got.tolist() == clear_reference(ia.tolist(), ib.tolist(), cost.tolist(), ok.tolist(), margin)


def _table(pos: np.ndarray, confirmed: np.ndarray, vel: np.ndarray | None = None) -> TrackTable:
    n = len(pos)
    return TrackTable(
        np.array([f"t{i:03d}" for i in range(n)]),
        confirmed,
        np.zeros(n),
        pos,
        np.zeros((n, 3)) if vel is None else vel,
        np.broadcast_to(np.eye(6), (n, 6, 6)).copy(),
        np.full(n, 5, dtype=np.int64),
        np.full(n, None, dtype=object),
    )


@pytest.mark.parametrize("seed", range(6))
def test_isolated_equals_the_loop(seed: int) -> None:
    rng = np.random.default_rng(seed)
    site = Site("R", 46.0, 2.0)
    enu = rng.uniform(-12_000, 12_000, (30, 3)) * [1, 1, 0.1] + [0, 80_000, 9_000]
    pos = site.enu_to_ecef(enu)
    heading = rng.choice([0.0, 0.1, 2.0], 30)  # most fly together, some cross
    vel = np.stack([220 * np.sin(heading), 220 * np.cos(heading), np.zeros(30)], axis=1) @ site.rotation.T
    confirmed = rng.random(30) < 0.6
    table = _table(pos, confirmed, vel)
    rows = list(range(0, 30, 3))
    got = isolated(table, site, 0.0, table.track_id[rows], 2_000.0, 40.0)
    want = isolated_reference(pos, vel, confirmed.tolist(), site.rotation[:, 2], rows, 2_000.0, 40.0)
    assert got.tolist() == want
    assert (~confirmed).any()  # (both kinds of neighbour are in the scene)


@pytest.mark.parametrize("seed", range(3))
def test_isolated_of_a_whole_table_equals_the_loop(seed: int) -> None:
    """A radar's whole table at its update (the k-d tree form, above ``DENSE_PAIRS``),
    with a track of unknown position among them."""
    rng = np.random.default_rng(seed)
    site = Site("R", 46.0, 2.0)
    n = 220
    enu = rng.uniform(-40_000, 40_000, (n, 3)) * [1, 1, 0.05] + [0, 120_000, 9_000]
    pos = site.enu_to_ecef(enu)
    pos[7] = np.nan
    heading = rng.choice([0.0, 0.1, 2.0], n)
    vel = np.stack([220 * np.sin(heading), 220 * np.cos(heading), np.zeros(n)], axis=1) @ site.rotation.T
    confirmed = rng.random(n) < 0.7
    table = _table(pos, confirmed, vel)
    rows = list(range(n))
    assert n * n > DENSE_PAIRS
    got = isolated(table, site, 0.0, table.track_id[rows], 2_000.0, 40.0)
    want = isolated_reference(pos, vel, confirmed.tolist(), site.rotation[:, 2], rows, 2_000.0, 40.0)
    assert got.tolist() == want
    assert 0 < sum(want) < n  # (isolated tracks and grouped ones both in the scene)


def test_tracks_are_brought_to_the_update_time_before_the_distance() -> None:
    site = Site("R", 46.0, 2.0)
    east = site.rotation[:, 0]
    pos = site.enu_to_ecef(np.array([[0.0, 80_000.0, 9_000.0], [5_000.0, 80_000.0, 9_000.0]]))
    vel = np.array([np.zeros(3), -250.0 * east])  # the tentative one closes in at 250 m/s
    table = _table(pos, np.array([True, False]), vel)
    assert isolated(table, site, 0.0, table.track_id[:1], 2_000.0).tolist() == [True]
    assert isolated(table, site, 16.0, table.track_id[:1], 2_000.0).tolist() == [False]  # 1 km apart
    # a confirmed neighbour holds a track back only when it flies with it
    crossing = _table(pos, np.array([True, True]), vel)
    assert isolated(crossing, site, 16.0, crossing.track_id[:1], 2_000.0, 40.0).tolist() == [True]
    along = _table(pos, np.array([True, True]), np.zeros((2, 3)))
    assert isolated(along, site, 0.0, along.track_id[:1], 6_000.0, 40.0).tolist() == [False]


def test_a_clear_pair_confirms_at_once_and_a_busy_track_keeps_its_pair() -> None:
    book = PairBook()
    nan = np.full(2, np.nan)
    zeros = np.zeros(2, dtype=np.int64)
    ids_a, ids_b = np.array(["a1", "a2"]), np.array(["b1", "b2"])
    # one update: a1-b1 clear, a2-b2 not: only the clear one is confirmed
    book.update(0.0, ids_a, ids_b, ids_a, ids_b, nan, nan, nan, zeros, confirm_now=np.array([True, False]))
    assert {(p.track_a, p.status) for p in book.states()} == {("a1", "confirmed"), ("a2", "tentative")}
    # between updates: a new clear pair of a fresh track confirms; one of a busy track does not
    changed = book.admit(
        1.0,
        np.array(["a1", "a2", "a3"]),
        np.array(["b1", "b2", "b3"]),
        np.array(["a3", "a1"]),
        np.array(["b3", "b2"]),
        nan,
        nan,
        nan,
        zeros,
        np.array([1, 1], dtype=np.int8),
    )
    states = {(p.track_a, p.track_b): p.status for p in book.states()}
    assert changed and states[("a3", "b3")] == "confirmed" and ("a1", "b2") not in states
    # a track that went leaves the book at the next admission
    book.admit(
        2.0,
        np.array(["a2", "a3"]),
        np.array(["b2", "b3"]),
        ids_a[:0],
        ids_b[:0],
        nan[:0],
        nan[:0],
        nan[:0],
        zeros[:0],
        np.zeros(0, dtype=np.int8),
    )
    assert {p.track_a for p in book.states()} == {"a2", "a3"}


@settings(max_examples=100, deadline=None)
@given(
    st.integers(0, 30),
    st.integers(0, 6),
    st.integers(0, 2**31 - 1),
    st.sampled_from([500.0, 20_000.0, 60_000.0]),
)
def test_rows_near_fresh_tracks_equal_the_loop(n: int, k: int, seed: int, reach_m: float) -> None:
    """The rows near a pair's fresh tracks (one product for every row and anchor) are those a
    loop finds, at ECEF magnitudes, with NaN rows and anchors never near."""
    rng = np.random.default_rng(seed)
    centre = np.array([4.0e6, 3.0e5, 4.9e6])
    pos = centre + rng.normal(0.0, 30_000.0, (n, 3))
    anchors = centre + rng.normal(0.0, 30_000.0, (k, 3))
    if n:
        pos[rng.integers(0, n)] = np.nan
    if k > 1:
        anchors[0] = np.nan
    busy = sorted(set(rng.integers(0, max(n, 1), 3).tolist())) if n else []
    got = _within(pos, anchors, reach_m, np.array(busy, dtype=np.intp) if busy else None)
    assert got.tolist() == within_reference(pos, anchors, reach_m, busy)
