"""Initiators by name: each turns the window's unused plots into candidate groups.

* ``logic`` (default): three-plot M/N logic with velocity gates (:mod:`.logic`).  Default
  because it needs only three looks, runs in milliseconds for thousands of plots, and the
  track manager's M-of-N confirmation removes the few clutter triples it lets through.
* ``hough`` / ``hough-velocity``: the paper's method, probabilistic-grid Hough (Eq. 2-6)
  then velocity fuzzy clustering (Eq. 7-10, Steps 1-8 with the fixes of
  :mod:`.velocity_tracks`) over the bands of all Hough peaks.
* ``pg-hough``: probabilistic-grid Hough alone (baseline of Table 1).
* ``classic-hough``: classic Hough alone (baseline of Table 1).

The Hough family works in the east-north plane (the paper's 2-D set-up) with each plot's
plane covariance (the paper's location error ``delta = sqrt(trace C)``).  In the streaming
tracker it is applied *locally*: the window's unused plots are split into clusters of plots
that one target could have produced (pairs closer than ``max_speed * |dt|`` plus 3 sigma,
:func:`local_clusters`), and each cluster of at least ``min_plots`` plots gets its own Hough
transform.  A Hough line spanning the whole coverage (hundreds of kilometres, every plot of
the window) is never formed, and the cost follows the number of plots per cluster.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from service.tracking.groups import Groups, IntArray
from service.tracking.hough import classic_hough, pg_hough, pg_hough_bands
from service.tracking.logic import logic_initiate
from service.tracking.measurement import Measurements
from service.tracking.pairs import time_gated_pairs
from service.tracking.params import BoundParams, TrackerParams
from service.tracking.velocity_tracks import global_tracks

#: Names accepted by :func:`service.tracking.make_tracker`.
INITIATORS: tuple[str, ...] = ("logic", "hough", "hough-velocity", "pg-hough", "classic-hough")

Initiator = Callable[[Measurements, TrackerParams, float], Groups]
PlaneMethod = Callable[[np.ndarray, np.ndarray, np.ndarray, TrackerParams], list[IntArray]]


def location_error(cov2: np.ndarray) -> np.ndarray:
    """Location error ``delta`` of a plot: ``sqrt(trace C)`` of its plane covariance."""
    return np.asarray(np.sqrt(np.trace(cov2, axis1=1, axis2=2)))


def hough_velocity(t: np.ndarray, xy: np.ndarray, cov: np.ndarray, params: TrackerParams) -> list[IntArray]:
    """The paper's two stages: PG Hough bands (Eq. 2-6), then velocity clustering over all
    bands (:func:`service.tracking.velocity_tracks.global_tracks`)."""
    bands = pg_hough_bands(xy, cov, params.hough)
    return global_tracks(t, xy, cov, bands, params.cluster)


def local_clusters(
    meas: Measurements, max_speed_mps: float, min_plots: int, bounds: BoundParams | None = None
) -> list[IntArray]:
    """Connected components (at least ``min_plots`` plots) of the graph joining two plots when
    one target could have produced both: plane distance at most ``max_speed |dt|`` plus 3
    sigma of the two plots' position errors.  Components come in order of their first plot.
    The pairs are searched within ``bounds`` (:func:`service.tracking.pairs.time_gated_pairs`:
    blockwise, at most ``max_pairs`` candidates)."""
    n = len(meas)
    if n < min_plots:
        return []
    bounds = bounds if bounds is not None else BoundParams()
    xy = meas.enu_m[:, :2]
    t = meas.time_s
    sig = location_error(meas.covariance[:, :2, :2])
    span = float(np.ptp(t))
    radius = max_speed_mps * span + 6.0 * float(sig.max())

    def joins(a: IntArray, b: IntArray) -> np.ndarray:
        dist = np.linalg.norm(xy[a] - xy[b], axis=1)
        return np.asarray(dist <= max_speed_mps * np.abs(t[a] - t[b]) + 3.0 * np.hypot(sig[a], sig[b]))

    a, b = time_gated_pairs(t, xy, radius, 0.0, span, joins, bounds.max_pairs, bounds.block)
    graph = coo_matrix((np.ones(a.shape[0]), (a, b)), shape=(n, n))
    n_comp, label = connected_components(graph, directed=False)
    sizes = np.bincount(label, minlength=n_comp)
    order = np.argsort(label, kind="stable")
    edges = np.concatenate([[0], np.cumsum(sizes)])
    return [order[edges[c] : edges[c + 1]] for c in range(n_comp) if sizes[c] >= min_plots]


def _local(method: PlaneMethod) -> Initiator:
    """Apply a plane method to each local cluster of the window's plots (loop over clusters:
    the handful of plot groups a target could have formed, not over plots).  Clusters of more
    than ``bounds.max_cluster_plots`` plots are left alone: the plane methods' memory grows
    with the cube of a cluster's plots (velocity clustering's ``S x S x S`` arrays)."""

    def run(meas: Measurements, params: TrackerParams, scan_period_s: float) -> Groups:
        min_plots = max(3, min(params.hough.min_plots, params.cluster.min_plots))
        out: list[IntArray] = []
        for members in local_clusters(meas, params.cluster.max_speed_mps, min_plots, params.bounds):
            if members.shape[0] > params.bounds.max_cluster_plots:
                continue
            t = meas.time_s[members]
            xy = meas.enu_m[members, :2]
            xy = xy - xy.mean(axis=0)  # local frame: small coordinates for the LS sums
            cov = meas.covariance[members, :2, :2]
            out.extend(members[g] for g in method(t, xy, cov, params))
        return Groups.from_lists(out)

    return run


def _logic(meas: Measurements, params: TrackerParams, scan_period_s: float) -> Groups:
    return logic_initiate(meas, params.logic, scan_period_s, params.bounds)


def _classic_plane(t: np.ndarray, xy: np.ndarray, cov: np.ndarray, params: TrackerParams) -> list[IntArray]:
    return classic_hough(xy, params.hough).to_lists()


def _pg_plane(t: np.ndarray, xy: np.ndarray, cov: np.ndarray, params: TrackerParams) -> list[IntArray]:
    return pg_hough(xy, cov, params.hough).to_lists()


_REGISTRY: dict[str, Initiator] = {
    "logic": _logic,
    "hough": _local(hough_velocity),
    "hough-velocity": _local(hough_velocity),
    "pg-hough": _local(_pg_plane),
    "classic-hough": _local(_classic_plane),
}


def get_initiator(name: str) -> Initiator:
    """The initiator called ``name``; ``ValueError`` naming the accepted names otherwise."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown initiator {name!r}; expected one of {', '.join(INITIATORS)}") from None
