"""Consistency around three radars: pairs A-B, B-C and A-C must agree (a cycle).

Where radars X, Y and Z see the same group, the confirmed pairs ``x-z`` (of X-Z) and ``z-y``
(of Z-Y) *imply* the pair ``x-y`` of X-Y.  Before X-Y's update the implied pairs are joined
from the two other books (:func:`implied_pairs`; each track is in at most one confirmed pair
per radar pair, so the join on ``z`` is one-to-one).  A chain is as strong as its weaker
link (the smaller of its two pairs' ``score``, the probability each is right) and counts only
from ``min_strength`` on.  In X-Y's update (:class:`~.correlator.PairCorrelator`):

* **evidence**: a candidate ``x-y`` an implied pair names has its cost lowered by ``bonus``
  (chi-square units, like the confirmed-pair bonus): the cycle is a second, independent look
  at the same hypothesis through a third radar's tracks;
* **the weakest link goes**: a confirmed pair of X-Y that a chain contradicts (it names another
  partner for one of its tracks) and that is weaker than that chain is not kept on its own
  re-check, but decided afresh with the rest, where the implied rival has the bonus.  When the
  weakest link is one of the chain's pairs, that pair meets the same test in its own update
  from the cycle's other side.

Every pair of a triangle must be in one place: with ``--partition N`` > 1 a worker owns only
some pairs, so the step is off there (docs/contract.md, partitioning).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from service.correlation.base import FloatArray
from service.correlation.pairkeys import find


@dataclass(frozen=True)
class CycleParams:
    """The cycle step (every threshold named)."""

    #: Use the cycles (one worker only: every pair of a triangle is needed).
    enabled: bool = True
    #: A chain counts from this strength on (its weaker pair's probability of being right).
    min_strength: float = 0.9
    #: Cost bonus of a candidate a chain implies (chi-square units; 6 ~ likelihood ratio 20).
    bonus: float = 6.0


@dataclass(frozen=True)
class Implied:
    """Pairs ``(track_a[k], track_b[k])`` of one radar pair that chains through third radars
    imply, with each chain's strength (one row per chain; a pair may have several)."""

    track_a: NDArray[np.str_]
    track_b: NDArray[np.str_]
    strength: FloatArray

    def __len__(self) -> int:
        return int(self.track_a.shape[0])

    @staticmethod
    def empty() -> Implied:
        return Implied(np.empty(0, dtype=str), np.empty(0, dtype=str), np.empty(0))

    @staticmethod
    def concat(parts: list[Implied]) -> Implied:
        parts = [p for p in parts if len(p)]
        if not parts:
            return Implied.empty()
        return Implied(
            np.concatenate([p.track_a for p in parts]),
            np.concatenate([p.track_b for p in parts]),
            np.concatenate([p.strength for p in parts]),
        )


def implied_pairs(
    x_of_xz: NDArray[np.str_],
    z_of_xz: NDArray[np.str_],
    score_xz: FloatArray,
    z_of_zy: NDArray[np.str_],
    y_of_zy: NDArray[np.str_],
    score_zy: FloatArray,
    min_strength: float,
) -> Implied:
    """The pairs ``x-y`` the confirmed pairs ``x-z`` and ``z-y`` imply (joined on ``z``), with
    strength ``min(score_xz, score_zy)``, those at least ``min_strength``."""
    strong_xz = np.flatnonzero(score_xz >= min_strength)
    strong_zy = np.flatnonzero(score_zy >= min_strength)
    if strong_xz.size == 0 or strong_zy.size == 0:
        return Implied.empty()
    at = find(np.asarray(z_of_zy)[strong_zy], np.asarray(z_of_xz)[strong_xz])
    hit = at >= 0
    i = strong_xz[hit]
    j = strong_zy[at[hit]]
    return Implied(
        np.asarray(x_of_xz)[i].astype(str),
        np.asarray(y_of_zy)[j].astype(str),
        np.minimum(score_xz[i], score_zy[j]),
    )


def contradicted(
    track_a: NDArray[np.str_], track_b: NDArray[np.str_], strength: FloatArray, implied: Implied
) -> NDArray[np.bool_]:
    """For pairs ``(track_a[k], track_b[k])`` of strength ``strength[k]``: does a stronger chain
    name another partner for either track?"""
    n = len(track_a)
    if n == 0 or len(implied) == 0:
        return np.zeros(n, dtype=bool)
    out = np.zeros(n, dtype=bool)
    for mine, theirs, other_mine, other_theirs in (
        (track_a, implied.track_a, track_b, implied.track_b),
        (track_b, implied.track_b, track_a, implied.track_a),
    ):
        # The strongest chain through each track on this side.
        order = np.lexsort((-implied.strength, theirs))
        first = np.r_[True, theirs[order][1:] != theirs[order][:-1]]
        k = order[first]
        at = find(theirs[k], np.asarray(mine).astype(str))
        hit = at >= 0
        other = np.full(n, "", dtype=object)
        other[hit] = other_theirs[k][at[hit]]
        s = np.full(n, -np.inf)
        s[hit] = implied.strength[k][at[hit]]
        out |= hit & (other != np.asarray(other_mine).astype(str)) & (s > strength)
    return out


class _Book(Protocol):
    @property
    def track_a(self) -> NDArray[np.str_]: ...
    @property
    def track_b(self) -> NDArray[np.str_]: ...
    @property
    def confirmed(self) -> NDArray[np.bool_]: ...
    @property
    def score(self) -> FloatArray: ...


class _Site(Protocol):
    @property
    def site_id(self) -> str: ...


class _Pair(Protocol):
    """What the step reads of a radar pair's correlator (:class:`~.correlator.PairCorrelator`)."""

    @property
    def book(self) -> _Book: ...
    @property
    def site_a(self) -> _Site: ...
    @property
    def site_b(self) -> _Site | None: ...


def _confirmed(corr: _Pair, first: str) -> tuple[NDArray[np.str_], NDArray[np.str_], FloatArray]:
    """A radar pair's confirmed pairs as (tracks of radar ``first``, tracks of the other, score)."""
    book = corr.book
    conf = book.confirmed
    a, b, score = book.track_a[conf], book.track_b[conf], book.score[conf]
    return (a, b, score) if corr.site_a.site_id == first else (b, a, score)


def implied_for(
    key: tuple[str, str], correlators: Mapping[tuple[str, str], _Pair], min_strength: float
) -> Implied:
    """The pairs of radar pair ``key`` (``key[0]``'s tracks first) that the confirmed pairs of
    ``correlators`` (keyed by sorted radar ids) imply through every third radar."""
    x, y = key
    parts = []
    for z in sorted({r for k in correlators for r in k if r not in key}):
        xz = correlators.get((min(x, z), max(x, z)))
        zy = correlators.get((min(z, y), max(z, y)))
        if xz is None or zy is None or xz.site_b is None or zy.site_b is None:
            continue
        x_xz, z_xz, s_xz = _confirmed(xz, x)
        z_zy, y_zy, s_zy = _confirmed(zy, z)
        parts.append(implied_pairs(x_xz, z_xz, s_xz, z_zy, y_zy, s_zy, min_strength))
    return Implied.concat(parts)
