"""A radar's revisit period as its plots show it, against the one its site declares.

The tracker reads every time scale of its life cycle in scans of the site's ``scan_period_s``:
the gap a track may coast before it is deleted, the spacing of the plots the initiator pairs,
how often it searches the window.  A site that declares a period far from the radar's own (a
configuration error, a bridge with a wrong default) breaks all of them at once: declared at
1 s for a radar turning in 4 s, every track is deleted before its next look and no plot pair
is far enough apart to start one, so the radar holds no track at all.

The revisit period is what the plots say: an aircraft seen on consecutive looks leaves plots
one period apart in time and a short flight apart in space.  The time gaps from each recent
plot to the plots of the same radar near it (its ``neighbours`` nearest in the horizontal
plane, within ``radius_m``, at least ``min_dt_s`` earlier: another aircraft of the same look
is closer in time than that) crowd at the period and its multiples, while other aircraft's
spread out: the densest narrow span of them is the observed period (:func:`observed_period`).
It is measured on a data-time schedule, every ``interval_s`` (a tenth of it until one counts)
from the radar's last ``max_plots`` plots, so it costs one KD-tree of at most that many points
a radar per ``interval_s``, and nothing per plot but keeping its position and time.

The declared period stands unless the gaps contradict it (:func:`contradicted`): the observed
period is off by more than ``tolerance`` and hardly any gap lies at the declared one, which a
radar really turning at that period always leaves.  Then the observed period is used and
logged once per change; either way ``/status`` shows it (``scan_period_observed_s``).  A
period is judged only from plots spanning two declared periods (a radar with more plots per
scan than ``max_plots`` is not judged), must stand out from the gaps around it
(``prominence``: clutter spreads them evenly), and needs ``min_samples`` gaps.  So a period
declared too short, which deletes every track before its next look, is corrected, as is one
too long by a fraction; one too long by a whole factor stands (its gaps are real too), as do
a formation's and a cluttered radar's honest ones.
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


def gaps(xy: FloatArray, t: FloatArray, p: RevisitParams) -> FloatArray:
    """The time from each plot (``xy``: horizontal positions, m; ``t``: times, s) to each of
    its ``neighbours`` nearest plots in space (within ``radius_m``) at least ``min_dt_s``
    earlier."""
    n = t.shape[0]
    if n < 2:
        return np.empty(0)
    k = min(p.neighbours + 1, n)
    dist, idx = cKDTree(xy).query(xy, k=k, distance_upper_bound=p.radius_m)
    dist, idx = dist.reshape(n, k), idx.reshape(n, k)  # (k == 1 gives flat arrays)
    dt = t[:, None] - np.append(t, np.inf)[idx]  # (absent neighbours: index n, -inf)
    return np.asarray(dt[np.isfinite(dist) & (dt >= p.min_dt_s)])


def densest(g: FloatArray, width: float) -> tuple[float, int]:
    """The densest span of relative ``width`` among the gaps ``g`` (sorted): its median and
    how many gaps it holds."""
    hi = np.searchsorted(g, g * (1.0 + width), side="right")
    counts = hi - np.arange(g.shape[0])
    i = int(np.argmax(counts))
    return float(np.median(g[i : hi[i]])), int(counts[i])


def observed_period(g: FloatArray, p: RevisitParams) -> tuple[float, int] | None:
    """The revisit period the gaps ``g`` (:func:`gaps`, sorted) show, and how many gaps say
    so; None with fewer than ``min_samples``.

    An aircraft leaves plots one period apart, and plots near each other are seen near the
    same azimuth, so their gaps are whole periods: they crowd at the period and its multiples
    (a missed look, an older look still near), while other aircraft's spread out.  The period
    is the densest span of ``peak_width`` of them; a span at half of it holding at least half
    as many gaps is the period instead (an aircraft seen every other look), and so on.  It
    must stand out: ``prominence`` times as many gaps as half a period beyond it, which the
    gaps must reach (else None: clutter spreads gaps evenly, and a radar whose last
    ``max_plots`` plots span less than that cannot be judged)."""
    if g.shape[0] < p.min_samples:
        return None
    period, count = densest(g, p.peak_width)
    while True:
        half = support(g, period / 2, p.peak_width)
        if half < max(count / 2, p.min_samples):
            break
        lo, hi = _span(g, period / 2, p.peak_width)
        period, count = float(np.median(g[lo:hi])), half
    # A period is a crowd, not the densest stretch of gaps spread evenly (clutter, or plots
    # too many for the kept ones to span a period): half a period beyond it, gaps are few.
    beyond = 1.5 * period
    if g[-1] < beyond * (1 + p.peak_width / 2) or p.prominence * support(g, beyond, p.peak_width) > count:
        return None
    return (period, count) if count >= p.min_samples else None


def _span(g: FloatArray, x: float, width: float) -> tuple[int, int]:
    lo, hi = np.searchsorted(g, [x / (1 + width / 2), x * (1 + width / 2)])
    return int(lo), int(hi)


def support(g: FloatArray, x: float, width: float) -> int:
    """How many of the gaps ``g`` (sorted) lie within the relative ``width`` around ``x``."""
    lo, hi = _span(g, x, width)
    return hi - lo


def contradicted(g: FloatArray, observed: tuple[float, int], declared_s: float, p: RevisitParams) -> bool:
    """Whether the gaps ``g`` (sorted) contradict the declared period, ``observed`` being the
    period they show and its count: it is off by more than ``tolerance`` and hardly any gap
    lies at the declared period (fewer than ``min_share`` of the observed one's).  A declared
    period the radar really has always leaves its gaps, whatever crowds elsewhere (a
    formation's neighbour where an aircraft was two looks ago, clutter of one sector batch),
    so it stands; so does a whole multiple of the true period (its gaps are real too)."""
    period, count = observed
    if abs(period - declared_s) <= p.tolerance * declared_s:
        return False
    return support(g, declared_s, p.peak_width) < p.min_share * count


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
        #: The declared period the last decision was for, and the period it chose over it.
        self._declared: float | None = None
        self._use: float | None = None

    def add(self, xy: FloatArray, t: FloatArray, time_s: float, declared_s: float) -> None:
        """A batch's plots (horizontal positions and times) at data time ``time_s``."""
        p = self.params
        if not p.enabled:
            return
        if t.shape[0]:
            self._chunks.append((xy[-p.max_plots :], t[-p.max_plots :]))
            self._count += min(t.shape[0], p.max_plots)
            while self._count - self._chunks[0][1].shape[0] >= p.max_plots:
                self._count -= self._chunks.popleft()[1].shape[0]
        if time_s >= self._next_s and self._count >= p.min_samples:
            self._measure(declared_s)  # (judges nothing unless the plots span two declared periods)
            self._next_s = time_s + (p.interval_s if self.observed_s is not None else p.interval_s / 10)

    def _measure(self, declared_s: float) -> None:
        got = None
        if self._count:
            xy, t = (np.concatenate([c[i] for c in self._chunks]) for i in (0, 1))
            if float(t.max() - t.min()) >= 2.0 * declared_s:  # else its gaps could not show
                g = np.sort(gaps(xy, t, self.params))
                got = observed_period(g, self.params)
        if got is not None:
            self.observed_s = got[0]
            use = got[0] if contradicted(g, got, declared_s, self.params) else None
            if use is not None and (
                self._use is None or abs(use - self._use) > self.params.tolerance * self._use
            ):
                log.warning(
                    "radar %s: its plots show a revisit period of %.2f s, its site declares %.2f s: "
                    "tracking with %.2f s (tracking.revisit)",
                    self.name,
                    use,
                    declared_s,
                    use,
                )
            self._use = use
        elif self._declared != declared_s:
            self._use = None  # (a new declaration, nothing to judge it by)
        self._declared = declared_s

    def period(self, declared_s: float) -> float:
        """The period the tracker uses: the declared one, unless the plots contradict it
        (:func:`contradicted`); a new declaration is judged at once."""
        if self.params.enabled and declared_s != self._declared and self._declared is not None:
            self._measure(declared_s)
        return self._use if self._use is not None else declared_s

    def clear(self) -> None:
        """The radar's plots of before go (it expired); the measured period stays."""
        self._chunks.clear()
        self._count = 0
