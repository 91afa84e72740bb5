"""A confirmed pair whose compensated residual jumps is decided afresh at once (a swap).

A tracker may swap two tracks of a formation: from one scan on, each id carries the other
aircraft's state.  Both confirmed pairs of the two tracks are then wrong, and the history
that confirmed them defends them: the book keeps a confirmed pair through ``drop_misses``
misses, the assignment gives it the ``confirmed_bonus``, its accumulated residual
(:mod:`.evidence`, a mean over minutes) moves only slowly, and the right pairings, each
track with the other's partner, carry a history of rejection from the time they were wrong.

Once the two radars are registered, every update re-checks each confirmed pair by its
bias-compensated chi-square (``svd-topology`` stage 3, :func:`.svd_topology.compensated_chi2`:
the position difference of the two compensated tracks, the radars' relative bias removed by
the registration of the paper's Eq. (2) model, with ``P_A + P_B`` plus the registration's
own covariance, and the velocity difference with ``P_vA + P_vB``; He et al.'s test, the
paper's reference [1]).  For a right pair it is chi-square with ``dof`` degrees of freedom
(6 with velocities).  A pair failing the re-check at ``alpha_position`` is decided in full,
where its history still speaks for it.  A pair whose chi-square **jumps** beyond

    ``chi2 > chi2_{dof}(1 - alpha)``   (``SwapParams.alpha``, far below ``alpha_position``)

is no case for its history: a right pair with Gaussian errors gets there with probability
``alpha`` per update, while two aircraft ``s`` apart give about ``s^T S^-1 s`` (a swap within a
formation a few kilometres wide, or any swap of tracks further apart).  Real track errors have
longer tails (a manoeuvre the two trackers follow at different times, a track's glitch), so a
jump counts as a swap only when a rival pairing explains it (``require_rival``): one of the
pair's two tracks with another track of the other radar passes the same re-check.  Such a pair

* is re-decided at once: it is not kept, it loses the confirmed pair's cost bonus, and unless
  this update's decision chooses it again it leaves the book now (not after ``drop_misses``);
* resets the evidence of its two tracks: every entry of the evidence book with its A track or
  its B track (its own, and its tracks' rival pairings, whose history was measured while the
  tracks followed other aircraft) is forgotten before this update's looks are added, so the
  right pairings start afresh and confirm by their new looks (``min_looks``, M of N).

Cost: one comparison per confirmed pair re-checked (the chi-square is the re-check's own);
only when a pair jumps, the re-check of its two tracks against every track of the other
radar (``2 n`` pairings per jumped pair), one search of the evidence book's entries against
the few tracks and one of the pair book's keys.  Before registration there is no compensated
residual, and no swap rule (the pair book's ``drop_misses`` applies).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.chi2 import chi2_upper
from service.correlation.base import BoolArray, FloatArray, IntArray


@dataclass(frozen=True)
class SwapParams:
    """When a confirmed pair's compensated residual has jumped (module docstring)."""

    #: Re-decide a confirmed pair at once when its compensated chi-square jumps (False: it is
    #: defended by its history as any pair failing the re-check).
    enabled: bool = True
    #: False-alarm probability per update of a right pair: the gate is the chi-square's upper
    #: ``alpha`` quantile at the re-check's degrees of freedom (1e-6: 38.3 with 6 dof, position
    #: and velocity; 30.7 with 3).  Far beyond the re-check's own ``alpha_position`` (0.005:
    #: 18.5), so that a pair merely failing it (a manoeuvre the prediction lags) is still decided
    #: with its history; a national stream re-checks about 10^5 confirmed pairs an hour.
    alpha: float = 1e-6
    #: Only a jump that a rival pairing explains is a swap: one of the pair's two tracks with
    #: another track of the other radar passes the re-check (the method's own test, at
    #: ``alpha_position``).  A right pair's residual can jump without a swap (a manoeuvre the
    #: two trackers follow at different times, a track's glitch); no rival then fits, and the
    #: pair is decided with its history as before.  False: every jump counts.
    require_rival: bool = True


def rivals(ia: IntArray, ib: IntArray, n_a: int, n_b: int) -> tuple[IntArray, IntArray, IntArray]:
    """Every pairing that shares exactly one track with one of the pairs ``(ia[k], ib[k])``
    (rows of snapshots of ``n_a`` and ``n_b`` tracks): ``(k, i, j)``, in (k, A side first) order."""
    m = len(ia)
    if m == 0 or n_a == 0 or n_b == 0:
        e = np.empty(0, dtype=np.intp)
        return e, e.copy(), e.copy()
    # A track of the pair with every other track of the other radar, each side in turn.
    ka, jb = np.nonzero(np.arange(n_b)[None, :] != np.asarray(ib)[:, None])
    kb, ja = np.nonzero(np.arange(n_a)[None, :] != np.asarray(ia)[:, None])
    k = np.concatenate([ka, kb]).astype(np.intp)
    i = np.concatenate([np.asarray(ia)[ka], ja]).astype(np.intp)
    j = np.concatenate([jb, np.asarray(ib)[kb]]).astype(np.intp)
    return k, i, j


def with_rival(k: IntArray, passed: BoolArray, m: int) -> BoolArray:
    """For each of ``m`` pairs: does one of its rivals (``k``: the pair of each, ``passed``:
    whether it passed the re-check) pass?"""
    return np.asarray(np.bincount(np.asarray(k)[np.asarray(passed, dtype=bool)], minlength=m)[:m] > 0)


def jumped(chi2: FloatArray, dof: FloatArray, alpha: float) -> BoolArray:
    """Which of the chi-squares ``chi2`` (with ``dof`` degrees of freedom each) lie beyond
    their upper ``alpha`` quantile (NaN: never)."""
    chi2 = np.asarray(chi2, dtype=float)
    if chi2.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    gate = chi2_upper(alpha, np.asarray(dof, dtype=float))
    return np.asarray(chi2 > gate)
