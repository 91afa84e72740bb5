"""A radar's measurement errors as its tracks' innovations show them, against the sigmas its
site declares.

The tracker takes a plot's error covariance from the site's ``range_sigma_m``,
``azimuth_sigma_deg`` and ``elevation_sigma_deg``.  A site that declares them far smaller than
the radar's own (a nominal figure, a default of a bridge) makes the filter trust every plot
too much: its tracks' predictions grow too tight, the gate refuses the next plots, and the
tracks die.  Measured on the three-radar scenario with one radar's three sigmas declared at a
half, a third and a quarter of the truth: its confirmed tracks fell by 5 %, 51 % and 78 %.

An association's normalised innovation squared (NIS, the ``d^2`` the gate takes, three
degrees of freedom) is chi-square distributed when the declared errors are the radar's:
median 2.37.  With sigmas declared too small it grows (median 6.7 at a half, 8.5 at a third);
honest radars stay between 1.9 and 3.2 in every lab scenario, formations included.  Every
``interval_s`` of data time the median NIS of the radar's last ``max_samples`` unambiguous
associations (no other plot in the track's gate, no other track's gate holding the plot) is
read: above ``high_median`` every sigma the tracker uses grows by the square root of its
ratio to 2.37 (at most twice a step, at most ``max_scale`` in all), below ``low_median`` a
grown scale shrinks back the same way (never below the site's sigmas); after a change the
samples start again, so each step is judged on innovations of the new scale.  A growth that
does not bring the next reading's median below ``min_drop`` of the one that called for it
shows the sigmas are not what is wrong (clutter plots taken by the gates: growing them would
take more, three thousand false tracks instead of two hundred with 400 clutter plots a batch):
the scale goes back and is held there (until the service restarts: like the tracks, the
scale is not kept across a restart, and is read again).  The scale is logged once per change
and shown in ``/status`` (``measurement_sigma_scale``).  It only ever grows the sigmas: sigmas
declared too large cost little (ten times the truth kept every track), and an honest site's
tracker is exactly what it was.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from service.chi2 import chi2_quantile
from service.geo import Site
from service.tracking.params import NoiseParams

log = logging.getLogger(__name__)

#: The median of the NIS of a consistent filter: chi-square with three degrees of freedom.
NIS_MEDIAN = float(chi2_quantile(0.5, 3))


def next_scale(scale: float, median_nis: float, p: NoiseParams) -> float:
    """The sigma scale after reading ``median_nis`` at ``scale`` (module docstring)."""
    step = float(np.sqrt(median_nis / NIS_MEDIAN))
    if median_nis > p.high_median:
        return min(p.max_scale, scale * min(step, 2.0))
    if median_nis < p.low_median and scale > 1.0:
        return max(1.0, scale * max(step, 0.5))
    return scale


class NoiseMeter:
    """One radar's recent association NIS and the sigma scale they call for (module
    docstring).  ``add`` once per batch; ``site`` is the site the tracker measures with."""

    def __init__(self, params: NoiseParams, name: str = "") -> None:
        self.params = params
        self.name = name
        #: What the tracker multiplies the site's sigmas by (1: the site's own).
        self.scale = 1.0
        self._nis: deque[NDArray[np.float64]] = deque()
        self._count = 0
        self._next_s = -np.inf
        self._scaled: tuple[Site, float, Site] | None = None
        #: The last growth: the scale before it and the median NIS that called for it.
        self._grown: tuple[float, float] | None = None
        #: A growth that did not bring the innovations down: the sigmas are not what is wrong
        #: (clutter in the gates), the scale went back and stays.
        self.held = False

    def add(self, nis: NDArray[np.float64], time_s: float) -> None:
        """The NIS of a batch's associations at data time ``time_s``."""
        p = self.params
        if not p.enabled:
            return
        if nis.shape[0]:
            self._nis.append(nis[-p.max_samples :])
            self._count += min(nis.shape[0], p.max_samples)
            while self._count - self._nis[0].shape[0] >= p.max_samples:
                self._count -= self._nis.popleft().shape[0]
        if time_s < self._next_s:
            return
        if self._count < p.min_samples:
            self._next_s = time_s + p.interval_s / 10
            return
        self._next_s = time_s + p.interval_s
        if self.held:
            return
        median = float(np.median(np.concatenate(self._nis)))
        grown, self._grown = self._grown, None
        if grown is not None and median > p.min_drop * grown[1]:
            self.held = True
            self._change(grown[0], median, "did not bring them down: back, and held")
            return
        scale = next_scale(self.scale, median, p)
        if scale > self.scale:
            self._grown = (self.scale, median)
        if scale != self.scale:
            self._change(scale, median, "call for it")

    def _change(self, scale: float, median: float, why: str) -> None:
        log.warning(
            "radar %s: its tracks' innovations (median NIS %.1f, consistent: %.1f) %s: the site's "
            "sigmas times %.2f (were times %.2f) (tracking.noise)",
            self.name,
            median,
            NIS_MEDIAN,
            why,
            scale,
            self.scale,
        )
        self.scale = scale
        self.clear()

    def site(self, declared: Site) -> Site:
        """``declared`` with its sigmas times the scale (the same object at scale 1)."""
        if self.scale == 1.0:
            return declared
        held = self._scaled
        if held is None or held[0] is not declared or held[1] != self.scale:
            s = self.scale
            scaled = replace(
                declared,
                range_sigma_m=declared.range_sigma_m * s,
                azimuth_sigma_deg=declared.azimuth_sigma_deg * s,
                elevation_sigma_deg=declared.elevation_sigma_deg * s,
            )
            held = self._scaled = (declared, s, scaled)
        return held[2]

    def clear(self) -> None:
        """The samples go (a new scale, or the radar expired); the scale stays."""
        self._nis.clear()
        self._count = 0
