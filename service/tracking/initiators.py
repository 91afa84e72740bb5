"""Initiators by name: each turns the window's unused plots into candidate groups.

* ``logic`` (default): three-plot M/N logic with velocity gates (:mod:`.logic`).  Default
  because it needs only three looks, runs in milliseconds for thousands of plots, and the
  track manager's M-of-N confirmation removes the few clutter triples it lets through; the
  Hough family needs many plots per target in the window (the paper uses 10 s with random
  sampling) and its cost grows with the surveillance area.
* ``hough`` / ``hough-velocity``: the paper's method, probabilistic-grid Hough (Eq. 2-6)
  then velocity fuzzy clustering (Eq. 7-10, Steps 1-8) on each preliminary track.
* ``pg-hough``: probabilistic-grid Hough alone (baseline of Table 1).
* ``classic-hough``: classic Hough alone (baseline of Table 1).

The Hough family works in the east-north plane (the paper's 2-D set-up); the plot sigma used
as the location error ``delta`` of Eq. (8) is ``sqrt(trace C)`` of its plane covariance.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from service.tracking.clustering import velocity_cluster
from service.tracking.groups import Groups, IntArray
from service.tracking.hough import classic_hough, pg_hough
from service.tracking.logic import logic_initiate
from service.tracking.measurement import Measurements
from service.tracking.params import TrackerParams

#: Names accepted by :func:`service.tracking.make_tracker`.
INITIATORS: tuple[str, ...] = ("logic", "hough", "hough-velocity", "pg-hough", "classic-hough")

Initiator = Callable[[Measurements, TrackerParams, float], Groups]


def location_error(cov2: np.ndarray) -> np.ndarray:
    """Location error ``delta`` of a plot: ``sqrt(trace C)`` of its plane covariance."""
    return np.asarray(np.sqrt(np.trace(cov2, axis1=1, axis2=2)))


def cluster_groups(
    prelim: Groups, t: np.ndarray, xy: np.ndarray, delta: np.ndarray, params: TrackerParams
) -> Groups:
    """Velocity fuzzy clustering (Section 2) of every preliminary track (loop over lines)."""
    out: list[IntArray] = []
    for members in prelim.to_lists():
        for sub in velocity_cluster(t[members], xy[members], delta[members], params.cluster):
            out.append(members[sub])
    return Groups.from_lists(out)


def _logic(meas: Measurements, params: TrackerParams, scan_period_s: float) -> Groups:
    return logic_initiate(meas, params.logic, scan_period_s)


def _classic(meas: Measurements, params: TrackerParams, scan_period_s: float) -> Groups:
    return classic_hough(meas.enu_m[:, :2], params.hough)


def _pg(meas: Measurements, params: TrackerParams, scan_period_s: float) -> Groups:
    return pg_hough(meas.enu_m[:, :2], meas.covariance[:, :2, :2], params.hough)


def _pg_velocity(meas: Measurements, params: TrackerParams, scan_period_s: float) -> Groups:
    xy, cov2 = meas.enu_m[:, :2], meas.covariance[:, :2, :2]
    prelim = pg_hough(xy, cov2, params.hough)
    return cluster_groups(prelim, meas.time_s, xy, location_error(cov2), params)


_REGISTRY: dict[str, Initiator] = {
    "logic": _logic,
    "hough": _pg_velocity,
    "hough-velocity": _pg_velocity,
    "pg-hough": _pg,
    "classic-hough": _classic,
}


def get_initiator(name: str) -> Initiator:
    """The initiator called ``name``; ``ValueError`` naming the accepted names otherwise."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown initiator {name!r}; expected one of {', '.join(INITIATORS)}") from None
