"""A radar's detection probability as its established tracks show it, and the misses in a
row that delete such a track (``ManagerParams.deletion_miss_probability``).

A confirmed track is deleted after a run of expected misses; three, on a radar that detects an
aircraft 95 times in 100, is a run such an aircraft gives once in 8 000 looks.  On a radar of
Pd 0.7 it comes about every 50 looks, so a fixed count deleted and re-initiated each of its
tracks every 5-8 minutes (at a 6-10 s scan), each time under a new track number, and every pair
and system track on it started again.  The count is therefore the shortest run that an
aircraft still there gives with at most the named probability (:func:`misses_to_delete`).

The rule holds for *established* tracks, confirmed with ``established_plots`` plots or more;
younger confirmed tracks keep ``confirmed_max_misses``.  Clutter makes young confirmed tracks
that soon miss: counted, they lowered the measured Pd, which let them live longer, which
lowered it further (two radars in 3 000 clutter plots a scan ended with 87 % of their
confirmed tracks on clutter, against 51 % with a fixed three).

The Pd is measured in data time over the radar's established tracks (:class:`DetectionMeter`):
the hits they take against the looks they are due, one a scan each (a batch ``dt`` after the
previous one is due ``dt / scan`` of a look from each, a sector batch its share of the scan),
both summed with an exponential memory of ``detection_memory_scans``; a batch late after the
one before (``LATE_GAP_FACTOR``: lost batches, a silent radar) counts neither.  The looks of
the M-of-N history cannot give it: a miss counts there only where the batch's plots cover the
track's azimuth, and a sector's plots around a formation end where its edge aircraft was
missed, so most misses of a formation's edge tracks are never counted (a radar of Pd 0.75
measured so showed 0.94).  Counting looks by time has the opposite, smaller bias: a track whose aircraft
has left the coverage is due looks it cannot have until it is deleted (a few scans of a
track's life), so the measured Pd is a few percent low where aircraft are apart (the national
scenario's radars of Pd 0.90-0.95 measure 0.87-0.93), which keeps a track a look longer, not
shorter.  Where they are not, it reads high: a hit is any plot a track took, and in a dense
formation a track whose aircraft was missed often takes a neighbour's (the formation study's
radar C, Pd 0.75 and the largest gates, measures a median 0.91 in the 2x lattice and 0.95 in the
1x one, so it mostly keeps 3; with every radar at Pd 0.7 the three measure 0.70, 0.82 and 0.86).
It is what the tracks show, and so what the rule weighs.  A radar with fewer than about five
established tracks never gathers ``detection_min_looks`` in its memory and keeps
``confirmed_max_misses``.  Cost: a few sums a batch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from service.tracking.params import ManagerParams


def misses_to_delete(pd: float, probability: float, fewest: int, most: int) -> int:
    """Expected misses in a row that delete a confirmed track on a radar of detection
    probability ``pd``: the smallest ``k`` with ``(1 - pd)^k <= probability``, within
    ``[fewest, most]``; ``fewest`` when ``probability`` is 0 (the rule off)."""
    most = max(most, fewest)
    q = 1.0 - pd
    if probability <= 0.0 or q <= probability:  # off, or one miss is already that unlikely
        return fewest
    if q >= 1.0:  # no hit at all
        return most
    # (the tolerance: (1 - 0.9)^3 is 1.0000000000000002e-3 in floats, not above 1e-3)
    return min(max(math.ceil(math.log(probability) / math.log(q) - 1e-9), fewest), most)


#: A batch more than this many times the usual gap after the one before it (the radar was
#: silent, or batches were lost) counts neither looks nor hits: looks counted by time would be
#: due from every track for the whole gap, while the batch holds the plots of its own sector
#: only, and each loss would read as misses.
LATE_GAP_FACTOR = 1.5
#: The usual gap between a radar's batches: an exponential mean over about this many batches.
GAP_MEMORY_BATCHES = 8


@dataclass(frozen=True)
class DetectionMeter:
    """The share of due looks that the radar's established tracks took a plot in (module
    docstring), in data time.  Immutable: an update makes the next one
    (:meth:`added`), which the tracker keeps only once its whole batch has succeeded."""

    params: ManagerParams
    hits: float = 0.0
    looks: float = 0.0
    scans: float = 0.0
    last_time_s: float | None = None
    gap_s: float | None = None  # the usual gap between batches (``GAP_MEMORY_BATCHES``)

    def added(self, hits: int, established: int, time_s: float, scan_s: float) -> DetectionMeter:
        """After one batch at ``time_s`` in which ``hits`` of the ``established`` tracks
        (established before it) took a plot."""
        last = self.last_time_s
        now = time_s if last is None else max(last, time_s)
        if last is None or scan_s <= 0.0:
            return replace(self, last_time_s=now)
        gap = time_s - last
        usual = self.gap_s
        if gap <= 0.0 or gap > scan_s or (usual is not None and gap > LATE_GAP_FACTOR * usual):
            return replace(self, last_time_s=now)  # late, or no time passed: not counted
        due = gap / scan_s
        keep = math.exp(-due / self.params.detection_memory_scans)
        return replace(
            self,
            hits=keep * self.hits + hits,
            looks=keep * self.looks + due * established,
            scans=keep * self.scans + due,
            last_time_s=now,
            gap_s=gap if usual is None else usual + (gap - usual) / GAP_MEMORY_BATCHES,
        )

    @property
    def pd(self) -> float | None:
        """The measured detection probability; None before ``detection_min_looks`` looks over
        ``detection_min_scans`` scans (weighted as the sums are)."""
        if self.looks < self.params.detection_min_looks or self.scans < self.params.detection_min_scans:
            return None
        return min(self.hits / self.looks, 1.0)

    def misses_to_delete(self) -> int:
        """Expected misses in a row that delete an established track of this radar now."""
        p = self.params
        pd = self.pd
        if pd is None:
            return p.confirmed_max_misses
        fewest, most = p.confirmed_max_misses, p.confirmed_misses_cap
        return misses_to_delete(pd, p.deletion_miss_probability, fewest, most)
