"""Correlation that notices a swap and is careful with ambiguous tracks (issue #26, 1c and 2a).

Two radars with known biases see sparse traffic and a formation (the lab's simulated tracker
output, TrackTables built from the truth with each radar's bias and correlated noise).  Tested:

* one radar's two formation tracks swap their aircraft mid-run: with the swap rule
  (:mod:`service.correlation.swap`) the two wrong confirmed pairs leave the book at the update
  of the swap and the right pairings confirm within a few updates; without it the wrong pairs
  are defended by their history for several updates more;
* a pair one of whose tracks has a low quality (``TrackTable.quality``) is not confirmed at
  its first look (nor between updates), but is confirmed later by its accumulated evidence;
  NaN quality changes nothing;
* the vectorised pieces against plain loops.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from service.correlation import CorrelationParams, PairCorrelator
from service.correlation.evidence import EvidenceBook
from service.correlation.pairkeys import pair_keys
from service.correlation.pairs import PairBook
from service.correlation.prompt import PromptParams, quality_clear
from service.correlation.swap import SwapParams, jumped, rivals, with_rival
from service.tracking.base import TrackTable
from topofusion_lab.evaluation.correlation_scenario import make_sites
from topofusion_lab.evaluation.correlation_stream import RadarTrackSim, StreamScenario, make_targets

SC = StreamScenario(sparse_targets=60, cluster_targets=0, confirm_scans=1, box_m=250_000.0)
#: The update at which B's tracks of formation aircraft 0 and 1 swap.
SWAP_AT = 30
SCANS = 38

Stream = list[tuple[TrackTable, TrackTable, float]]


def _formation_stream(
    spacing_m: float, extra: np.ndarray | None = None, seed: int = 4
) -> tuple[Stream, np.ndarray, np.ndarray]:
    """Tables of radars A and B (biases ``SC.bias_a``, ``SC.bias_b``) over ``SCANS`` scans of
    60 sparse aircraft and a formation of 4 flying north abreast ``spacing_m`` apart (the last
    four targets; ``extra``: more targets after them).  Also each radar's id of every target."""
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    pos0, vel = make_targets(rng, SC, a)
    form = np.array([[60_000.0 + spacing_m * k, 40_000.0, 9_000.0] for k in range(4)])
    pos0 = np.vstack([pos0, form] + ([extra[:, :3]] if extra is not None else []))
    vel = np.vstack([vel, np.tile([0.0, 220.0, 0.0], (4, 1))] + ([extra[:, 3:]] if extra is not None else []))
    ra = RadarTrackSim(rng, a, SC.bias_a, len(pos0), SC)
    rb = RadarTrackSim(rng, b, SC.bias_b, len(pos0), SC)
    tables = [
        (ra.table(a, pos0, vel, 4.0 * k), rb.table(a, pos0, vel, 4.0 * k), 4.0 * k + 4.0)
        for k in range(SCANS)
    ]
    return tables, ra.ids, rb.ids


def _swap_ids(table: TrackTable, x: str, y: str) -> TrackTable:
    """The tracker swapped tracks ``x`` and ``y``: each id now carries the other aircraft."""
    ids = table.track_id.copy()
    i, j = int(np.flatnonzero(ids == x)[0]), int(np.flatnonzero(ids == y)[0])
    ids[i], ids[j] = ids[j], ids[i]
    return dataclasses.replace(table, track_id=ids)


def _statuses(corr: PairCorrelator) -> dict[tuple[str, str], str]:
    return {(p.track_a, p.track_b): p.status for p in corr.pairs()}


def _run_swap(
    spacing_m: float, swap_on: bool
) -> tuple[list[dict[tuple[str, str], str]], list[int], tuple[str, ...]]:
    tables, ids_a, ids_b = _formation_stream(spacing_m)
    n = len(ids_a)
    ax, ay, bx, by = ids_a[n - 4], ids_a[n - 3], ids_b[n - 4], ids_b[n - 3]
    a, b = make_sites()
    corr = PairCorrelator("svd-topology", a, b, CorrelationParams(swap=SwapParams(enabled=swap_on)))
    books, swaps = [], []
    for k, (ta, tb, t) in enumerate(tables):
        corr.update(ta, _swap_ids(tb, bx, by) if k >= SWAP_AT else tb, t)
        books.append(_statuses(corr))
        swaps.append(corr.last_swaps)
    assert corr.registered
    return books, swaps, (ax, ay, bx, by)


def _first(books: list[dict[tuple[str, str], str]], cond) -> int:  # type: ignore[no-untyped-def]
    return next(k for k in range(SWAP_AT, len(books)) if cond(books[k]))


@pytest.mark.parametrize("spacing_m", [2_500.0, 1_800.0])
def test_a_swapped_formation_pair_is_redecided_at_once(spacing_m: float) -> None:
    """2.5 km: the formation's tracks are isolated, their right pairings clear at one look;
    1.8 km: inside the isolation distance, so they confirm by their evidence and M of N."""
    on, swaps_on, (ax, ay, bx, by) = _run_swap(spacing_m, True)
    off, swaps_off, _ = _run_swap(spacing_m, False)
    wrong, right = [(ax, bx), (ay, by)], [(ax, by), (ay, bx)]

    def confirmed(pairs: list[tuple[str, str]]):  # type: ignore[no-untyped-def]
        return lambda book: all(book.get(p) == "confirmed" for p in pairs)

    def gone(pairs: list[tuple[str, str]]):  # type: ignore[no-untyped-def]
        return lambda book: all(book.get(p) != "confirmed" for p in pairs)

    for books in (on, off):  # before the swap, both runs hold the formation's right pairs
        assert all(books[SWAP_AT - 1].get(p) == "confirmed" for p in wrong)
    # the swap rule fired on the two wrong pairs at the swap, and nowhere else in the run
    assert swaps_on[SWAP_AT] == 2 and sum(swaps_on) == 2 and sum(swaps_off) == 0
    gone_on, gone_off = _first(on, gone(wrong)), _first(off, gone(wrong))
    assert gone_on == SWAP_AT  # re-decided at once: not confirmed one update longer
    assert gone_off >= SWAP_AT + 3  # defended: the book's drop_misses (4) misses
    # ... and the right pairings confirm within a few updates (no later than without the rule)
    right_on, right_off = _first(on, confirmed(right)), _first(off, confirmed(right))
    assert right_on <= SWAP_AT + 5 and right_on <= right_off
    for books in (on, off):
        assert all(books[-1].get(p) == "confirmed" for p in right)
        assert all(p not in books[-1] or books[-1][p] != "confirmed" for p in wrong)


def test_no_swap_no_jump() -> None:
    """Without a swap the rule never fires and the book is the one without the rule."""
    tables, _, _ = _formation_stream(2_500.0)
    a, b = make_sites()
    with_rule = PairCorrelator("svd-topology", a, b, CorrelationParams())
    without = PairCorrelator("svd-topology", a, b, CorrelationParams(swap=SwapParams(enabled=False)))
    for ta, tb, t in tables:
        with_rule.update(ta, tb, t)
        without.update(ta, tb, t)
        assert with_rule.last_swaps == 0
        assert _statuses(with_rule) == _statuses(without)


# -- caution with ambiguous tracks ----------------------------------------------------------------

#: A late aircraft, alone (far from the sparse traffic's box edge and the formation).
LATE = np.array([[130_000.0, -60_000.0, 10_500.0, -150.0, 160.0, 0.0]])
LATE_AT = 16


def _late_stream() -> tuple[Stream, str, str]:
    tables, ids_a, ids_b = _formation_stream(2_500.0, extra=LATE, seed=5)
    xa, xb = ids_a[-1], ids_b[-1]
    out = []
    for k, (ta, tb, t) in enumerate(tables):
        if k < LATE_AT:  # the late aircraft has no track yet
            ta, tb = ta.take(ta.track_id != xa), tb.take(tb.track_id != xb)
        out.append((ta, tb, t))
    return out, xa, xb


def _with_quality(table: TrackTable, track: str, q: float) -> TrackTable:
    quality = np.full(len(table), np.nan)
    quality[table.track_id == track] = q
    return dataclasses.replace(table, quality=quality)


#: The caution rule on (off by default, ``PromptParams.min_quality`` 0: docs/correlation.md).
MIN_QUALITY = 0.8


def _first_confirmed(quality: float, min_quality: float = MIN_QUALITY) -> int:
    tables, xa, xb = _late_stream()
    a, b = make_sites()
    prm = CorrelationParams(prompt=PromptParams(min_quality=min_quality))
    corr = PairCorrelator("svd-topology", a, b, prm)
    for k, (ta, tb, t) in enumerate(tables):
        corr.update(_with_quality(ta, xa, quality), tb, t)
        if k == LATE_AT - 1:
            assert corr.registered
        if _statuses(corr).get((xa, xb)) == "confirmed":
            return k
    return len(tables)


def test_an_ambiguous_track_is_not_confirmed_promptly_but_by_its_evidence() -> None:
    clear = _first_confirmed(np.nan)
    assert clear == LATE_AT  # unknown quality: confirmed at its first look, as before
    assert _first_confirmed(1.0) == LATE_AT
    low = _first_confirmed(0.5)
    assert LATE_AT < low <= LATE_AT + 4  # waits for its looks and M of N, then confirmed
    assert _first_confirmed(0.5, min_quality=0.0) == LATE_AT  # (the rule off)
    assert PromptParams().min_quality == 0.0  # off by default


def test_an_ambiguous_fresh_track_is_not_admitted_between_updates() -> None:
    """The prompt decision between two updates (:meth:`PairCorrelator.decide_new`)."""
    tables, xa, xb = _late_stream()
    for quality, admitted in ((np.nan, True), (0.5, False)):
        a, b = make_sites()
        corr = PairCorrelator(
            "svd-topology", a, b, CorrelationParams(prompt=PromptParams(min_quality=MIN_QUALITY))
        )
        for ta, tb, t in tables[:LATE_AT]:
            corr.update(ta, tb, t)
        ta, tb, t = tables[LATE_AT]
        late = _with_quality(ta, xa, quality)
        fresh_a = corr.track_keys[0].of(late.track_id)[late.track_id == xa]
        fresh_b = corr.track_keys[1].of(tb.track_id)[tb.track_id == xb]
        corr.decide_new(late, tb, t - 2.0, fresh_a, fresh_b)
        assert (_statuses(corr).get((xa, xb)) == "confirmed") is admitted


# -- the vectorised forms against plain loops -----------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(st.one_of(st.floats(0, 200), st.just(float("nan"))), st.sampled_from([3, 6])), max_size=20
    ),
    st.sampled_from([1e-3, 1e-6, 1e-9]),
)
def test_jumped_equals_the_loop(rows: list[tuple[float, int]], alpha: float) -> None:
    q = np.array([r[0] for r in rows], dtype=float)
    dof = np.array([r[1] for r in rows], dtype=float)
    want = [bool(x > chi2.isf(alpha, d)) for x, d in rows]  # (NaN > gate is False)
    got = jumped(q, dof, alpha)
    for g, w, (x, d) in zip(got.tolist(), want, rows, strict=True):
        # (the two quantile routines may differ in the last digits: never mind a tie)
        assert g == w or abs(x - chi2.isf(alpha, d)) < 1e-6


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.one_of(st.floats(0, 1), st.just(float("nan"))),
            st.one_of(st.floats(0, 1), st.just(float("nan"))),
        ),
        max_size=20,
    ),
    st.sampled_from([0.0, 0.5, 0.9]),
    st.booleans(),
)
def test_quality_clear_equals_the_loop(rows: list[tuple[float, float]], m: float, b_known: bool) -> None:
    qa = np.array([r[0] for r in rows], dtype=float)
    qb = np.array([r[1] for r in rows], dtype=float) if b_known else None

    def ok(x: float) -> bool:
        return bool(np.isnan(x) or x >= m)

    want = [ok(x) and (not b_known or ok(y)) for x, y in rows]
    assert quality_clear(qa, qb, m).tolist() == want


_IDS = st.sampled_from(["a1", "a2", "a3", "a10", "a22"])
_IDS_B = st.sampled_from(["b1", "b2", "b3", "b10"])


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(_IDS, _IDS_B), max_size=15, unique=True),
    st.lists(st.tuples(_IDS, _IDS_B), max_size=3),
)
def test_forgetting_a_swapped_tracks_evidence_equals_the_loop(
    entries: list[tuple[str, str]], swapped: list[tuple[str, str]]
) -> None:
    book = EvidenceBook()
    if entries:
        n = len(entries)
        r = np.arange(3 * n, dtype=float).reshape(n, 3)
        cov = np.broadcast_to(np.eye(3) * 1e4, (n, 3, 3)).copy()
        book.observe(10.0, np.array([e[0] for e in entries]), np.array([e[1] for e in entries]), r, cov)
    sa = np.array([s[0] for s in swapped], dtype=str)
    sb = np.array([s[1] for s in swapped], dtype=str)
    want = [e for e in entries if e[0] not in sa.tolist() and e[1] not in sb.tolist()]
    gone = book.forget_tracks(sa, sb)
    assert list(zip(book.track_a.tolist(), book.track_b.tolist(), strict=True)) == want
    assert gone == len(entries) - len(want)
    keep = [entries.index(e) for e in want]
    assert book.rbar.tolist() == (np.arange(3 * len(entries), dtype=float).reshape(-1, 3)[keep].tolist())


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(_IDS, _IDS_B, st.booleans()), max_size=12, unique_by=lambda t: (t[0], t[1])),
    st.lists(st.tuples(_IDS, _IDS_B), max_size=4, unique=True),
)
def test_releasing_swapped_pairs_equals_the_loop(
    pairs: list[tuple[str, str, bool]], swapped: list[tuple[str, str]]
) -> None:
    """Pairs of the book that scored no hit at the release time leave it; hit ones stay."""
    book = PairBook()
    nan = np.full(len(pairs), np.nan)
    zeros = np.zeros(len(pairs), dtype=np.int64)
    ta = np.array([p[0] for p in pairs], dtype=str)
    tb = np.array([p[1] for p in pairs], dtype=str)
    book.update(0.0, ta, tb, ta, tb, nan, nan, nan, zeros)
    hit = np.array([p[2] for p in pairs], dtype=bool)
    book.update(1.0, ta, tb, ta[hit], tb[hit], nan[hit], nan[hit], nan[hit], zeros[hit])
    before = list(zip(book.track_a.tolist(), book.track_b.tolist(), strict=True))
    sa = np.array([s[0] for s in swapped], dtype=str)
    sb = np.array([s[1] for s in swapped], dtype=str)
    hit_now = {(p[0], p[1]) for p in pairs if p[2]}
    want = [p for p in before if p not in set(swapped) or p in hit_now]
    assert book.release(sa, sb, 1.0) == len(before) - len(want)
    assert list(zip(book.track_a.tolist(), book.track_b.tolist(), strict=True)) == want
    assert (
        book.keys.tolist()
        == pair_keys(
            np.array([p[0] for p in want], dtype=str), np.array([p[1] for p in want], dtype=str)
        ).tolist()
    )


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 6), st.integers(0, 6), st.data())
def test_rivals_equal_the_loop(n_a: int, n_b: int, data: st.DataObject) -> None:
    """Every pairing sharing exactly one track with a jumped pair, and which pairs have one that passed."""
    pairs = data.draw(
        st.lists(st.tuples(st.integers(0, max(n_a - 1, 0)), st.integers(0, max(n_b - 1, 0))), max_size=3)
        if n_a and n_b
        else st.just([])
    )
    ia = np.array([p[0] for p in pairs], dtype=np.intp)
    ib = np.array([p[1] for p in pairs], dtype=np.intp)
    k, i, j = rivals(ia, ib, n_a, n_b)
    want = [(m, x, jj) for m, (x, y) in enumerate(pairs) for jj in range(n_b) if jj != y]
    want += [(m, ii, y) for m, (x, y) in enumerate(pairs) for ii in range(n_a) if ii != x]
    assert sorted(zip(k.tolist(), i.tolist(), j.tolist(), strict=True)) == sorted(want)
    passed = np.array(data.draw(st.lists(st.booleans(), min_size=len(k), max_size=len(k))), dtype=bool)
    got = with_rival(k, passed, len(pairs))
    assert got.tolist() == [
        any(p for kk, p in zip(k.tolist(), passed.tolist(), strict=True) if kk == m)
        for m in range(len(pairs))
    ]
