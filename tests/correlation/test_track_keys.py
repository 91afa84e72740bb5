"""Integer track keys: what the books and the evidence identify tracks by (module pairkeys)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.correlation.pairkeys import KEY_LIMIT, TrackKeys, comparable, id_codes, pair_keys
from service.correlation.pairs import PairBook, PairBookParams
from tests.reference_forms import track_keys_reference

IDS = [f"R1-{n}" for n in range(12)]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.lists(st.sampled_from(IDS), unique=True), min_size=1, max_size=8), st.booleans())
def test_keys_against_the_plain_form(tables: list[list[str]], in_order: bool) -> None:
    """A track keeps its key while it stays in the tables; a new id, or one back after a table
    without it, gets the next key.  Tables in id order (as the tracker gives them) or not."""
    tables = [sorted(t) if in_order else t for t in tables]
    keys = TrackKeys()
    got = [keys.of(np.array(t, dtype=str)).tolist() for t in tables]
    assert got == track_keys_reference(tables, KEY_LIMIT)


def test_the_same_table_is_keyed_once_and_keys_stay_below_the_limit() -> None:
    keys = TrackKeys()
    keys._next = KEY_LIMIT - 2  # (as after 2**31 - 2 tracks)
    table = np.array(["a", "b", "c", "d"], dtype=str)
    first = keys.of(table)
    assert first.tolist() == [KEY_LIMIT - 2, KEY_LIMIT - 1, 0, 1]
    assert keys.of(table) is first  # (every pair of the radar reads its table's keys at no cost)
    assert keys.of(np.array(["b", "d", "e"], dtype=str)).tolist() == [KEY_LIMIT - 1, 1, 2]
    big = pair_keys(np.array([KEY_LIMIT - 1]), np.array([KEY_LIMIT - 1]))
    assert big.dtype == np.int64 and big[0] == (KEY_LIMIT - 1) * 2**32 + KEY_LIMIT - 1 > 0


@given(st.lists(st.tuples(st.integers(0, KEY_LIMIT - 1), st.integers(0, KEY_LIMIT - 1)), unique=True))
def test_pair_keys_of_track_keys_are_one_number_per_pair(pairs: list[tuple[int, int]]) -> None:
    a = np.array([p[0] for p in pairs], dtype=np.int64)
    b = np.array([p[1] for p in pairs], dtype=np.int64)
    got = pair_keys(a, b)
    assert got.tolist() == [x * 2**32 + y for x, y in pairs]
    assert len(set(got.tolist())) == len(pairs)
    # track ids keep their string keys
    ids = pair_keys(np.array(["A-1"]), np.array(["B-2"]))
    assert ids.tolist() == ["A-1\x1fB-2"]


def _run(book: PairBook, steps: list[list[tuple[str, str]]], by_key: bool) -> list[tuple[str, str, str, int]]:
    """The book after each step's chosen pairs, identified by the track ids themselves or by
    track keys (the ids then given as the pairs' names, as the correlation does)."""
    ka, kb = TrackKeys(), TrackKeys()
    present_a = np.array(sorted({p[0] for s in steps for p in s} | {"a0"}), dtype=str)
    present_b = np.array(sorted({p[1] for s in steps for p in s} | {"b0"}), dtype=str)
    keys_a, keys_b = ka.of(present_a), kb.of(present_b)
    out = []
    for t, chosen in enumerate(steps):
        ca = np.array([p[0] for p in chosen], dtype=str)
        cb = np.array([p[1] for p in chosen], dtype=str)
        n = len(chosen)
        ones = np.ones(n)
        if by_key:
            ia, ib = np.searchsorted(present_a, ca), np.searchsorted(present_b, cb)
            ids = (keys_a, keys_b, keys_a[ia], keys_b[ib])
            names = (ca, cb)
        else:
            ids, names = (present_a, present_b, ca, cb), None
        book.update(float(t), *ids, ones, ones, ones, np.zeros(n, dtype=np.int64), names=names)
        out += [(s.track_a, s.track_b, s.status, s.hits) for s in book.states()]
    return out


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.lists(
            st.tuples(st.sampled_from(["a1", "a2", "a3"]), st.sampled_from(["b1", "b2", "b3"])), max_size=3
        )
        .map(lambda ps: list({p[0]: p for p in ps}.values()))
        .map(lambda ps: list({p[1]: p for p in ps}.values())),
        max_size=8,
    )
)
def test_a_book_on_keys_publishes_what_it_would_on_ids(steps: list[list[tuple[str, str]]]) -> None:
    params = PairBookParams(window=4, confirm_hits=2, drop_misses=2)
    assert _run(PairBook(params), steps, by_key=True) == _run(PairBook(params), steps, by_key=False)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.text(alphabet=st.characters(max_codepoint=0x1FF), max_size=10), min_size=1, max_size=30),
    st.lists(st.text(alphabet=st.characters(max_codepoint=0x1FF), max_size=10), max_size=10),
)
def test_id_codes_sort_search_and_compare_as_the_ids(ids: list[str], query: list[str]) -> None:
    """Integer codes of track ids: every sort, search and comparison as on the ids (numpy's
    string order); none for an id of more than 8 characters or one beyond U+00FF."""
    a, q = np.array(ids, dtype=str), np.array(query, dtype=str)
    fits = all(len(x.rstrip("\x00")) <= 8 and all(ord(c) <= 0xFF for c in x) for x in ids)
    codes = id_codes(a)
    assert (codes is not None) == fits
    if codes is None:
        assert comparable(a, q)[0] is a
        return
    ca, cq = comparable(a, q)
    if cq is q:  # (the query has no codes: both stay ids)
        assert ca is a
        return
    assert ca.dtype == np.uint64 and cq.dtype == np.uint64
    assert np.array_equal(np.argsort(a, kind="stable"), np.argsort(ca, kind="stable"))
    s, cs = np.sort(a), np.sort(ca)
    assert np.array_equal(np.searchsorted(s, q), np.searchsorted(cs, cq))
    assert np.array_equal(np.searchsorted(s, q, side="right"), np.searchsorted(cs, cq, side="right"))
    assert np.array_equal(a[:, None] == q[None, :], ca[:, None] == cq[None, :])
