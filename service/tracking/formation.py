"""Tracks flying in formation: who flies with whom, and when a formation manoeuvres.

Aircraft in formation fly straight together, a few hundred metres to a few kilometres apart,
closer than any separation minimum of controlled traffic (3 NM, 5.6 km, in a terminal area).
Such a track predicts with the formation's quiet model (:class:`~.params.FormationParams`):
a missed plot then leaves it where its aircraft is instead of where its last few noisy plots
pointed, and a neighbour's plot falls outside its gate more often.

* :func:`formation_groups`: a track flies in formation when one of its few nearest neighbours
  of the same radar lies within ``radius_m`` at a velocity within ``speed_mps`` of its own
  (both at one data time); the formations are the connected groups of such neighbours.
* :func:`manoeuvring`: a formation turns or changes speed as one, so its members' innovations
  share a common part, while their noise is each their own.  The sum of the members'
  innovations ``Y = sum y_i`` has covariance ``sum S_i`` when nothing is common, so
  ``Y^T (sum S_i)^-1 Y`` is chi-square with 3 degrees of freedom; above the named threshold
  (the sum taken without the member that deviates most on its own, so that one track on a
  neighbour's plot does not pass for a turn of all) the formation manoeuvres, and its tracks
  go back to the filter's own models (whose manoeuvre model follows the turn) for a while.
  Summing over the members makes the test see a common deviation of a fraction of one plot's
  error: the more members, the sooner a turn shows.
* :func:`common_velocity`, :func:`velocity_update`: a formation flies one velocity, so each
  member's velocity is measured by the mean of the others' (docs/architecture.md, "Tracks in
  formations"): their noise averages out over the members, where each track's own estimate
  carries its plots' noise alone.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from service.geo import FloatArray
from service.linalg import mahalanobis3
from service.tracking import kalman

IntArray = NDArray[np.intp]


def formation_groups(
    position: FloatArray, velocity: FloatArray, radius_m: float, speed_mps: float, neighbours: int
) -> IntArray:
    """Each track's formation (rows of ``position`` and ``velocity``, ``(n, 3)`` each): a label
    shared by the tracks of one formation, -1 for a track none of whose ``neighbours`` nearest
    tracks within ``radius_m`` has a velocity within ``speed_mps`` of its own.  The nearest
    few, not every track within the radius: the work is ``n * neighbours`` however crowded the
    tracks are, and a formation's nearest neighbours are its own members."""
    n = position.shape[0]
    out = np.full(n, -1, dtype=np.intp)
    k = min(neighbours, n - 1)
    if k < 1 or radius_m <= 0.0:
        return out
    _, near = cKDTree(position).query(position, k=k + 1, distance_upper_bound=radius_m)
    i = np.repeat(np.arange(n), k + 1)
    j = near.reshape(-1)
    keep = (j < n) & (j != i)  # (n: no neighbour that near)
    i, j = i[keep], j[keep]
    dv = velocity[i] - velocity[j]
    alike = np.einsum("kd,kd->k", dv, dv) <= speed_mps * speed_mps
    i, j = i[alike], j[alike]
    if i.shape[0] == 0:
        return out
    graph = coo_matrix((np.ones(i.shape[0]), (i, j)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    member = np.zeros(n, dtype=bool)
    member[i] = member[j] = True
    out[member] = label[member]
    return out


def manoeuvring(label: IntArray, y: FloatArray, S: FloatArray, chi2: float, members: int) -> IntArray:
    """The labels among ``label`` (one per associated track of a formation; ``y`` ``(k, 3)`` its
    innovation, ``S`` ``(k, 3, 3)`` that innovation's covariance) whose formation has at least
    ``members`` associated tracks and whose summed innovation, without its member of the
    largest own ``y^T S^-1 y``, exceeds ``chi2`` (module docstring), sorted.  Leaving that one
    out keeps a single track that took a neighbour's plot from passing for a manoeuvre of all."""
    if label.shape[0] == 0:
        return np.empty(0, dtype=np.intp)
    groups, inv = np.unique(label, return_inverse=True)
    own, fine = mahalanobis3(y, S)
    own = np.where(fine, own, np.inf)  # (a singular or not finite S: the one left out)
    order = np.lexsort((-own, inv))  # by group, the largest first
    first = np.ones(order.shape[0], dtype=bool)
    first[1:] = inv[order[1:]] != inv[order[:-1]]
    kept = np.ones(label.shape[0], dtype=bool)
    kept[order[first]] = False
    total = np.zeros((groups.shape[0], 3))
    cov = np.zeros((groups.shape[0], 3, 3))
    np.add.at(total, inv[kept], y[kept])
    np.add.at(cov, inv[kept], S[kept])
    q, ok = mahalanobis3(total, cov)
    big = np.bincount(inv, minlength=groups.shape[0]) >= members
    return np.asarray(groups[big & ok & (q > chi2)], dtype=np.intp)


def common_velocity(
    label: IntArray, velocity: FloatArray, variance: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Each track's formation velocity without it: the mean of the other members' horizontal
    ``velocity`` ``(n, 2)`` with the same ``label``, weighted by ``1 / variance`` ``(n,)``, and
    that mean's variance per axis, ``1 / sum`` of their weights; NaN for a track alone.
    Without the track's own, so that its velocity is not measured by itself."""
    labels, inv = np.unique(label, return_inverse=True)
    w = 1.0 / variance
    total_w = np.bincount(inv, weights=w, minlength=labels.shape[0])
    total_v = np.stack(
        [np.bincount(inv, weights=w * velocity[:, a], minlength=labels.shape[0]) for a in (0, 1)], 1
    )
    rest_w = total_w[inv] - w
    alone = ~(rest_w > 0.0)
    safe = np.where(alone, 1.0, rest_w)
    mean = (total_v[inv] - w[:, None] * velocity) / safe[:, None]
    mean[alone] = np.nan
    return mean, np.where(alone, np.nan, 1.0 / safe)


def _velocity_innovation(
    x: FloatArray, P: FloatArray, v: FloatArray, r: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Innovation ``y = v - H x`` of a measurement ``v`` ``(k, 2)`` of the horizontal velocity
    (``H`` picks east and north velocity) and the inverse of its covariance
    ``S = H P H^T + r I`` (closed form)."""
    s = P[:, 3:5, 3:5] + r[:, None, None] * np.eye(2)
    det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
    inv = np.stack([np.stack([s[:, 1, 1], -s[:, 0, 1]], 1), np.stack([-s[:, 1, 0], s[:, 0, 0]], 1)], 1)
    return v - x[:, 3:5], inv / det[:, None, None]


def velocity_gate(x: FloatArray, P: FloatArray, v: FloatArray, r: FloatArray) -> FloatArray:
    """``y^T S^-1 y`` of the measurement of :func:`velocity_update` (NaN where not finite)."""
    y, s_inv = _velocity_innovation(x, P, v, r)
    return np.asarray(np.einsum("ki,kij,kj->k", y, s_inv, y))


def velocity_update(
    x: FloatArray, P: FloatArray, v: FloatArray, r: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Kalman update (Joseph form, :func:`service.tracking.kalman.joseph_update`; Bar-Shalom,
    Li, Kirubarajan 2001, Section 5.2.3) of states ``x`` ``(k, 6)``, ``P`` ``(k, 6, 6)`` with a
    measurement ``v`` ``(k, 2)`` of their horizontal velocity of variance ``r`` ``(k,)`` per
    axis."""
    y, s_inv = _velocity_innovation(x, P, v, r)
    R = r[:, None, None] * np.eye(2)
    return kalman.joseph_update(x, P, R, y, s_inv, slice(3, 5))
