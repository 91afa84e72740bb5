"""The M-of-N pair book."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.correlation.pairkeys import isin_few, isin_sorted
from service.correlation.pairs import PairBook, PairBookParams


def _upd(
    book: PairBook, t: float, pairs: list[tuple[str, str]], present_a=("a1", "a2"), present_b=("b1", "b2")
):
    ca = np.array([p[0] for p in pairs], dtype=str)
    cb = np.array([p[1] for p in pairs], dtype=str)
    k = len(pairs)
    book.update(
        t,
        np.array(present_a),
        np.array(present_b),
        ca,
        cb,
        np.ones(k),
        np.ones(k),
        np.ones(k),
        np.full(k, 4, dtype=np.int64),
    )


def _status(book: PairBook) -> dict[tuple[str, str], str]:
    return {(s.track_a, s.track_b): s.status for s in book.states()}


def test_confirm_after_m_hits_and_drop_after_misses() -> None:
    book = PairBook(PairBookParams(window=5, confirm_hits=3, drop_misses=2))
    _upd(book, 1.0, [("a1", "b1")])
    _upd(book, 2.0, [])
    _upd(book, 3.0, [("a1", "b1")])
    assert _status(book) == {("a1", "b1"): "tentative"}
    _upd(book, 4.0, [("a1", "b1")])
    assert _status(book) == {("a1", "b1"): "confirmed"}
    s = book.states()[0]
    assert s.hits == 3 and s.first_time_s == 1.0 and s.last_time_s == 4.0 and 0 < s.score <= 1
    _upd(book, 5.0, [])
    assert _status(book) == {("a1", "b1"): "confirmed"}
    _upd(book, 6.0, [])
    assert _status(book) == {}


def test_one_confirmed_pair_per_track_and_vanished_tracks() -> None:
    book = PairBook(PairBookParams(window=4, confirm_hits=2, drop_misses=3))
    for t in range(3):
        _upd(book, float(t), [("a1", "b1"), ("a2", "b2")])
    # a1 now alternates to b2: its pair with b2 must wait until (a1, b1) and (a2, b2) are gone.
    for t in range(3, 6):
        _upd(book, float(t), [("a1", "b2")])
    st = _status(book)
    confirmed = [k for k, v in st.items() if v == "confirmed"]
    assert len({a for a, _ in confirmed}) == len(confirmed)
    assert len({b for _, b in confirmed}) == len(confirmed)
    _upd(book, 7.0, [("a1", "b2")], present_a=("a1",), present_b=("b2",))
    assert all(k == ("a1", "b2") for k in _status(book))


def test_tentative_dropped_when_window_empty() -> None:
    book = PairBook(PairBookParams(window=2, confirm_hits=2))
    _upd(book, 0.0, [("a1", "b1")])
    _upd(book, 1.0, [])
    assert _status(book) == {("a1", "b1"): "tentative"}
    _upd(book, 2.0, [])
    assert _status(book) == {}


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.sampled_from(["A-1", "A-2", "A-10", "B-3", "B-30", "C-7", ""]), max_size=12),
    st.lists(st.sampled_from(["A-1", "A-2", "A-10", "B-3", "B-30", "C-7", "D-9", ""]), max_size=40),
)
def test_set_membership_forms_equal_numpy(x: list[str], y: list[str]) -> None:
    """The books' two membership tests (few among many, and many against a sorted or unsorted
    set) answer what ``np.isin`` answers."""
    xs, ys = np.array(x, dtype=str), np.array(y, dtype=str)
    want = np.isin(xs, ys)
    assert isin_few(xs, ys).tolist() == want.tolist()
    assert isin_sorted(xs, ys).tolist() == want.tolist()
    assert isin_sorted(ys, xs).tolist() == np.isin(ys, xs).tolist()


def _published(score: float, quality: float, power: float) -> float:
    """The published score as the contract's docs say it, one pair at a time: the score's odds
    times ``quality ** power``."""
    s = min(score, 1.0 - 1e-9)
    odds = s / (1.0 - s) * quality**power
    return odds / (1.0 + odds)


def test_published_score_counts_the_tracks_quality() -> None:
    """A pair is right only if both its tracks follow their aircraft: the published score is
    the correlation's score with its odds multiplied by the geometric mean of the tracks'
    qualities at the pair's latest look (not known: 1) to ``published_quality_power``; the
    hold reads the score times that mean; the book's own score (read by the cycles and the
    system tracks) is neither."""
    book = PairBook(PairBookParams(window=4, confirm_hits=2))
    pairs = [("a1", "b1"), ("a2", "b2"), ("a3", "b3")]
    present = (tuple(p[0] for p in pairs), tuple(p[1] for p in pairs))
    for t, qa in ((1.0, [1.0, 0.2, np.nan]), (2.0, [1.0, 0.64, np.nan])):
        ca, cb = (np.array([p[k] for p in pairs], dtype=str) for k in (0, 1))
        quality = book.pair_quality(3, np.array(qa), np.array([1.0, 1.0, 0.81]))
        book.update(
            t, *(np.array(p) for p in present), ca, cb, np.ones(3), np.ones(3), np.ones(3),
            np.full(3, 4, dtype=np.int64), quality=quality,
        )  # fmt: skip
    score = {(s.track_a, s.track_b): s.score for s in book.states()}
    own = dict(zip(zip(book.track_a, book.track_b, strict=True), book.score, strict=True))
    power = book.params.published_quality_power
    assert power > 0
    assert score[("a1", "b1")] == own[("a1", "b1")] > 0
    a2, a3 = own[("a2", "b2")], own[("a3", "b3")]
    assert np.isclose(score[("a2", "b2")], _published(a2, 0.8, power))  # the latest look's: sqrt(0.64)
    assert np.isclose(score[("a3", "b3")], _published(a3, 0.9, power))  # NaN counts as 1
    assert score[("a2", "b2")] < score[("a3", "b3")] < a3
    discounted = dict(zip(zip(book.track_a, book.track_b, strict=True), book.discounted_score, strict=True))
    assert np.isclose(discounted[("a2", "b2")], a2 * 0.8)
    plain = PairBook(PairBookParams(quality_exponent=0.0))
    assert np.array_equal(plain.pair_quality(2, np.array([0.1, np.nan]), None), np.ones(2))


def test_published_scores_vectorised_equal_the_plain_form() -> None:
    """Every pair's published score equals the plain form's, at scores of exactly 0 and 1 and
    qualities of 0 and 1 too; a quality of 1 publishes the score itself."""
    rng = np.random.default_rng(7)
    n = 64
    p = np.concatenate([[0.0, 1.0, 1.0, 0.5, 0.999999], rng.uniform(0.0, 1.0, n - 5)])
    q = np.concatenate([[0.3, 0.0, 1.0, 0.0, 0.6], rng.uniform(0.0, 1.0, n - 5)])
    for power in (0.0, 1.0, 3.0):
        book = PairBook(PairBookParams(published_quality_power=power))
        book.admit(
            1.0, None, None, np.array([f"a{i}" for i in range(n)]), np.array([f"b{i}" for i in range(n)]),
            np.ones(n), np.ones(n), np.ones(n), np.full(n, 4), np.ones(n, dtype=np.int8), p, q,
        )  # fmt: skip
        got = dict(zip(book.track_a, book.published_score, strict=True))
        for i in range(n):
            assert np.isclose(got[f"a{i}"], _published(p[i], q[i], power), rtol=1e-12, atol=1e-12), (i, power)
        ones = book.published_score[np.isclose(book.cols["quality"], 1.0)]
        assert np.allclose(ones, np.minimum(book.score[np.isclose(book.cols["quality"], 1.0)], 1 - 1e-9))


def test_a_pair_confirmed_at_its_first_look_publishes_its_tracks_quality() -> None:
    book = PairBook()
    one = np.ones(1)
    quality = book.pair_quality(1, np.array([0.25]), np.array([1.0]))
    book.admit(
        1.0, None, None, np.array(["a1"]), np.array(["b1"]), one, one, one,
        np.array([4]), np.array([1], dtype=np.int8), np.array([0.99]), quality,
    )  # fmt: skip
    (state,) = book.states()
    power = book.params.published_quality_power
    assert state.status == "confirmed" and np.isclose(state.score, _published(0.99, 0.5, power))
    assert state.score < 0.99
    assert np.isclose(book.score[0], 0.99)


def _look(book: PairBook, t: float, quality: float, probability: float) -> None:
    """One update choosing (a1, b1) with its tracks' quality, then the evidence's probability."""
    one = np.ones(1)
    book.update(
        t, np.array(["a1", "a2"]), np.array(["b1"]), np.array(["a1"]), np.array(["b1"]), one, one, one,
        np.array([4]), quality=book.pair_quality(1, np.array([quality]), None),
    )  # fmt: skip
    book.set_probability(np.array([probability]))
    book.hold_ambiguous()


def test_a_contested_pair_the_evidence_turned_against_is_held_until_its_score_recovers() -> None:
    """A confirmed pair whose discounted score falls below ``hold_score`` while a track is
    contested goes back to tentative, keeps scoring hits, and is confirmed again only once its
    discounted score reaches ``release_score``: its hits alone do not (hysteresis)."""
    prm = PairBookParams(window=4, confirm_hits=2)
    book = PairBook(prm)
    for t in (1.0, 2.0):
        _look(book, t, 1.0, 0.95)
    assert _status(book) == {("a1", "b1"): "confirmed"}
    _look(book, 3.0, 1.0, 0.3)  # the evidence is against it, but no track is contested: kept
    assert _status(book) == {("a1", "b1"): "confirmed"}
    _look(book, 4.0, 0.64, 0.6)  # discounted 0.6 * 0.8 = 0.48 < hold_score, quality 0.8 < 0.9, 4 hits: held
    assert _status(book) == {("a1", "b1"): "tentative"} and book.held.all()
    for t in (5.0, 6.0, 7.0):  # every update a hit, the score between the two thresholds
        _look(book, t, 1.0, (prm.hold_score + prm.release_score) / 2)
        assert _status(book) == {("a1", "b1"): "tentative"}
    _look(book, 8.0, 1.0, prm.release_score)
    assert _status(book) == {("a1", "b1"): "confirmed"} and not book.held.any()
    young = PairBook(prm)  # confirmed on 2 hits, fewer than ``hold_after_hits``: its evidence is young
    for t, q, p in ((1.0, 1.0, 0.95), (2.0, 0.64, 0.1)):
        _look(young, t, q, p)
    assert _status(young) == {("a1", "b1"): "confirmed"}
    off = PairBook(PairBookParams(window=4, confirm_hits=2, hold_score=0.0))
    for t, q, p in ((1.0, 1.0, 0.95), (2.0, 1.0, 0.95), (3.0, 0.64, 0.1)):
        _look(off, t, q, p)
    assert _status(off) == {("a1", "b1"): "confirmed"}


def test_a_held_pair_in_a_lasting_formation_is_released_by_its_evidence_alone() -> None:
    """A held pair whose tracks stay contested (discounted score never back at
    ``release_score``) is confirmed again once its evidence is at least ``release_probability``
    and it has scored ``release_hits`` hits since the hold; it is then not held again while
    that lasts, and is held again once its evidence falls."""
    prm = PairBookParams(window=4, confirm_hits=2, release_probability=0.999, release_hits=5)
    book = PairBook(prm)
    for t in (1.0, 2.0, 3.0):
        _look(book, t, 1.0, 0.95)
    _look(book, 4.0, 0.25, 0.9)  # discounted 0.9 * 0.5 < hold_score, quality 0.5: held
    assert book.held.all()
    for k in range(1, prm.release_hits):  # strong evidence, low quality: 4 hits since the hold
        _look(book, 4.0 + k, 0.25, 0.9999)
        assert _status(book) == {("a1", "b1"): "tentative"}, k
    _look(book, 4.0 + prm.release_hits, 0.25, 0.998)  # the 5th, but the evidence below 0.999
    assert _status(book) == {("a1", "b1"): "tentative"}
    _look(book, 10.0, 0.25, 0.9995)
    assert _status(book) == {("a1", "b1"): "confirmed"} and not book.held.any()
    _look(book, 11.0, 0.25, 0.9999)  # discounted still below hold_score: not held again
    assert _status(book) == {("a1", "b1"): "confirmed"}
    _look(book, 12.0, 0.25, 0.99)  # the evidence falls: held again, its count from now
    assert _status(book) == {("a1", "b1"): "tentative"} and book.held.all()
    _look(book, 13.0, 0.25, 0.9999)
    assert _status(book) == {("a1", "b1"): "tentative"}
    steady = PairBook(prm)  # never held: its hits in all count, strong evidence keeps it
    for t in range(1, prm.release_hits + 1):
        _look(steady, float(t), 1.0, 0.9999)
    _look(steady, 10.0, 0.25, 0.9999)
    assert _status(steady) == {("a1", "b1"): "confirmed"}
    off = PairBook(replace(prm, release_probability=2.0))  # (> 1: never)
    for t, q, p in ((1.0, 1.0, 0.95), (2.0, 1.0, 0.95), (3.0, 1.0, 0.95), (4.0, 0.25, 0.9)):
        _look(off, t, q, p)
    for t in range(5, 20):
        _look(off, float(t), 0.25, 0.9999)
    assert _status(off) == {("a1", "b1"): "tentative"}


def test_a_held_pair_frees_its_tracks_for_their_rival() -> None:
    """While held, neither track is in a confirmed pair: the rival pairing of one of them
    confirms on its hits, and the held pair is then never confirmed beside it."""
    book = PairBook(PairBookParams(window=4, confirm_hits=2))
    for t in (1.0, 2.0):
        _look(book, t, 1.0, 0.95)
    _look(book, 3.0, 0.5, 0.4)
    assert book.held.all()
    one = np.ones(1)
    for t in (4.0, 5.0):
        book.update(
            t, np.array(["a1", "a2"]), np.array(["b1"]), np.array(["a2"]), np.array(["b1"]), one, one, one,
            np.array([4]),
        )  # fmt: skip
        book.set_probability(np.where(book.track_a == "a2", 0.9, 0.4))
        book.hold_ambiguous()
    st = _status(book)
    assert st[("a2", "b1")] == "confirmed" and st[("a1", "b1")] == "tentative"
