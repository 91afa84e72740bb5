"""The pair book: single decisions accumulated over time into tentative and confirmed pairs.

M-of-N scoring (the "计分法" the SVD paper combines its single decisions with, Section 2,
after He et al. 2007): each update, every pair of the book scores a hit if it was among the
update's chosen single decisions, a miss otherwise.

* A new chosen pair enters as ``tentative``.
* A tentative pair becomes ``confirmed`` once it has ``confirm_hits`` hits in the last
  ``window`` updates and neither of its tracks is in another confirmed pair (conflicts
  among pairs confirming in the same update are settled by a one-to-one assignment on the
  score), so each track is in at most one confirmed pair.
* A tentative pair with no hit in the last ``window`` updates is dropped; a confirmed pair
  is dropped after ``drop_misses`` consecutive misses (it "stops passing"), or at once when
  one of its tracks has vanished from the input.
* A confirmed pair whose evidence turns against it while one of its tracks is contested is
  *held* (:meth:`PairBook.hold_ambiguous`): back to tentative, so that neither its fused
  picture nor the confirmed bonus defends it, and confirmed again only once its discounted
  score has recovered to ``release_score`` (hysteresis: not on its hits alone, which a track
  following two aircraft in turn keeps scoring), or once it has scored ``release_hits`` hits
  since the hold and its evidence alone is at ``release_probability`` (a lasting formation,
  whose tracks stay contested: its discounted score cannot recover).

``hit_fraction = hits in the window / window`` drives the logic above.  ``score`` is the
pair's probability of being right from its accumulated evidence (:mod:`.evidence`, set by the
caller in ``probability``) where the method gives one, the hit fraction otherwise: the
correlation's own figure, which the cycle step and the system tracks read.  Two figures also
count the tracks themselves: a pair is right only if both its tracks follow their aircraft,
and a track whose recent plots were contested (``TrackTable.quality``, the tracker's
likelihood share of its associations) may have swapped onto a neighbour, which no
correlation evidence shows.  A pair's ``quality`` is ``(q_a q_b) ** quality_exponent`` of its
tracks' qualities at its latest hit (a quality not known counts as 1).  The *discounted*
score (:attr:`PairBook.discounted_score`), ``score * quality``, is what the hold reads; the
*published* score (:attr:`PairBook.published_score`), the one a ``PairSet`` carries, is the
score with its odds multiplied by ``quality ** published_quality_power``,

    ``published = s f / (s f + 1 - s)``,  ``s = min(score, 1 - 1e-9)``,  ``f = quality ** k``,

a calibration of the score by the tracks' quality through the whole pipeline (measured in
:class:`PairBookParams`): a pair of unambiguous tracks (quality 1) publishes its score.
``basis`` records what the pair's latest hit rested on (:class:`~.base.Basis`, -1: not
given).  Stored columnar (numpy), updated with set operations on keys: no Python loop over
pairs.  The book identifies tracks by what it is
given, track keys or track ids (:mod:`.pairkeys`; the correlation gives keys, and the track ids
as the pairs' names, ``track_a``/``track_b``, which is what it publishes).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from annotated_types import Ge, Le
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from service.correlation.base import BASIS_NAMES, FloatArray
from service.correlation.pairkeys import comparable, find, isin_few, joined
from service.correlation.pairkeys import isin_sorted as _isin
from service.correlation.pairkeys import pair_keys as _keys

#: The published score never takes the score as more certain than this: a probability of
#: exactly 1 (the evidence's exponentials can round to it) would make its odds infinite and the
#: tracks' quality count for nothing.
_MOST_CERTAIN = 1.0 - 1e-9


@dataclass(frozen=True)
class PairBookParams:
    """M-of-N confirmation logic."""

    #: N: number of recent updates the score looks at (<= 32).
    window: Annotated[int, Ge(1), Le(32)] = 6
    #: M: hits within the window needed to confirm.
    confirm_hits: int = 3
    #: Consecutive misses after which a confirmed pair is dropped.
    drop_misses: int = 4
    #: A pair's quality is ``(q_a q_b) ** quality_exponent`` (module docstring; 0: always 1).
    #: 0.5, the geometric mean of the two qualities: through the whole pipeline in formations
    #: (``topofusion evaluate --only formation``, 8 points, seeds 4-5, 6 167 judged confirmed
    #: pairs) the Brier score of ``score * quality`` (then the published score) was 0.254 with
    #: the score alone, 0.181 / 0.178 / 0.199 / 0.226 with exponents 0.25 / 0.5 / 0.75 / 1
    #: (taken on seeds 1-3 beforehand, where 0.25 and 0.5 were equal: 0.232 -> 0.159 / 0.161),
    #: and the pairs so scored at 0.95 or more were right 96 % of the time (scored so by the
    #: score alone: 81 %).  National network: the qualities are about 1, the discounted scores 0.4 %
    #: below the score alone on average.
    quality_exponent: float = 0.5
    #: The published score is the score with its odds multiplied by ``quality`` (above) to
    #: this power (module docstring; 0: the score alone).  Fitted by the likelihood of the
    #: pairs' truth through the whole pipeline in formations (``topofusion evaluate --only
    #: formation``'s points but 1x, seeds 4-6, every confirmed and held pair every 10 s from
    #: 360 s: 30 113 samples, 2.93) and checked on seeds 1-3 (30 396 samples, not used to fit
    #: it), where the Brier score of the confirmed pairs' published scores was 0.038 with
    #: ``score * quality`` (the published score before, under-confident once the trackers held
    #: their formations: pairs published at 0.5-0.8 were right 98 % of the time), 0.0096 with
    #: the score alone and 0.0094 with this, lower at 8 of the 9 points (2x 0.092 -> 0.013, 2x
    #: at Pd 0.7 0.119 -> 0.067, Pd 0.95 0.101 -> 0.000, crossing 0.084 -> 0.015) and higher at
    #: merging (0.383 -> 0.622: there the trackers lose half their tracks to neighbours, and
    #: the pairs confirmed are mostly false at any quality).  National network: the qualities
    #: are about 1, so the published score is the score (docs/correlation.md).
    published_quality_power: Annotated[float, Ge(0)] = 3.0
    #: A confirmed pair is held (module docstring) when its discounted score falls below this
    #: while its quality (``(q_a q_b) ** quality_exponent`` at its latest hit) is below
    #: ``hold_quality`` (0: never held): a track contested by a neighbour's plots may have
    #: swapped onto it, and the evidence finds a rival hypothesis about as likely.  0.6 of
    #: 0.5 / 0.6 / 0.7 (formation study, 4 seeds, docs/correlation.md "Held pairs"): false
    #: pairs at 2x 4.0 / 1.6 / 0.3 %, correct 46.5 / 38.1 / 19.6 %; at 3x false 10.7 / 6.7 /
    #: 3.8 %, correct 62.3 / 67.3 / 61.5 %.  Without the quality condition a fresh pair, whose
    #: evidence starts low, was held too: national time to pair median 0.25 -> 0.94 scans.
    hold_score: float = 0.6
    #: ... see ``hold_score``.  0.9: on the national network the qualities are about 1.
    hold_quality: float = 0.9
    #: ... and only a pair with at least this many hits: a pair confirmed at its first look
    #: (:mod:`.prompt`) has too little history for its evidence to judge it (on the national
    #: network 131 of the 135 pairs held in 120 s had 1-2 hits, and none was false).
    hold_after_hits: int = 3
    #: A held pair is confirmed again only once its discounted score is at least this (and it
    #: has the hits of a confirmation): a held pair confirmed again on its hits alone flapped
    #: between the two (306 pairs in 120 s of national data, docs/results.md).
    release_score: float = 0.65
    #: ... or once its evidence alone (the ``probability`` column, before the tracks' quality)
    #: is at least this and it has scored ``release_hits`` hits since it was held (> 1: never);
    #: a pair so vouched for (``release_hits`` hits since its hold, or in all if never held) is
    #: not held while its evidence stays there.  A formation that stays one keeps its
    #: tracks contested, so the discounted score of a right pair stays below ``release_score``
    #: for good.  Formation study (4 seeds, held pairs only on ``release_score`` against these):
    #: (0.999, 12): correct / false pairs at 2x 38.1 / 1.59 % -> 42.5 / 1.45 %, 2x at Pd 0.95
    #: 34.5 / 1.76 -> 43.3 / 1.09, at Pd 0.7 13.3 / 24.6 -> 15.4 / 22.7, 3x 67.3 / 6.65 ->
    #: 67.3 / 6.75; (0.99, 10) gave 45.5 / 2.16 at 2x, (0.999, 8) 44.2 / 1.16 but 65.5 / 7.09
    #: at 3x, (0.999, 20) 39.6 / 1.52 (docs/correlation.md, "Held pairs").
    release_probability: float = 0.999
    #: ... see ``release_probability``.
    release_hits: int = 12


@dataclass
class PairState:
    """One pair of the book, as published in ``PairSet`` (docs/contract.md)."""

    track_a: str
    track_b: str
    status: str
    score: float
    statistic: float
    rotation_weight: float
    scale: float
    neighbors: int
    hits: int
    first_time_s: float
    last_time_s: float
    basis: str | None = None
    #: A tentative pair held (:meth:`PairBook.hold_ambiguous`).
    held: bool = False


def _popcount(x: NDArray[np.uint32]) -> NDArray[np.int64]:
    return np.bitwise_count(x).astype(np.int64)


@dataclass(frozen=True)
class StrongPairs:
    """A book's confirmed pairs of at least some score, with each side's track ids in the form
    the cycle step joins on (:mod:`.cycles`; their integer codes where they have them,
    :func:`~.pairkeys.comparable`) and its sort order."""

    track_a: NDArray[np.str_]
    track_b: NDArray[np.str_]
    score: FloatArray
    key_a: NDArray[Any]
    key_b: NDArray[Any]
    order_a: NDArray[np.intp]
    order_b: NDArray[np.intp]

    @staticmethod
    def of(track_a: NDArray[np.str_], track_b: NDArray[np.str_], score: FloatArray) -> StrongPairs:
        (key_a,), (key_b,) = comparable(track_a), comparable(track_b)
        return StrongPairs(track_a, track_b, score, key_a, key_b, np.argsort(key_a), np.argsort(key_b))


class PairBook:
    """Columnar M-of-N book for one radar pair."""

    _float_cols = (
        *("statistic", "rotation_weight", "scale", "first_time_s", "last_time_s", "probability"),
        "quality",
    )

    def __init__(self, params: PairBookParams | None = None) -> None:
        self.params = params or PairBookParams()
        if not 1 <= self.params.window <= 32:
            raise ValueError("window must be within 1..32")
        #: The pairs' track ids (what the book publishes) ...
        self.track_a = np.empty(0, dtype=str)
        self.track_b = np.empty(0, dtype=str)
        #: ... and the identifiers the book was given for them (track keys, or the ids again),
        #: which its set operations run on, with the pair keys of the two.
        self.id_a: NDArray[Any] = np.empty(0, dtype=np.int64)
        self.id_b: NDArray[Any] = np.empty(0, dtype=np.int64)
        self.keys: NDArray[Any] = np.empty(0, dtype=np.int64)
        self.history = np.empty(0, dtype=np.uint32)
        self.hits = np.empty(0, dtype=np.int64)
        self.misses = np.empty(0, dtype=np.int64)
        self.confirmed = np.empty(0, dtype=bool)
        #: Held pairs (tentative; :meth:`hold_ambiguous`).
        self.held = np.empty(0, dtype=bool)
        #: The hits a held pair had when it was held (:meth:`hold_ambiguous`; else unused).
        self.held_hits = np.empty(0, dtype=np.int64)
        self.neighbors = np.empty(0, dtype=np.int64)
        self.basis = np.empty(0, dtype=np.int8)
        self.cols: dict[str, FloatArray] = {c: np.empty(0) for c in self._float_cols}
        #: Counts the changes of the book (:meth:`update`, a new probability column).
        self.version = 0
        self._strong: tuple[int, float, StrongPairs] | None = None

    def strong_confirmed(self, min_score: float) -> StrongPairs:
        """The confirmed pairs with ``score >= min_score`` (computed once per book version)."""
        if self._strong is not None and self._strong[:2] == (self.version, min_score):
            return self._strong[2]
        keep = self.confirmed & (self.score >= min_score)
        out = StrongPairs.of(self.track_a[keep], self.track_b[keep], self.score[keep])
        self._strong = (self.version, min_score, out)
        return out

    def set_probability(self, probability: FloatArray) -> None:
        """The pairs' probability of being right (row for row; NaN: none, the hit fraction)."""
        self.cols["probability"] = probability
        self.version += 1

    def __len__(self) -> int:
        return int(self.track_a.shape[0])

    @property
    def score(self) -> FloatArray:
        """The pair's score: the evidence probability where set, else the hit fraction."""
        p = self.cols["probability"]
        return np.where(np.isfinite(p), p, self.hit_fraction)

    @property
    def _known_quality(self) -> FloatArray:
        """The pairs' quality, 1 where not known (module docstring)."""
        q = self.cols["quality"]
        return np.where(np.isfinite(q), q, 1.0)

    @property
    def discounted_score(self) -> FloatArray:
        """``score`` times the pair's tracks' quality (module docstring): what the hold reads."""
        return np.asarray(self.score * self._known_quality)

    @property
    def published_score(self) -> FloatArray:
        """``score`` with its odds multiplied by the pair's tracks' quality to the power
        ``published_quality_power`` (module docstring): what a ``PairSet`` publishes.  The
        score is capped below 1, so ``1 - s`` and the denominator are never 0."""
        s = np.minimum(self.score, _MOST_CERTAIN)
        num = s * self._known_quality**self.params.published_quality_power
        return np.asarray(num / (num + (1.0 - s)))

    def pair_quality(self, n: int, quality_a: FloatArray | None, quality_b: FloatArray | None) -> FloatArray:
        """``(q_a q_b) ** quality_exponent`` of ``n`` pairs from their tracks' qualities (row for
        row; None or NaN: not known, 1)."""
        q = np.ones(n)
        for side in (quality_a, quality_b):
            if side is not None:
                side = np.clip(np.asarray(side, dtype=float), 0.0, 1.0)
                q *= np.where(np.isfinite(side), side, 1.0)
        return np.asarray(q**self.params.quality_exponent)

    @property
    def hit_fraction(self) -> FloatArray:
        mask = np.uint32((1 << self.params.window) - 1) if self.params.window < 32 else np.uint32(0xFFFFFFFF)
        return _popcount(self.history & mask) / float(self.params.window)

    def _keep(self, keep: NDArray[np.bool_]) -> None:
        self.version += 1
        self.track_a = self.track_a[keep]
        self.track_b = self.track_b[keep]
        self.id_a = self.id_a[keep]
        self.id_b = self.id_b[keep]
        self.keys = self.keys[keep]
        self.history = self.history[keep]
        self.hits = self.hits[keep]
        self.misses = self.misses[keep]
        self.confirmed = self.confirmed[keep]
        self.held = self.held[keep]
        self.held_hits = self.held_hits[keep]
        self.neighbors = self.neighbors[keep]
        self.basis = self.basis[keep]
        self.cols = {k: v[keep] for k, v in self.cols.items()}

    def update(
        self,
        time_s: float,
        present_a: NDArray[Any],
        present_b: NDArray[Any],
        chosen_a: NDArray[Any],
        chosen_b: NDArray[Any],
        statistic: FloatArray,
        rotation_weight: FloatArray,
        scale: FloatArray,
        neighbors: NDArray[np.int64],
        basis: NDArray[np.int8] | None = None,
        confirm_now: NDArray[np.bool_] | None = None,
        quality: FloatArray | None = None,
        names: tuple[NDArray[np.str_], NDArray[np.str_]] | None = None,
    ) -> None:
        """Score one update: ``chosen_*`` are this update's one-to-one single decisions;
        ``confirm_now``: those that are clear (:mod:`.prompt`) confirm at once, without the M
        hits (still one-to-one: never a track already in a confirmed pair); ``quality``: their
        tracks' (:meth:`pair_quality`; None: not known).  ``present_*`` and ``chosen_*`` are
        identifiers (track keys or ids, module docstring); ``names``: the chosen pairs' track
        ids (None: the identifiers are the ids).

        A hit pair's ``statistic``, ``rotation_weight``, ``scale`` and ``neighbors`` are those
        of the decision that scored it, the latest one: NaN where that decision computed none
        (e.g. a confirmed pair kept by the registered re-check fitted no rotation), published
        as null.  No placeholder: a weight of 1 would claim a fit that was not made.  Infinite
        statistics are clipped to +-1e6.
        """
        prm = self.params
        self.version += 1
        statistic = np.clip(np.asarray(statistic, dtype=float), -1e6, 1e6)
        rotation_weight = np.asarray(rotation_weight, dtype=float)
        scale = np.asarray(scale, dtype=float)
        basis = np.full(len(chosen_a), -1, dtype=np.int8) if basis is None else basis.astype(np.int8)
        quality = np.full(len(chosen_a), np.nan) if quality is None else np.asarray(quality, dtype=float)
        new_keys = _keys(chosen_a, chosen_b)
        # Book pairs among the chosen ones, and which chosen pair each is (one sort, one search).
        hit = np.zeros(len(self), dtype=bool)
        src = np.empty(0, dtype=np.intp)
        if len(self) and len(new_keys):
            order = np.argsort(new_keys)
            ns = new_keys[order]
            pos = np.minimum(np.searchsorted(ns, self.keys), len(ns) - 1)
            hit = ns[pos] == self.keys
            src = order[pos[hit]]
        self.history = (self.history << np.uint32(1)) | hit.astype(np.uint32)
        self.hits = self.hits + hit
        self.misses = np.where(hit, 0, self.misses + 1)
        now = np.zeros(len(self), dtype=bool)
        if confirm_now is not None and hit.any():
            now[hit] = confirm_now[src]
        # Refresh statistics of the hit pairs.
        if hit.any():
            self.cols["statistic"][hit] = statistic[src]
            self.cols["rotation_weight"][hit] = rotation_weight[src]
            self.cols["scale"][hit] = scale[src]
            self.cols["last_time_s"][hit] = time_s
            self.cols["quality"][hit] = quality[src]
            self.neighbors[hit] = neighbors[src]
            self.basis[hit] = basis[src]
        # Append the new pairs: the chosen ones no book pair found (chosen pairs are one-to-one,
        # so their keys are unique).
        fresh = np.ones(len(new_keys), dtype=bool)
        fresh[src] = False
        nf = int(fresh.sum())
        if nf:
            named_a, named_b = names if names is not None else (chosen_a, chosen_b)
            self._append(
                time_s,
                (chosen_a[fresh], chosen_b[fresh]),
                (named_a[fresh], named_b[fresh]),
                new_keys[fresh],
                (statistic[fresh], rotation_weight[fresh], scale[fresh], np.full(nf, np.nan), quality[fresh]),
                neighbors[fresh],
                basis[fresh],
            )
            now = np.concatenate(
                [now, confirm_now[fresh] if confirm_now is not None else np.zeros(nf, dtype=bool)]
            )
        # Drop.
        score = self.hit_fraction
        gone = ~_isin(self.id_a, present_a) | ~_isin(self.id_b, present_b)
        stale_tent = ~self.confirmed & (score <= 0)
        stale_conf = self.confirmed & (self.misses >= prm.drop_misses)
        keep = ~(gone | stale_tent | stale_conf)
        self._keep(keep)
        now = now[keep]
        self._confirm(np.flatnonzero(~self.confirmed & ~self.held & (self._hits_to_confirm() | now)))

    def _hits_to_confirm(self) -> NDArray[np.bool_]:
        """Which pairs have the hits of a confirmation (``confirm_hits`` in the window)."""
        return np.asarray(self.hit_fraction * self.params.window >= self.params.confirm_hits - 1e-9)

    def hold_ambiguous(self) -> None:
        """Hold the confirmed pairs the evidence has turned against while a track is contested,
        and confirm again the held pairs whose discounted score has recovered or whose evidence
        vouches for them (module docstring; called once the pairs' probability is set)."""
        prm = self.params
        if prm.hold_score <= 0.0 or len(self) == 0:
            return
        score = self.discounted_score
        quality = self.cols["quality"]
        # Evidence that vouches for the pair whatever its tracks' quality: a pair in a formation
        # that stays one has contested tracks for good, so its discounted score cannot recover.
        vouched = (self.cols["probability"] >= prm.release_probability) & (  # (NaN: not)
            self.hits - self.held_hits >= prm.release_hits
        )
        hold = self.confirmed & (score < prm.hold_score) & (quality < prm.hold_quality)  # (NaN: not)
        hold &= (self.hits >= prm.hold_after_hits) & ~vouched
        if hold.any():
            self.confirmed[hold] = False
            self.held |= hold
            self.held_hits[hold] = self.hits[hold]
        recovered = (score >= prm.release_score) | vouched
        release = np.flatnonzero(self.held & ~hold & recovered & self._hits_to_confirm())
        if release.size:
            self._confirm(release)
            self.held &= ~self.confirmed
        if hold.any() or release.size:
            self.version += 1

    def admit(
        self,
        time_s: float,
        present_a: NDArray[Any] | None,
        present_b: NDArray[Any] | None,
        track_a: NDArray[Any],
        track_b: NDArray[Any],
        statistic: FloatArray,
        rotation_weight: FloatArray,
        scale: FloatArray,
        neighbors: NDArray[np.int64],
        basis: NDArray[np.int8],
        probability: FloatArray | None = None,
        quality: FloatArray | None = None,
        names: tuple[NDArray[np.str_], NDArray[np.str_]] | None = None,
    ) -> bool:
        """Confirm clear pairs between two updates (:mod:`.prompt`): a pair of the book is
        confirmed, a new one enters confirmed with one hit; neither scores the other pairs (the
        next update does), and a track already in a confirmed pair keeps it.  ``probability``:
        their score (NaN: the hit fraction); ``quality``: their tracks' (:meth:`pair_quality`; None:
        not known).  As at an update, pairs whose track is not among
        ``present_a``/``present_b`` any more leave the book (None: that side's tracks are
        those the book was last checked against, none gone).  Identifiers and ``names`` as at
        :meth:`update`.  Whether the book changed."""
        gone = np.zeros(len(self), dtype=bool)
        for present, tracks in ((present_a, self.id_a), (present_b, self.id_b)):
            if present is not None:
                gone |= ~_isin(tracks, present)
        if gone.any():
            self._keep(~gone)
        keys = _keys(track_a, track_b)
        # (a few pairs against the whole book: searched among the few, the book never sorted)
        conf = self.confirmed
        busy = isin_few(track_a, self.id_a[conf]) | isin_few(track_b, self.id_b[conf])
        if busy.all():
            return bool(gone.any())  # (``_keep`` counted the change)
        keep = ~busy
        named_a, named_b = names if names is not None else (track_a, track_b)
        keys, track_a, track_b = keys[keep], track_a[keep], track_b[keep]
        named_a, named_b = named_a[keep], named_b[keep]
        prob = np.full(len(keys), np.nan) if probability is None else np.asarray(probability)[keep]
        qual = np.full(len(keys), np.nan) if quality is None else np.asarray(quality, dtype=float)[keep]
        pos = np.flatnonzero(_isin(self.keys, keys))
        held = _isin(keys, self.keys[pos])
        if pos.size:  # (the book's pairs among them: their latest look's quality)
            self.cols["quality"][pos] = qual[find(keys, self.keys[pos])]
        fresh = np.flatnonzero(~held)
        if fresh.size:
            k = np.flatnonzero(keep)[fresh]
            self._append(
                time_s,
                (track_a[fresh], track_b[fresh]),
                (named_a[fresh], named_b[fresh]),
                keys[fresh],
                (np.clip(statistic[k], -1e6, 1e6), rotation_weight[k], scale[k], prob[fresh], qual[fresh]),
                neighbors[k],
                basis[k],
            )
        rows = np.concatenate([pos, len(self) - fresh.size + np.arange(fresh.size)]).astype(np.intp)
        before = int(np.count_nonzero(self.confirmed))
        # (none of them is busy: above; a held pair waits for :meth:`hold_ambiguous` to release it)
        self._confirm(rows[~self.confirmed[rows] & ~self.held[rows]], free=True)
        self.version += 1
        return bool(gone.any()) or fresh.size > 0 or int(np.count_nonzero(self.confirmed)) != before

    def release(self, track_a: NDArray[Any], track_b: NDArray[Any], time_s: float) -> int:
        """Drop the pairs ``(track_a[k], track_b[k])`` (identifiers) of the book that scored no hit at
        ``time_s`` (a swap, :mod:`.swap`: re-decided at once rather than after
        ``drop_misses`` misses); how many went."""
        if len(self) == 0 or len(track_a) == 0:
            return 0
        at = find(self.keys, _keys(np.asarray(track_a), np.asarray(track_b)))
        at = at[at >= 0]
        at = at[self.cols["last_time_s"][at] < time_s]
        if at.size == 0:
            return 0
        keep = np.ones(len(self), dtype=bool)
        keep[at] = False
        self._keep(keep)
        return int(at.size)

    def _append(
        self,
        time_s: float,
        ids: tuple[NDArray[Any], NDArray[Any]],
        names: tuple[NDArray[np.str_], NDArray[np.str_]],
        keys: NDArray[Any],
        values: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray],
        neighbors: NDArray[np.int64],
        basis: NDArray[np.int8],
    ) -> None:
        """New pairs, tentative with one hit at ``time_s``: their identifiers, track ids and
        keys; ``values``: their statistic, rotation weight, scale, probability and quality."""
        nf = len(keys)
        self.track_a = np.concatenate([self.track_a, np.asarray(names[0]).astype(str)])
        self.track_b = np.concatenate([self.track_b, np.asarray(names[1]).astype(str)])
        self.id_a = joined(self.id_a, ids[0])
        self.id_b = joined(self.id_b, ids[1])
        self.keys = joined(self.keys, keys)
        self.history = np.concatenate([self.history, np.ones(nf, dtype=np.uint32)])
        self.hits = np.concatenate([self.hits, np.ones(nf, dtype=np.int64)])
        self.misses = np.concatenate([self.misses, np.zeros(nf, dtype=np.int64)])
        self.confirmed = np.concatenate([self.confirmed, np.zeros(nf, dtype=bool)])
        self.held = np.concatenate([self.held, np.zeros(nf, dtype=bool)])
        self.held_hits = np.concatenate([self.held_hits, np.zeros(nf, dtype=np.int64)])
        self.neighbors = np.concatenate([self.neighbors, neighbors.astype(np.int64)])
        self.basis = np.concatenate([self.basis, basis.astype(np.int8)])
        statistic, rotation_weight, scale, probability, quality = values
        add = {
            "statistic": statistic,
            "rotation_weight": rotation_weight,
            "scale": scale,
            "first_time_s": np.full(nf, time_s),
            "last_time_s": np.full(nf, time_s),
            "probability": probability,
            "quality": quality,
        }
        self.cols = {k: np.concatenate([v, add[k]]) for k, v in self.cols.items()}

    def _confirm(self, idx: NDArray[np.intp], free: bool = False) -> None:
        """Confirm the pairs ``idx`` whose tracks are in no confirmed pair; among them, conflicts
        are settled by a one-to-one assignment on the score.  ``free``: the caller has already
        left out every pair with a track in a confirmed pair."""
        if idx.size and not free:  # (the busy test only for these: in a steady state they are few)
            conf = self.confirmed
            idx = idx[~isin_few(self.id_a[idx], self.id_a[conf]) & ~isin_few(self.id_b[idx], self.id_b[conf])]
        if idx.size:
            ua, ra = np.unique(self.id_a[idx], return_inverse=True)
            ub, rb = np.unique(self.id_b[idx], return_inverse=True)
            if ua.size == idx.size and ub.size == idx.size:
                self.confirmed[idx] = True
            else:
                # Prefer higher score, then more recent hit, then lower statistic.
                statistic = np.nan_to_num(self.cols["statistic"][idx], nan=1e2).clip(0, 1e2)
                val = self.hit_fraction[idx] * 1e3 - statistic
                mat = np.full((ua.size, ub.size), -1e12)
                mat[ra, rb] = val
                r, c = linear_sum_assignment(mat, maximize=True)
                ok = mat[r, c] > -1e12
                sel = np.zeros((ua.size, ub.size), dtype=bool)
                sel[r[ok], c[ok]] = True
                self.confirmed[idx[sel[ra, rb]]] = True

    def states(self) -> list[PairState]:
        """The book as :class:`PairState` rows sorted by (track_a, track_b)."""
        order = np.lexsort((self.track_b, self.track_a))
        score = self.published_score
        return [
            PairState(
                track_a=str(self.track_a[i]),
                track_b=str(self.track_b[i]),
                status="confirmed" if self.confirmed[i] else "tentative",
                score=float(score[i]),
                statistic=float(self.cols["statistic"][i]),
                rotation_weight=float(self.cols["rotation_weight"][i]),
                scale=float(self.cols["scale"][i]),
                neighbors=int(self.neighbors[i]),
                hits=int(self.hits[i]),
                first_time_s=float(self.cols["first_time_s"][i]),
                last_time_s=float(self.cols["last_time_s"][i]),
                basis=BASIS_NAMES[self.basis[i]] if self.basis[i] >= 0 else None,
                held=bool(self.held[i]),
            )
            for i in order
        ]
