"""Clear decisions: a pair whose evidence is unambiguous is confirmed at its first update.

The pair book accumulates single decisions (M of N updates) and the evidence module
accumulates looks (:mod:`.evidence`): both are there for the cases one snapshot cannot settle,
two aircraft closer than the radars can tell apart.  Waiting for them costs every other pair
three or four scans.  As in a sequential test (Wald's SPRT), a look whose likelihood ratio
already crosses the bound ends the test at once; only the ambiguous cases take more looks.

A candidate ``(i, j)`` of one update is **clear** when

* its single decision accepts it (the topology match, SVD paper Sections 1.4-1.6, or once
  registered the compensated chi-square, He et al.'s test);
* every rival sharing one of its tracks, accepted or not, costs at least ``clear_margin``
  more.  The costs are chi-square excesses, so between the pair and its best rival the
  likelihood ratio is at least ``exp(clear_margin / 2)`` (12: about 400 to 1); a rival the
  method could not decide at all (no fit, outside its gates) is none;
* neither track has a neighbour of its own radar within ``isolation_m`` (horizontally, every
  track brought to the update time) that is tentative, or confirmed and flying with it
  (velocity within ``isolation_velocity_mps``).  A confirmed neighbour is in the update's
  snapshots, so its candidates are the rivals above; a tentative one is not, and the other
  radar may hold the aircraft it follows confirmed.  One flying with it makes the track part
  of a group (a formation), where one update's margin can be chance: those pairs wait for the
  evidence, so what it does for dense groups is unchanged; an aircraft crossing another
  (another heading or level) is not held back by it;
* both tracks' quality (``TrackTable.quality``, the tracker's figure of how unambiguous each
  track's recent plot associations were) is at least ``min_quality``.  A track whose plots
  were contested (two aircraft in one gate, a track that may have swapped) can carry the
  other aircraft's state while passing every test above: its pairs are paired with caution,
  by the accumulated evidence and the M-of-N book.  NaN (not known) counts as clear, so a
  tracker that does not say changes nothing.

A clear candidate is accepted without the looks :class:`~.evidence.EvidenceBook` otherwise
wants (but never against a history that rejects it) and, once the one-to-one assignment
chooses it, enters the book confirmed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.correlation.assignment import rival_costs
from service.correlation.base import BoolArray, FloatArray, IntArray
from service.correlation.pairkeys import find
from service.geo import Site
from service.tracking.base import TrackTable

#: Above this many row-point pairs :func:`companions` finds neighbours by a k-d tree (a few
#: per track) instead of every row against every point: below it the tree's set-up costs more.
DENSE_PAIRS = 20_000


@dataclass(frozen=True)
class PromptParams:
    """When one update's decision is clear enough to confirm a pair (module docstring)."""

    #: Confirm clear pairs at their first update (False: every pair waits for the book's M of N).
    enabled: bool = True
    #: Least cost (chi-square excess) by which every rival must lose: likelihood ratio
    #: ``exp(margin / 2)`` against the best rival (12: about 400 to 1; twice the assignment's
    #: ambiguity margin).
    clear_margin: float = 12.0
    #: No tentative track of the same radar, nor a confirmed one flying with it, may be this
    #: close (m, horizontal).  Twice the cross-range error of an en-route radar at 250 km
    #: (0.2 deg: 870 m).
    isolation_m: float = 2_000.0
    #: A confirmed neighbour flies with the track when their horizontal velocities differ by
    #: less than this (m/s): a formation's tracks share one velocity up to their errors (tens of
    #: m/s for young tracks), two aircraft passing each other differ by far more.
    isolation_velocity_mps: float = 40.0
    #: Least quality (``TrackTable.quality``, in [0, 1]; NaN counts as clear) both tracks must
    #: have for their pair to be confirmed at its first look; below it the pair waits for the
    #: accumulated evidence (``EvidenceParams.min_looks``) and the book's M of N.  The quality
    #: is an average, over about five associations, of each association's likelihood share
    #: among the plots and tracks it competed with (1: no rival).  0 (the default) turns the
    #: rule off: on the national stream (docs/correlation.md, "Caution with ambiguous tracks")
    #: 0.8 holds back 51 of 140 wrong clear looks in 300 s but also 1.9 % of the right ones,
    #: leaves 9 more of 33 371 aircraft unpaired after 120 s and costs 8-11 % more correlation
    #: CPU; where formations are common, 0.8 is the measured choice.
    min_quality: float = 0.0


def clear_of_rivals(
    index_a: IntArray, index_b: IntArray, cost: FloatArray, accepted: BoolArray, margin: float
) -> BoolArray:
    """Accepted candidates whose every rival (another candidate sharing a track, finite cost)
    costs at least ``margin`` more (vectorised; :func:`tests.reference_forms` has the loop)."""
    finite = np.isfinite(cost)
    c = np.where(finite, cost, np.inf)
    own = np.where(finite, cost, 0.0)  # (a non-finite cost is never clear: no inf - inf)
    gap = np.minimum(rival_costs(index_a, c), rival_costs(index_b, c)) - own
    return np.asarray(accepted & finite & (gap >= margin))


def quality_clear(
    quality_a: FloatArray | None, quality_b: FloatArray | None, min_quality: float
) -> BoolArray:
    """Per candidate: are both tracks' qualities (row for row; None: not known) at least
    ``min_quality``?  NaN (not known) passes: a tracker that gives none changes nothing."""
    n = 0 if quality_a is None else len(quality_a)
    n = n if quality_b is None else len(quality_b)
    ok = np.ones(n, dtype=bool)
    for q in (quality_a, quality_b):
        if q is not None:
            ok &= ~(np.asarray(q, dtype=float) < min_quality)  # (NaN < x is False: clear)
    return ok


def companions(
    position: FloatArray,
    velocity: FloatArray,
    up: FloatArray | None,
    rows: IntArray,
    radius_m: float,
    velocity_mps: float,
    any_velocity: BoolArray,
) -> BoolArray:
    """For each of ``rows``: is another point within ``radius_m`` horizontally (the component
    along ``up`` removed; None: none) that flies with it (horizontal velocity within
    ``velocity_mps``), or is one of ``any_velocity`` whatever its velocity?"""
    n = len(rows)
    if n == 0 or len(position) < 2:
        return np.zeros(n, dtype=bool)
    if up is not None:  # (projected once per point, not once per pair: the same differences)
        position = position - (position @ up)[:, None] * up
        velocity = velocity - (velocity @ up)[:, None] * up
    if n * len(position) > DENSE_PAIRS:
        return _companions_sparse(position, velocity, rows, radius_m, velocity_mps, any_velocity)
    d = position[rows][:, None, :] - position[None, :, :]
    dv = velocity[rows][:, None, :] - velocity[None, :, :]
    near = np.einsum("ijk,ijk->ij", d, d) <= radius_m**2  # (NaN positions are never near)
    near &= any_velocity[None, :] | (np.einsum("ijk,ijk->ij", dv, dv) < velocity_mps**2)
    near[np.arange(n), rows] = False  # (a point is not its own companion)
    return np.asarray(near.any(axis=1))


def _companions_sparse(
    position: FloatArray,
    velocity: FloatArray,
    rows: IntArray,
    radius_m: float,
    velocity_mps: float,
    any_velocity: BoolArray,
) -> BoolArray:
    """:func:`companions` (positions already projected) by the pairs within ``radius_m`` a
    k-d tree finds: a few per track in traffic, where the dense form builds every row against
    every point (a radar's whole table at its update)."""
    finite = np.flatnonzero(np.isfinite(position).all(axis=1))  # (NaN positions are never near)
    tree = cKDTree(position[finite])
    sdm = tree.sparse_distance_matrix(cKDTree(position[finite]), radius_m, output_type="ndarray")
    i, j = finite[sdm["i"]], finite[sdm["j"]]
    dv = velocity[i] - velocity[j]
    hit = (i != j) & (any_velocity[j] | (np.einsum("ij,ij->i", dv, dv) < velocity_mps**2))
    near = np.zeros(len(position), dtype=bool)
    near[i[hit]] = True
    return near[rows]


def isolated(
    table: TrackTable,
    site: Site | None,
    time_s: float,
    track_ids: np.ndarray,
    radius_m: float,
    velocity_mps: float = np.inf,
    table_ids: np.ndarray | None = None,
) -> BoolArray:
    """For each of ``track_ids`` (tracks of ``table``): no other track of the table within
    ``radius_m`` horizontally in the site's plane (every track brought to ``time_s`` at its
    velocity) that is tentative, or confirmed with a horizontal velocity within
    ``velocity_mps`` of its own (a reference source, ``site`` None: in ECEF).  ``table_ids``:
    what ``track_ids`` are found among, row for row (None: the table's track ids; the
    correlation gives track keys, :mod:`.pairkeys`)."""
    n = len(track_ids)
    if n == 0 or len(table) < 2:
        return np.ones(n, dtype=bool)
    pos = table.position_ecef_m + table.velocity_ecef_mps * (time_s - table.time_s)[:, None]
    idx = find(table.track_id if table_ids is None else table_ids, track_ids)
    found, at = idx >= 0, np.maximum(idx, 0)
    up = site.rotation[:, 2] if site is not None else None
    near = companions(pos, table.velocity_ecef_mps, up, at, radius_m, velocity_mps, ~table.confirmed)
    return np.asarray(~found | ~near)
