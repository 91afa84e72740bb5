"""A radar's revisit period as its plots show it, against the one its site declares.

The tracker reads every time scale of its life cycle in scans of the site's ``scan_period_s``:
the gap a track may coast before it is deleted, the spacing of the plots the initiator pairs,
how often it searches the window.  A site that declares a period far from the radar's own (a
configuration error, a bridge with a wrong default) breaks all of them at once: declared at
1 s for a radar turning in 4 s, every track is deleted before its next look and no plot pair
is far enough apart to start one, so the radar holds no track at all.

The revisit period is what the plots say: an aircraft seen on consecutive looks leaves plots
one period apart in time and a short flight apart in space.  For each recent plot the nearest
plot of the same radar (in the horizontal plane, within ``radius_m``) at least ``min_dt_s``
earlier is most often the same aircraft's previous look (a missed look gives twice the
period, another aircraft of the same look is closer in time than ``min_dt_s`` or rare): the
median of those time gaps is the observed period (:func:`observed_period`).  It is measured on
a data-time schedule, every ``interval_s`` (a tenth of it until one counts) from the radar's
last ``max_plots`` plots, so it costs one KD-tree of at most that many points a radar per
``interval_s``, and nothing per plot but keeping its position and time.

The declared period stands while the observed one is within ``tolerance`` of it (an honest
site's tracker is exactly what it was); beyond, the observed one is used, logged once per
change, and shown in ``/status`` (``scan_period_observed_s``).  A measurement with fewer than
``min_samples`` plots that have such a neighbour (quiet sky, a radar too slow for aircraft to
stay within ``radius_m`` between looks) changes nothing: the last measured period stays.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.tracking.params import RevisitParams

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


def observed_period(xy: FloatArray, t: FloatArray, p: RevisitParams) -> tuple[float, int] | None:
    """The median time from each plot (``xy``: horizontal positions, m; ``t``: times, s) to the
    nearest plot in space at least ``min_dt_s`` earlier within ``radius_m``, and how many plots
    had one; None with fewer than ``min_samples``."""
    n = t.shape[0]
    if n < 2:
        return None
    k = min(p.neighbours + 1, n)
    dist, idx = cKDTree(xy).query(xy, k=k, distance_upper_bound=p.radius_m)
    dist, idx = dist.reshape(n, k), idx.reshape(n, k)  # (k == 1 gives flat arrays)
    found = np.isfinite(dist)  # (absent neighbours: infinite distance, index n)
    dt = t[:, None] - np.append(t, np.inf)[idx]
    earlier = found & (dt >= p.min_dt_s)
    has = earlier.any(axis=1)
    if int(has.sum()) < p.min_samples:
        return None
    first = np.argmax(earlier, axis=1)  # nearest first: the first earlier one is the nearest
    gaps = dt[np.flatnonzero(has), first[has]]
    return float(np.median(gaps)), int(has.sum())


class RevisitMeter:
    """One radar's recent plot positions and times, and the period they show (module
    docstring).  ``add`` once per batch; ``period`` is what the tracker uses."""

    def __init__(self, params: RevisitParams, name: str = "") -> None:
        self.params = params
        self.name = name
        self._chunks: deque[tuple[FloatArray, FloatArray]] = deque()
        self._count = 0
        self._next_s = -np.inf
        #: The last measured period (s); None until a measurement counted.
        self.observed_s: float | None = None
        self._told: float | None = None

    def add(self, xy: FloatArray, t: FloatArray, time_s: float) -> None:
        """A batch's plots (horizontal positions and times) at data time ``time_s``."""
        p = self.params
        if not p.enabled:
            return
        if t.shape[0]:
            self._chunks.append((xy[-p.max_plots :], t[-p.max_plots :]))
            self._count += min(t.shape[0], p.max_plots)
            while self._count - self._chunks[0][1].shape[0] >= p.max_plots:
                self._count -= self._chunks.popleft()[1].shape[0]
        if time_s < self._next_s or self._count < p.min_samples:
            return
        xy, t = (np.concatenate([c[i] for c in self._chunks]) for i in (0, 1))
        got = observed_period(xy, t, p)
        if got is not None:
            self.observed_s = got[0]
        self._next_s = time_s + (p.interval_s if self.observed_s is not None else p.interval_s / 10)

    def period(self, declared_s: float) -> float:
        """The period the tracker uses: the declared one, unless the observed one differs from
        it by more than ``tolerance``."""
        seen = self.observed_s
        if seen is None or abs(seen - declared_s) <= self.params.tolerance * declared_s:
            return declared_s
        told = self._told
        if told is None or abs(seen - told) > self.params.tolerance * told:  # (once per change)
            self._told = seen
            log.warning(
                "radar %s: its plots show a revisit period of %.2f s, its site declares %.2f s: "
                "tracking with %.2f s (tracking.revisit)",
                self.name,
                seen,
                declared_s,
                seen,
            )
        return seen

    def clear(self) -> None:
        """The radar's plots of before go (it expired); the measured period stays."""
        self._chunks.clear()
        self._count = 0
