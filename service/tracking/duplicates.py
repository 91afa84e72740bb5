"""Duplicate tracks: two tracks of one radar fed by one aircraft's plots in turn.

When an aircraft shows two plots for a few scans (a split plot, or two aircraft merging to
within the radar's resolution) two tracks start on it; once it shows one plot a look, that
plot goes to one track or the other, each track is hit often enough never to reach its
deletion count of misses, and both live on.  Correlation then pairs one of them with the
other radar's track and the picture keeps a ghost beside it.

The rule (parameters in :class:`~service.tracking.params.FormationParams`):

* **candidates** are the pairs of tracks whose gates held the same plot in this batch (a
  duplicate's twin always gates the aircraft's plot, so no search over all tracks is needed:
  the cost follows the batch's own gated candidates);
* a candidate pair is a **duplicate** when (a) their states, predicted to the batch's time, are
  close: the Mahalanobis distance of the difference of the two 6-vectors, with the sum of
  their covariances, is at most ``duplicate_chi2``; and (b) over the last ``duplicate_looks``
  looks of each, the two never had a plot in the same look (an aircraft gives at most one plot
  a look; two aircraft this close both give one, with probability ``Pd^2``);
* of a duplicate pair the track with **fewer plots** is dropped (the younger one on a tie):
  the older, better-fed track keeps its number, so the aircraft's track number does not change.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from service.geo import FloatArray
from service.tracking import kalman

IntArray = NDArray[np.intp]


def shared_plot_pairs(rows: IntArray, cols: IntArray) -> tuple[IntArray, IntArray]:
    """Distinct pairs ``(a, b)``, ``a < b``, of track rows whose gates held the same plot.

    ``rows``/``cols``: the track and plot of each gated candidate (no repeated candidate).  The
    loop runs over the largest number of tracks gating one plot (a handful), never over pairs.
    """
    if rows.shape[0] < 2:
        e = np.empty(0, dtype=np.intp)
        return e, e
    shared = np.bincount(cols)[cols] >= 2  # most plots are in one gate only
    r, c = rows[shared], cols[shared]
    order = np.lexsort((r, c))
    r, c = r[order], c[order]
    a_parts: list[IntArray] = []
    b_parts: list[IntArray] = []
    for shift in range(1, r.shape[0]):
        same = c[shift:] == c[:-shift]
        if not same.any():  # sorted by plot: a longer shift cannot meet the same plot again
            break
        a_parts.append(r[:-shift][same])
        b_parts.append(r[shift:][same])
    if not a_parts:
        e = np.empty(0, dtype=np.intp)
        return e, e
    a, b = np.concatenate(a_parts), np.concatenate(b_parts)  # a < b: rows ascend within a plot
    span = np.int64(rows.max()) + 1
    key = np.unique(a.astype(np.int64) * span + b)
    return (key // span).astype(np.intp), (key % span).astype(np.intp)


def duplicate_losers(
    a: IntArray,
    b: IntArray,
    x: FloatArray,
    P: FloatArray,
    t: FloatArray,
    hist: NDArray[np.int64],
    looks: NDArray[np.int64],
    plots: NDArray[np.int64],
    time_s: float,
    process_noise_psd: float,
    chi2: float,
    window_looks: int,
) -> IntArray:
    """Rows to drop among the candidate pairs ``(a, b)`` (rows of the track arrays, which
    follow the tracks' birth order), in ascending order.

    ``hist``: each track's looks as bits, newest in bit 0 (1 = a plot); ``looks``: the looks
    counted; ``window_looks``: ``FormationParams.duplicate_looks``.  A track that loses to one
    twin is dropped even if it beats another.
    """
    if a.shape[0] == 0:
        return np.empty(0, dtype=np.intp)
    window = (np.int64(1) << window_looks) - 1
    enough = (looks[a] >= window_looks) & (looks[b] >= window_looks)
    apart = (hist[a] & hist[b] & window) == 0
    cand = np.flatnonzero(enough & apart)
    if cand.shape[0] == 0:
        return np.empty(0, dtype=np.intp)
    a, b = a[cand], b[cand]
    xa, pa = kalman.predict(x[a], P[a], time_s - t[a], process_noise_psd)
    xb, pb = kalman.predict(x[b], P[b], time_s - t[b], process_noise_psd)
    close = kalman.mahalanobis2(xa - xb, pa + pb) <= chi2
    a, b = a[close], b[close]
    # the loser: fewer plots, or on a tie the younger (the later row)
    a_loses = (plots[a] < plots[b]) | ((plots[a] == plots[b]) & (a > b))
    return np.unique(np.where(a_loses, a, b)).astype(np.intp)
