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

The correlation stage joins the books as they were at a recent point of a data-time grid, the
same for one worker and for N partitioned ones, whichever worker owns which pair of a
triangle (:mod:`service.pipeline.cycle_links`); :func:`implied_for` joins them as they are now.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from service.columns import concat_rows
from service.correlation.base import FloatArray
from service.correlation.pairs import StrongPairs


@dataclass(frozen=True)
class CycleParams:
    """The cycle step (every threshold named)."""

    #: Use the cycles.
    enabled: bool = True
    #: A chain counts from this strength on (its weaker pair's probability of being right).
    min_strength: float = 0.9
    #: Cost bonus of a candidate a chain implies (chi-square units; 6 ~ likelihood ratio 20).
    bonus: float = 6.0
    #: The chains of an update at data time ``t`` are those of the books as they were at the
    #: latest point of the links' grid (``system_interval_s``) at or before ``t - lag_s``:
    #: partitioned workers then have every other worker's books of that point in time, and a
    #: worker's correlation runs at most this far ahead of the slowest other's (data s).
    lag_s: float = 4.0


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
        return concat_rows(Implied, parts) if parts else Implied.empty()


def implied_pairs(xz: StrongPairs, x_first: bool, zy: StrongPairs, z_first: bool) -> Implied:
    """The pairs ``x-y`` the strong confirmed pairs ``x-z`` (of book ``xz``, whose A side is X
    when ``x_first``) and ``z-y`` (of ``zy``, A side Z when ``z_first``) imply, joined on
    ``z``, with strength ``min(score_xz, score_zy)``."""
    x_of_xz, z_of_xz = (xz.track_a, xz.key_b) if x_first else (xz.track_b, xz.key_a)
    z_of_zy, y_of_zy = (zy.key_a, zy.track_b) if z_first else (zy.key_b, zy.track_a)
    order = zy.order_a if z_first else zy.order_b  # (the same order on the ids as on their codes)
    if len(z_of_xz) == 0 or len(z_of_zy) == 0:
        return Implied.empty()
    if z_of_xz.dtype.kind != z_of_zy.dtype.kind:  # (one side's ids have no codes: both as ids)
        z_of_xz = xz.track_b if x_first else xz.track_a
        z_of_zy = zy.track_a if z_first else zy.track_b
    pos = np.minimum(np.searchsorted(z_of_zy, z_of_xz, sorter=order), len(order) - 1)
    j = order[pos]
    hit = z_of_zy[j] == z_of_xz
    i = np.flatnonzero(hit)
    j = j[hit]
    return Implied(x_of_xz[i], y_of_zy[j], np.minimum(xz.score[i], zy.score[j]))


def contradicted(
    rows_a: NDArray[np.intp],
    rows_b: NDArray[np.intp],
    strength: FloatArray,
    implied_a: NDArray[np.intp],
    implied_b: NDArray[np.intp],
    implied_strength: FloatArray,
    n_a: int,
    n_b: int,
) -> NDArray[np.bool_]:
    """For pairs of rows ``(rows_a[k], rows_b[k])`` of strength ``strength[k]``: does a stronger
    chain (implied pairs by rows, of ``n_a`` A and ``n_b`` B rows) name another partner for
    either row?  The strongest chain through each row counts."""
    n = len(rows_a)
    if n == 0 or len(implied_a) == 0:
        return np.zeros(n, dtype=bool)
    out = np.zeros(n, dtype=bool)
    order = np.argsort(implied_strength, kind="stable")  # assigned last = strongest
    for mine, other_mine, imp_mine, imp_other, size in (
        (rows_a, rows_b, implied_a, implied_b, n_a),
        (rows_b, rows_a, implied_b, implied_a, n_b),
    ):
        partner = np.full(size, -1, dtype=np.intp)
        best = np.full(size, -np.inf)
        partner[imp_mine[order]] = imp_other[order]
        best[imp_mine[order]] = implied_strength[order]
        p = partner[mine]
        out |= (p >= 0) & (p != other_mine) & (best[mine] > strength)
    return out


class _Book(Protocol):
    def strong_confirmed(self, min_score: float) -> StrongPairs: ...


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


#: Each radar pair's strong confirmed pairs with the id of its A side, keyed by sorted radar ids.
Books = Mapping[tuple[str, str], tuple[str, StrongPairs]]


def implied_from(key: tuple[str, str], books: Books) -> Implied:
    """The pairs of radar pair ``key`` (``key[0]``'s tracks first) that the strong confirmed
    pairs of ``books`` (radar pairs only) imply through every third radar."""
    x, y = key
    parts = []
    for z in sorted({r for k in books for r in k if r not in key}):
        xz = books.get((min(x, z), max(x, z)))
        zy = books.get((min(z, y), max(z, y)))
        if xz is None or zy is None:
            continue
        parts.append(implied_pairs(xz[1], xz[0] == x, zy[1], zy[0] == z))
    return Implied.concat(parts)


def implied_for(
    key: tuple[str, str], correlators: Mapping[tuple[str, str], _Pair], min_strength: float
) -> Implied:
    """The pairs of radar pair ``key`` that the books of ``correlators`` imply as they are now
    (keyed by sorted radar ids; pairs with a reference source are no link of a chain)."""
    books = {
        k: (c.site_a.site_id, c.book.strong_confirmed(min_strength))
        for k, c in correlators.items()
        if c.site_b is not None
    }
    return implied_from(key, books)
