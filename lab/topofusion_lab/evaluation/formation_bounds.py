"""What right association is worth in formations: the study's points with each radar's tracker
told whose plots are whose (evaluation only: the simulator's truth).

Each bound is the default tracker (:class:`~service.tracking.manager.TrackManager`) with one
change: the costs its one-to-one assignment solves (``TrackManager._assign``, the gated
candidates of a batch).  The gate, the filter, the tracks' quality (the clarity of the real
``d^2``), initiation and the life cycle are the tracker's own, and so is everything after it.

* ``truth``: a track takes no plot of another aircraft than its own (the aircraft of most of
  its plots so far, its ``truth_id``; a track with none yet, or a plot with none, as the
  tracker would): association without a mistake.
* ``true-position``: a candidate's cost is the plot's ``d^2`` (against the plot's own
  covariance) from the true position of the track's aircraft as the radar sees it (its biases
  applied, no noise) instead of from the track's prediction, and a candidate beyond the gate
  from it is dropped: one scan's assignment with a perfect prediction, whose mistakes the
  plots' noise alone makes.  With ``offset_m`` > 0 each track's reference is off by an error
  drawn once per track (normal, ``offset_m`` per horizontal axis): a prediction about as good
  as another radar's track of the aircraft, but free of this track's own mistakes.
* ``other-radar``: a candidate's cost is the plot's ``d^2`` from the other radars' track of
  the track's aircraft (the confirmed one of the smallest horizontal covariance, when smaller
  than the track's own), brought to the plot's time on its velocity and into this radar's
  view with every radar's true biases (registration without error); without such a track,
  the tracker's own ``d^2``.  An association aided by the more precise radars' tracks, the
  pairing (which track is of which aircraft) and the registration done right.

``python -m topofusion_lab.evaluation.formation_bounds`` prints, per point, the default
tracker's row and each bound's (the formation study's columns, the same messages);
``--no-hold`` runs every row with the correlation's hold of pairs whose tracks are contested
off (``correlation.book.hold_score`` 0), which a right association leaves without a cause.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.config import EngineConfig
from service.evaluation.truth import TruthLabelledTracker
from service.geo import FloatArray, Site
from service.pipeline.tracking_stage import TrackerFactory
from service.tracking import make_tracker
from service.tracking.assignment import assign
from service.tracking.base import PlotColumns, Tracker
from service.tracking.coincident import first_in_cell
from service.tracking.manager import TrackManager
from service.tracking.measurement import Measurements

#: The bounds, as ``--bound`` names and the study's variants.
BOUNDS = ("truth", "true-position", "other-radar")

#: True ECEF positions, as one radar sees them, of aircraft ``names`` at data times (NaN rows:
#: unknown).
Reference = Callable[[Sequence[str], FloatArray], FloatArray]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class RadarTruth:
    """What the truth says of one radar (evaluation only)."""

    #: The aircraft's true positions as the radar sees them.
    positions: Reference
    #: ECEF positions the radar reports -> where they are (its biases taken out) ...
    unbiased: Callable[[FloatArray], FloatArray]
    #: ... and back: true ECEF positions -> as the radar sees them.
    apparent: Callable[[FloatArray], FloatArray]


class BoundedTracker(TrackManager):
    """The default tracker whose assignment costs come from the truth (module docstring).  Set
    up by :func:`bounded_factory`: ``bound``, ``truth``, ``peers``, ``labels`` (the wrapper's
    tally: each track uid's aircraft), ``offset_m`` and ``seed``."""

    bound: str = "truth"
    truth: RadarTruth | None = None
    #: The run's trackers (``other-radar``: the other radars').
    peers: Sequence[BoundedTracker] = ()
    labels: Callable[[NDArray[np.int64]], NDArray[np.object_]] | None = None
    offset_m: float = 0.0
    seed: int = 0
    #: The aircraft of each of the batch's plots, in the rows the tracker measures (after its
    #: repeats are dropped).
    _plot_truth: NDArray[np.object_] = np.empty(0, dtype=object)

    def update(self, plots: PlotColumns, time_s: float) -> None:
        mp = self.params.measurement
        keep = first_in_cell(plots, self.site, mp.coincident_sigma, mp.altitude_sigma_m)
        self._plot_truth = np.asarray(plots.truth_id, dtype=object)[keep]
        super().update(plots, time_s)

    def _assign(
        self, tracks: Any, meas: Measurements, rows: IntArray, cols: IntArray, d2: FloatArray
    ) -> IntArray:
        gate = self.params.filter.gate_chi2
        if self.labels is None or rows.shape[0] == 0:
            return super()._assign(tracks, meas, rows, cols, d2)
        own = self.labels(tracks.uid[rows])
        plot = self._plot_truth[cols]
        known = np.array([o is not None and p is not None for o, p in zip(own, plot, strict=True)], bool)
        cost = np.array(d2, dtype=float, copy=True)
        if self.bound == "truth":
            cost[known & (own != plot)] = np.inf
        elif self.bound == "other-radar":
            k = np.flatnonzero(known)
            aided = self.other_radar_d2(tracks, rows[k], own[k], meas, cols[k])
            cost[k] = np.where(np.isnan(aided), cost[k], aided)
        else:
            k = np.flatnonzero(known)
            cost[k] = self.reference_d2(tracks.uid[rows[k]], own[k], meas, cols[k])
        ok = np.flatnonzero(cost <= gate)  # (the rest: never this track's plot)
        return np.sort(ok[assign(rows[ok], cols[ok], cost[ok], gate)])

    def reference_d2(
        self, uids: NDArray[np.int64], names: NDArray[np.object_], meas: Measurements, cols: IntArray
    ) -> FloatArray:
        """Each candidate's ``d^2`` from its track's reference: the true position of aircraft
        ``names`` as this radar sees it at the plot's time (plus the track's drawn error), against
        the plot's covariance; inf where the truth does not know the aircraft then."""
        assert self.truth is not None
        ecef = self.truth.positions([str(n) for n in names], meas.time_s[cols])
        out = np.full(cols.shape[0], np.inf)
        ok = ~np.isnan(ecef[:, 0])
        ref = self.site.ecef_to_enu(ecef[ok])
        if self.offset_m > 0.0:  # (drawn once per track: the same draw at every batch)
            ref[:, :2] += [
                np.random.default_rng([self.seed, int(u)]).normal(0.0, self.offset_m, 2) for u in uids[ok]
            ]
        y = meas.enu_m[cols[ok]] - ref
        out[ok] = np.einsum("ni,nij,nj->n", y, np.linalg.inv(meas.covariance[cols[ok]]), y)
        return out

    def other_radar_d2(
        self, tracks: Any, rows: IntArray, names: NDArray[np.object_], meas: Measurements, cols: IntArray
    ) -> FloatArray:
        """Each candidate's ``d^2`` from the other radars' most precise confirmed track of
        aircraft ``names`` (module docstring), NaN where none is more precise than the track."""
        assert self.truth is not None
        best: dict[str, tuple[float, BoundedTracker, RadarTruth, int]] = {}
        for peer in self.peers:
            if peer is self or peer.labels is None or peer.truth is None or len(peer._tracks) == 0:
                continue
            frame = peer.truth
            pt = peer._tracks
            spread = np.trace(pt.P[:, :2, :2], axis1=1, axis2=2)
            for i, name in enumerate(peer.labels(pt.uid)):
                if name is not None and pt.confirmed[i] and spread[i] < best.get(name, (np.inf,))[0]:
                    best[name] = (float(spread[i]), peer, frame, i)
        own = np.trace(tracks.P[rows, :2, :2], axis1=1, axis2=2)
        out = np.full(cols.shape[0], np.nan)
        for k, name in enumerate(names):
            found = best.get(name)
            if found is None or found[0] >= own[k]:
                continue
            _, peer, frame, i = found
            pt = peer._tracks
            t = meas.time_s[cols[k]]
            ecef = peer.site.enu_to_ecef(pt.x[i, :3] + pt.x[i, 3:] * (t - pt.t[i]))
            seen = self.truth.apparent(frame.unbiased(np.atleast_2d(ecef)))
            y = meas.enu_m[cols[k]] - self.site.ecef_to_enu(seen)[0]
            out[k] = float(y @ np.linalg.solve(meas.covariance[cols[k]], y))
        return out


def bounded_factory(
    config: EngineConfig,
    bound: str,
    truth_for: Callable[[str, Site], RadarTruth],
    offset_m: float = 0.0,
    seed: int = 0,
) -> TrackerFactory:
    """The engine's tracker factory (``Engine(tracker_factory=...)``) for a bound (one engine:
    its trackers see each other, ``other-radar``): ``truth_for(radar_id, site)`` gives what
    the truth says of the radar."""
    if bound not in BOUNDS:
        raise ValueError(f"unknown bound {bound!r}: one of {', '.join(BOUNDS)}")
    peers: list[BoundedTracker] = []

    def factory(site: Site, radar_id: str) -> Tracker:
        inner = make_tracker(
            site, config.window_s, config.initiator, radar_id, config.tracking, kind=BoundedTracker
        )
        assert isinstance(inner, BoundedTracker)
        outer = TruthLabelledTracker(inner)
        inner.bound, inner.labels = bound, outer.tally.of
        inner.peers = peers
        inner.truth, inner.offset_m, inner.seed = truth_for(radar_id, site), offset_m, seed
        peers.append(inner)
        return outer

    return factory


def no_hold(config: EngineConfig) -> EngineConfig:
    """``config`` with the correlation's hold of contested pairs off."""
    corr = config.correlation
    return replace(config, correlation=replace(corr, book=replace(corr.book, hold_score=0.0)))


def table(rows: Sequence[tuple[str, str, dict[str, float]]]) -> str:
    """The markdown table of ``(point, association, summary)`` rows (the study's
    :func:`~topofusion_lab.evaluation.formation.summarize`)."""
    out = [
        "| point | association | completeness | duplicates | astray | plots to another aircraft "
        "| ID switches / aircraft-h | pairs correct | pairs false (worst seed) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for point, name, s in rows:
        out.append(
            f"| {point} | {name} | {100 * s['completeness']:.1f} % | {100 * s['duplicates']:.2f} % "
            f"| {100 * s['astray']:.1f} % | {100 * s['plots_other']:.1f} % | {s['switches_per_h']:.2f} "
            f"| {s['correct_pct']:.1f} % | {s['false_pct']:.2f} % ({s['false_worst_pct']:.2f} %) |"
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    from topofusion_lab.evaluation import formation
    from topofusion_lab.evaluation.jobs import run_jobs

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--point", action="append", choices=[x.label for x in formation.POINTS])
    p.add_argument("--runs", type=int, default=formation.DEFAULT_RUNS, help="seeds per point")
    p.add_argument("--seed", type=int, default=0, help="seeds are seed+1 .. seed+runs (default 0)")
    p.add_argument("--bound", action="append", choices=BOUNDS, help="only these bounds (default both)")
    p.add_argument("--offset-m", type=float, default=0.0, help="true-position: each track's reference error")
    p.add_argument("--no-hold", action="store_true", help="the correlation's hold of contested pairs off")
    p.add_argument("--duration", type=float, help="data seconds per run (default the study's)")
    p.add_argument("--targets", type=int, help="aircraft (default the scenario's 30)")
    p.add_argument("--workers", type=int, help="processes (default up to 2)")
    args = p.parse_args(argv)
    if args.offset_m < 0:
        p.error("--offset-m must be >= 0")
    points = [x for x in formation.POINTS if not args.point or x.label in args.point]
    variants = ("now", *(args.bound or BOUNDS))
    jobs = [
        replace(j, offset_m=args.offset_m, hold=not args.no_hold)
        for j in formation.make_jobs(args.runs, args.seed, points, args.duration, args.targets, variants)
    ]
    workers = min(2, os.cpu_count() or 1) if args.workers is None else args.workers

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    done = run_jobs(formation.run_one, jobs, workers, progress, "formation bounds")
    rows = []
    for i, point in enumerate(points):
        for v in variants:
            runs = [r for r in done if r["index"] == i and r["variant"] == v]
            name = v if v != "true-position" or args.offset_m == 0 else f"{v}, {args.offset_m:g} m off"
            rows.append((point.label, "tracker" if v == "now" else name, formation.summarize(runs)))
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
