"""Tracks flying in formation: who flies with whom, and when a formation manoeuvres.

Aircraft in formation fly straight together, a few hundred metres to a few kilometres apart,
closer than any separation minimum of controlled traffic (3 NM, 5.6 km, in a terminal area).
Such a track predicts with the formation's quiet model (:class:`~.params.FormationParams`):
a missed plot then leaves it where its aircraft is instead of where its last few noisy plots
pointed, and a neighbour's plot falls outside its gate more often.

* :func:`formation_groups`: a track flies in formation when a neighbour of the same radar lies
  within ``radius_m`` at a velocity within ``speed_mps`` of its own (both at one data time);
  the formations are the connected groups of such neighbours.
* :func:`manoeuvring`: a formation turns or changes speed as one, so its members' innovations
  share a common part, while their noise is each their own.  The sum of the members'
  innovations ``Y = sum y_i`` has covariance ``sum S_i`` when nothing is common, so
  ``Y^T (sum S_i)^-1 Y`` is chi-square with 3 degrees of freedom; above the named threshold
  (the sum taken without the member that deviates most on its own, so that one track on a
  neighbour's plot does not pass for a turn of all) the formation manoeuvres, and its tracks
  go back to the filter's own models (whose manoeuvre model follows the turn) for a while.
  Summing over the members makes the test see a common deviation of a fraction of one plot's
  error: the more members, the sooner a turn shows.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from service.geo import FloatArray
from service.linalg import mahalanobis3

IntArray = NDArray[np.intp]


def formation_groups(
    position: FloatArray, velocity: FloatArray, radius_m: float, speed_mps: float
) -> IntArray:
    """Each track's formation (rows of ``position`` and ``velocity``, ``(n, 3)`` each): a label
    shared by the tracks of one formation, -1 for a track with no neighbour within
    ``radius_m`` whose velocity differs from its own by at most ``speed_mps``."""
    n = position.shape[0]
    out = np.full(n, -1, dtype=np.intp)
    if n < 2 or radius_m <= 0.0:
        return out
    pairs = cKDTree(position).query_pairs(radius_m, output_type="ndarray")
    if pairs.shape[0] == 0:
        return out
    dv = velocity[pairs[:, 0]] - velocity[pairs[:, 1]]
    alike = pairs[np.einsum("kd,kd->k", dv, dv) <= speed_mps * speed_mps]
    if alike.shape[0] == 0:
        return out
    i, j = alike[:, 0], alike[:, 1]
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
    own, _ = mahalanobis3(y, S)  # (not finite: the largest)
    own = np.where(np.isfinite(own), own, np.inf)
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
