"""Topology sequences: each track's neighbours, in its own radar's frame (SVD paper Section 2 step 1).

The paper's topology sequence of a reference track is the list of vectors ``z_i = x_i - x_0``
from it to its neighbours within 10 km, sorted by increasing azimuth (Section 1.2).  The
10 km sphere assumes dense traffic; en-route aircraft are often 20-50 km apart.  The
neighbourhood here is *adaptive*: every neighbour within ``radius_m``, and if that gives
fewer than ``min_neighbours``, the nearest ones out to ``max_radius_m``.  The similarity
model of Eq. (6) stays valid over such distances because the Jacobians of Eq. (2) change
little over a few tens of km at ranges of 100 km and more (the translation of Eq. (4) grows
linearly with the neighbourhood size; the fit absorbs its constant part).

Neighbours are found with one ``cKDTree.query`` for all tracks (k nearest with a distance
bound), returned as a padded index array (``-1`` = none).  When only a few tracks' neighbourhoods
are wanted (a registered update asks for a handful of candidate references among hundreds of
tracks), a full distance scan from those tracks finds the same neighbours for less than the
cost of building the tree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.correlation.base import FloatArray


@dataclass(frozen=True)
class TopologyParams:
    """Neighbourhood of a reference track."""

    #: The paper's neighbourhood radius (10 km, Section 1.2): every neighbour inside is used.
    radius_m: float = 10_000.0
    #: Adaptive extension: with fewer than this many neighbours within ``radius_m`` ...
    min_neighbours: int = 4
    #: ... take the nearest ones out to this radius (``radius_m`` disables the extension).
    max_radius_m: float = 60_000.0
    #: Cap on the sequence length (the nearest are kept); bounds the work per candidate.
    max_neighbours: int = 8


#: Up to this many (queried track, track) distances the neighbours are found by a full
#: distance scan instead of a KD-tree (same neighbours; building a tree over a radar's
#: ~750 tracks costs more than ~20 000 distances).  Speed only: never changes a result.
BRUTE_FORCE_MAX_DISTANCES = 20_000


def _nearest_by_scan(
    enu: FloatArray, query_rows: NDArray[np.intp], k: int, bound: float
) -> tuple[FloatArray, NDArray[np.intp]]:
    """``cKDTree(enu).query(enu[query_rows], k, distance_upper_bound=bound)`` by a full scan:
    the ``k`` nearest of each queried track sorted by distance (itself first), ``inf`` and
    index ``n`` beyond ``bound`` (kept strictly within it, as the tree does)."""
    n = enu.shape[0]
    q = enu[query_rows]
    d2 = np.zeros((len(query_rows), n))
    for c in range(3):  # per coordinate: (q, n) arrays, no (q, n, 3) temporary
        dc = enu[None, :, c] - q[:, c, None]
        dc *= dc
        d2 += dc
    dist = np.sqrt(d2, out=d2)
    # The track itself first (ahead of any other track at distance 0), then dropped by the caller.
    dist[np.arange(len(query_rows)), query_rows] = -1.0
    near = np.argpartition(dist, k - 1, axis=1)[:, :k] if k < n else np.broadcast_to(np.arange(n), dist.shape)
    d = np.take_along_axis(dist, near, axis=1)
    order = np.argsort(d, axis=1, kind="stable")
    d = np.take_along_axis(d, order, axis=1)
    idx = np.take_along_axis(near, order, axis=1)
    out = d < bound
    return np.where(out, d, np.inf), np.where(out, idx, n)


def neighbourhoods(
    enu: FloatArray, params: TopologyParams | None = None, rows: NDArray[np.intp] | None = None
) -> NDArray[np.intp]:
    """Padded neighbour indices ``(n, max_neighbours)``, nearest first, ``-1`` where none.

    ``rows``: only these tracks' neighbourhoods are searched (the others are all ``-1``); the
    neighbours are still any of the ``n`` tracks.  A correlation update needs the
    neighbourhoods of candidate references only.
    """
    p = params or TopologyParams()
    n = enu.shape[0]
    kmax = int(p.max_neighbours)
    if n < 2 or kmax < 1:
        return np.full((n, max(kmax, 0)), -1, dtype=np.intp)
    k = min(kmax + 1, n)
    bound = max(p.max_radius_m, p.radius_m)
    query = enu if rows is None else enu[rows]
    nq = query.shape[0]
    if rows is not None and nq * n <= BRUTE_FORCE_MAX_DISTANCES:
        dist, idx = _nearest_by_scan(enu, np.asarray(rows, dtype=np.intp), k, bound)
        return _padded(dist, idx, n, rows, kmax, p)
    tree = cKDTree(enu)
    # Two searches giving the same neighbours as one k-nearest search within ``bound``: the
    # first ``min_neighbours + 1`` within ``bound``; only where the last of these lies within
    # ``radius_m`` can more be kept, and all of those (and the ones before) lie within
    # ``radius_m``, so a second, cheap search with that bound completes them.
    k1 = min(max(p.min_neighbours, 0) + 2, k)
    dist, idx = tree.query(query, k=k1, distance_upper_bound=bound)
    dist = dist.reshape(nq, k1)
    idx = idx.reshape(nq, k1)
    if k1 < k:
        more = np.flatnonzero(dist[:, k1 - 1] <= p.radius_m)
        dist = np.concatenate([dist, np.full((nq, k - k1), np.inf)], axis=1)
        idx = np.concatenate([idx, np.full((nq, k - k1), n)], axis=1)
        if more.size:
            d2, i2 = tree.query(query[more], k=k, distance_upper_bound=p.radius_m)
            dist[more] = d2.reshape(more.size, k)
            idx[more] = i2.reshape(more.size, k)
    return _padded(dist, idx, n, rows, kmax, p)


def _padded(
    dist: FloatArray,
    idx: NDArray[np.intp],
    n: int,
    rows: NDArray[np.intp] | None,
    kmax: int,
    p: TopologyParams,
) -> NDArray[np.intp]:
    """The neighbourhoods from the sorted k-nearest search results (the track itself first)."""
    dist = dist[:, 1:]  # column 0 is the track itself (distance 0)
    idx = idx[:, 1:]
    rank = np.arange(dist.shape[1])[None, :]
    keep = np.isfinite(dist) & ((dist <= p.radius_m) | (rank < p.min_neighbours))
    found = np.where(keep, idx, -1).astype(np.intp)
    if rows is None:
        out = found
    else:
        out = np.full((n, found.shape[1]), -1, dtype=np.intp)
        out[rows] = found
    if out.shape[1] < kmax:
        out = np.concatenate([out, np.full((n, kmax - out.shape[1]), -1, dtype=np.intp)], axis=1)
    return out


def sort_by_azimuth(z: FloatArray, mask: NDArray[np.bool_]) -> NDArray[np.intp]:
    """Order (P, K) putting valid vectors by increasing azimuth (clockwise from north), padding last."""
    az = np.mod(np.arctan2(z[..., 0], z[..., 1]), 2 * np.pi)
    return np.argsort(np.where(mask, az, np.inf), axis=-1, kind="stable")


def gather_points(
    enu: FloatArray, cov: FloatArray, nbr: NDArray[np.intp], ref: NDArray[np.intp], trim: bool = False
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Points of candidate references ``ref`` and their neighbours: ``(P, K+1, 3)``, covs, mask.

    Index 0 is the reference itself, 1.. its neighbours (padding masked out, zero-filled,
    covariance identity so that nothing singular reaches the linear algebra).  ``trim``: drop
    trailing padding columns no reference uses (neighbours are a prefix of each row, nearest
    first), so that the per-candidate arrays are no wider than the longest sequence.
    """
    nb = nbr[ref]
    if trim and nb.shape[1]:
        # at least one (padding) column: the batched fit indexes neighbour 0 of every side
        nb = nb[:, : max(1, int((nb >= 0).sum(axis=1).max(initial=0)))]
    idx = np.concatenate([ref[:, None], nb], axis=1)
    mask = idx >= 0
    n = enu.shape[0]
    safe = np.where(mask, idx, n)  # padding reads an appended zero point / identity covariance
    pts = np.concatenate([enu, np.zeros((1, 3))])[safe]
    cv = np.concatenate([cov, np.eye(3)[None]])[safe]
    return pts, cv, mask
