"""Candidate pairs of a window's plots with bounded memory and work, whatever arrives.

The initiators need the pairs of plots that one target could have produced: two plots within
a search radius (``max_speed * dt`` plus a few sigma, tens of kilometres) and, for the logic
initiator, a time gate.  A KD-tree ``query_pairs`` over the whole window returns *all* pairs
within the radius at once, which is quadratic in memory when many plots crowd one region (a
dense batch of the contract's 100 000 plots gives billions of pairs).  :func:`time_gated_pairs`
returns the same pairs with two bounds (:class:`~service.tracking.params.BoundParams`):

* **memory** -- candidates are materialised ``block`` at a time (plus at most one plot's own);
* **work** -- at most ``max_pairs`` candidates per call: when the window holds more, whole
  grid cells are searched, those with the fewest candidates first, stopping before the cell
  that would pass the bound (:func:`_within_work`).

A *candidate* of plot ``s`` is a plot later in (time, index) order that lies in one of the 3x3
cells around ``s``'s cell of a square grid of side ``radius`` in the first two coordinates, with
a time inside ``s``'s time range (widened by a rounding pad).  Every pair within the radius and
the time range is a candidate (a cell list), and the count per plot is known before any pair
is formed, so both bounds hold exactly.

When the whole window's pairs within the radius fit in one block and its candidates under
``max_pairs`` (the usual case), the pairs come from one ``query_pairs`` over the window (the
form used before these bounds), in that call's order, so results are exactly those of that
form; otherwise in (time, index) order of their first, then second plot.  Either way the *set*
of pairs is the same (tested against the ``query_pairs`` form); the order only decides which
of the tracks born in one update gets the lower id.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from service.geo import FloatArray

IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]
#: ``keep(i, j)``: the caller's exact gates on candidate pairs ``i`` before ``j``.
PairTest = Callable[[IntArray, IntArray], BoolArray]

#: The 3x3 block of grid cells around a cell, as (east, north) offsets.
_OFFSETS = np.array([(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)], dtype=np.int64)


#: Counts per cell go on a dense grid over the points' box when it has at most this many cells
#: beyond 4 per point (half a megabyte: cheaper than sorting the cells of a few thousand
#: points); wider boxes (points spread far apart) use the sorted cells instead.
_DENSE_GRID_CELLS = 65_536


def _empty() -> tuple[IntArray, IntArray]:
    e = np.empty(0, dtype=np.intp)
    return e, e


def _side(cell: float) -> float:
    """Grid cell side: the search radius, or 1 m when that is 0 (any side works for a radius
    of 0: only coincident points pair)."""
    return cell if cell > 0 else 1.0


def _cell_keys(xy: FloatArray, cell: float) -> tuple[NDArray[np.int64], int]:
    """Integer key of each point's grid cell, and the key stride of one east step (the north
    index has room for one empty cell on each side, so the 3x3 neighbours never wrap)."""
    ij = np.floor(xy / _side(cell)).astype(np.int64)
    ij -= ij.min(axis=0) - 1
    stride = int(ij[:, 1].max()) + 2
    return ij[:, 0] * stride + ij[:, 1], stride


def _neighbour_keys(keys: NDArray[np.int64], stride: int) -> NDArray[np.int64]:
    """``(n, 9)`` keys of the 3x3 cells around each key."""
    return keys[:, None] + _OFFSETS[:, 0] * stride + _OFFSETS[:, 1]


def _box_counts(keys: NDArray[np.int64], at: NDArray[np.int64], stride: int) -> IntArray:
    """For each key in ``at``, the points (``keys``: their cells) in the 3x3 cells around it."""
    size = int(max(keys.max(), at.max())) + stride + 2
    if size <= 4 * (keys.shape[0] + at.shape[0]) + _DENSE_GRID_CELLS:  # dense grid: no sort
        count = np.bincount(keys, minlength=size)
        around = np.zeros(size, dtype=np.intp)
        for off in (_OFFSETS[:, 0] * stride + _OFFSETS[:, 1]).tolist():  # the 9 cells
            lo, hi = max(off, 0), size + min(off, 0)
            around[lo - off : hi - off] += count[lo:hi]
        return around[at]
    cells, n_in = np.unique(keys, return_counts=True)
    nk = _neighbour_keys(at, stride)
    where = np.minimum(np.searchsorted(cells, nk), cells.shape[0] - 1)
    return np.asarray(np.where(cells[where] == nk, n_in[where], 0).sum(axis=1), dtype=np.intp)


def cell_counts(points: FloatArray, queries: FloatArray, cell: float) -> IntArray:
    """For each query, the points in the 3x3 cells around its own of a square grid of side
    ``cell`` (2-D coordinates): a bound on the points within ``cell`` of it."""
    lo = np.minimum(points.min(axis=0), queries.min(axis=0))
    ip = np.floor((points - lo) / _side(cell)).astype(np.int64) + 1  # >= 1: neighbours >= 0
    iq = np.floor((queries - lo) / _side(cell)).astype(np.int64) + 1
    stride = int(max(ip[:, 1].max(), iq[:, 1].max())) + 2
    return _box_counts(ip[:, 0] * stride + ip[:, 1], iq[:, 0] * stride + iq[:, 1], stride)


def _grid_total(xy: FloatArray, cell: float) -> int:
    """Sum over the points of the points in the 3x3 grid cells around each (itself included):
    twice a bound on the pairs within ``cell`` of each other, plus the points."""
    keys, stride = _cell_keys(xy, cell)
    return int(_box_counts(keys, keys, stride).sum())


def _one_query_tree(pos: FloatArray, radius: float, max_pairs: int, block: int) -> cKDTree | None:
    """The KD-tree for one ``query_pairs`` over all points when that stays within both bounds
    (else None): the plots in the 3x3 cells around each plot bound its partners within
    ``radius``, and where that bound is too loose the tree counts the pairs exactly (a
    dual-tree count, which forms no pairs)."""
    n = pos.shape[0]
    if n * n <= max_pairs and n * (n - 1) // 2 <= block:
        return cKDTree(pos)  # any n points: no grid needed
    total = _grid_total(pos[:, :2], radius)
    if total > max_pairs:
        return None
    tree = cKDTree(pos)
    if (total - n) // 2 <= block or (int(tree.count_neighbors(tree, radius)) - n) // 2 <= block:
        return tree
    return None


def _within_work(per_plot: IntArray, cell: IntArray, n_cells: int, max_pairs: int) -> BoolArray:
    """Plots whose candidates are searched: all when their total is within ``max_pairs``, else
    whole grid cells, the cells with the fewest candidates first (ties: lower cell rank),
    stopping before the first cell that would pass ``max_pairs``.  Where clutter crowds a
    region the pairs there are the least useful (every plot fits some velocity), while a
    target in a sparse region still forms its pairs and triples from the cell's plots of all
    times; those crowded plots are searched in a later update once the crowd has thinned."""
    if int(per_plot.sum()) <= max_pairs:
        return np.ones(per_plot.shape[0], dtype=bool)
    load = np.bincount(cell, weights=per_plot, minlength=n_cells)  # exact below 2^53
    by_load = np.lexsort((np.arange(n_cells), load))
    fits = np.cumsum(load[by_load]) <= max_pairs
    chosen = np.zeros(n_cells, dtype=bool)
    chosen[by_load[fits]] = True
    return chosen[cell]


def time_gated_pairs(
    time_s: FloatArray,
    pos: FloatArray,
    radius: float,
    dt_min: float,
    dt_max: float,
    keep: PairTest,
    max_pairs: int,
    block: int,
) -> tuple[IntArray, IntArray]:
    """Pairs ``(i, j)``, ``i`` before ``j`` in (time, index) order, that pass ``keep``.

    ``keep`` must only accept pairs within ``radius`` of each other (any metric at most the
    Euclidean one over ``pos``; the grid uses the first two coordinates) whose time difference
    ``t_j - t_i`` lies in ``[dt_min, dt_max]``; the search relies on both to skip the rest.
    Bounds and order: see the module docstring.
    """
    n = time_s.shape[0]
    if n < 2 or not dt_max >= dt_min:
        return _empty()
    tree = _one_query_tree(pos, radius, max_pairs, block)
    if tree is not None:
        pr = tree.query_pairs(radius, output_type="ndarray")
        if pr.shape[0] == 0:
            return _empty()
        a, b = pr[:, 0].astype(np.intp), pr[:, 1].astype(np.intp)
        swap = time_s[a] > time_s[b]  # query_pairs gives a < b: ties keep the lower index first
        i = np.where(swap, b, a)
        j = np.where(swap, a, b)
        ok = keep(i, j)
        return i[ok], j[ok]
    return _chunked(time_s, pos, radius, dt_min, dt_max, keep, max_pairs, block)


def _chunked(
    time_s: FloatArray,
    pos: FloatArray,
    radius: float,
    dt_min: float,
    dt_max: float,
    keep: PairTest,
    max_pairs: int,
    block: int,
) -> tuple[IntArray, IntArray]:
    """The cell-list search in time order, ``block`` candidates at a time (module docstring)."""
    n = time_s.shape[0]
    order = np.argsort(time_s, kind="stable")  # rank s -> plot; ties by index
    ts = time_s[order]
    keys, stride = _cell_keys(pos[order, :2], radius)
    # Ranks sorted by (cell, time): each cell's plots are one run, in time order.
    by_cell = np.argsort(keys, kind="stable")
    cells, first = np.unique(keys[by_cell], return_index=True)
    cell_rank = np.repeat(np.arange(cells.shape[0]), np.diff(np.append(first, n)))
    # One sortable number per plot: cell rank, then time within the cell.  Cells are spaced
    # wider than any time range searched, so a range never runs into the next cell.
    t0 = float(ts[0])
    span = float(ts[-1]) - t0 + max(abs(dt_min), abs(dt_max)) + 1.0
    code = cell_rank * span + (ts[by_cell] - t0)
    # Rounding pad on the time range: a few units in the last place of the largest number
    # formed, so the searched range always holds the exact gate ``[dt_min, dt_max]``.
    pad = 8.0 * float(np.spacing(max(float(code[-1]) + span, abs(t0) + abs(dt_max))))
    nk = _neighbour_keys(keys, stride)  # (n, 9)
    at = np.minimum(np.searchsorted(cells, nk), cells.shape[0] - 1)
    present = cells[at] == nk
    rel = (ts - t0)[:, None]
    lo = np.searchsorted(code, at * span + (rel + (dt_min - pad)), side="left")
    hi = np.searchsorted(code, at * span + (rel + (dt_max + pad)), side="right")
    width = np.where(present, np.maximum(hi - lo, 0), 0)  # (n, 9) candidates per cell
    per_plot = width.sum(axis=1)
    cell_of_plot = np.empty(n, dtype=np.intp)
    cell_of_plot[by_cell] = cell_rank
    searched = _within_work(per_plot, cell_of_plot, cells.shape[0], max_pairs)
    # Memory bound: the searched plots in time order, ``block`` candidates (plus one plot's
    # own) per chunk.
    ranks = np.flatnonzero(searched)
    total = np.cumsum(per_plot[ranks])
    chunk = (total - per_plot[ranks]) // max(block, 1)
    bounds = np.concatenate([[0], np.flatnonzero(np.diff(chunk)) + 1, [ranks.shape[0]]])
    out_i: list[IntArray] = []
    out_j: list[IntArray] = []
    for c0, c1 in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True):  # a few chunks
        rk = ranks[c0:c1]
        w = width[rk].ravel()
        m = int(w.sum())
        if m == 0:
            continue
        cell_of = np.repeat(np.arange(w.shape[0]), w)  # flat (plot, cell) of each candidate
        offs = np.arange(m) - np.repeat(np.cumsum(w) - w, w)
        s = rk[cell_of // _OFFSETS.shape[0]]
        q = by_cell[lo[rk].ravel()[cell_of] + offs]
        later = q > s
        s, q = s[later], q[later]
        ok = keep(order[s], order[q])
        s, q = s[ok], q[ok]
        sq = np.lexsort((q, s))
        out_i.append(order[s[sq]])
        out_j.append(order[q[sq]])
    if not out_i:
        return _empty()
    return np.concatenate(out_i), np.concatenate(out_j)
