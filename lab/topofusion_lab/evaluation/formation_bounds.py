"""What right association is worth in formations: the study's points with each radar's tracker
told whose plots are whose (evaluation only: the simulator's truth).

Each bound is the default tracker (:class:`~service.tracking.manager.TrackManager`) without
the aid of association (``tracking.aid``, on by default; ``--bound aided`` is the service's aid,
the default itself), with one change: the costs its one-to-one assignment solves
(``TrackManager._assign``, the gated candidates of a batch).  The gate, the filter, the
tracks' quality (the clarity of the real ``d^2``), initiation and the life cycle are the
tracker's own, and so is everything after it.

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
* ``paired``: no truth at all, what the service itself could do: a candidate's cost is the
  plot's ``d^2`` from the most precise track the engine's correlation pairs with the track
  (its confirmed pairs, the partner more precise than the track), brought to the plot's time
  on its velocity and into this radar's view with the engine's registration (each radar's
  five terms of ``/biases``); without such a partner, the tracker's own ``d^2``.
  ``paired-true-biases``: the same pairs with the true biases (a registration without error).
  ``paired-covariance``: the pairs as ``paired``, each pair of radars' own registration (its
  pair correlator's), and the partner taken only when its covariance in this radar's view
  (its track's plus the registration's, the relative covariance through the transform) is
  smaller than the track's own and the registration's part of it at most
  :data:`REGISTRATION_SIGMA_M`; the cost then against the plot's covariance plus that one.
  ``--aid-lag-s S``: the correlation's pairs and registrations as they were ``S`` of data time
  before the batch (:class:`EngineRef`), what a tracker gets deterministically when the
  correlation runs in another process.

The study's points include the lattice *in traffic* (:func:`~topofusion_lab.evaluation.
formation.with_traffic`): the formation among 32 other aircraft, which give the registration the
spread a formation alone lacks; only the formation's aircraft are scored.

``python -m topofusion_lab.evaluation.formation_bounds`` prints, per point, the default
tracker's row and each bound's (the formation study's columns, the same messages);
``--no-hold`` runs every row with the correlation's hold of pairs whose tracks are contested
off (``correlation.book.hold_score`` 0), which a right association leaves without a cause.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.config import EngineConfig
from service.correlation.partner_view import into_view
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
BOUNDS = ("truth", "true-position", "other-radar", "paired", "paired-true-biases", "paired-covariance")

#: True ECEF positions, as one radar sees them, of aircraft ``names`` at data times (NaN rows:
#: unknown).
Reference = Callable[[Sequence[str], FloatArray], FloatArray]
IntArray = NDArray[np.intp]
#: ``paired-covariance``: a partner is taken only where the registration brings it into this
#: radar's view with at most this horizontal 1-sigma (m; the registration's own relative
#: covariance through the transform): a formation's spacing is some 800 m at 2x.
REGISTRATION_SIGMA_M = 50.0


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
    #: ``paired``: the run's engine (its confirmed pairs and registered biases) and this
    #: tracker's radar.
    engine: EngineRef | None = None
    radar_id: str = ""

    def update(self, plots: PlotColumns, time_s: float) -> None:
        mp = self.params.measurement
        keep = first_in_cell(plots, self.site, mp.coincident_sigma, mp.altitude_sigma_m)
        self._plot_truth = np.asarray(plots.truth_id, dtype=object)[keep]
        super().update(plots, time_s)

    def _assign(
        self, tracks: Any, meas: Measurements, rows: IntArray, cols: IntArray, d2: FloatArray
    ) -> IntArray:
        gate = self.params.filter.gate_chi2
        paired = self.bound.startswith("paired")  # (no truth: these need no labels)
        if rows.shape[0] == 0 or (self.labels is None and not paired):
            return super()._assign(tracks, meas, rows, cols, d2)
        cost = np.array(d2, dtype=float, copy=True)
        if paired:
            aided = self.paired_d2(tracks, rows, meas, cols)
            cost = np.where(np.isnan(aided), cost, aided)
        else:
            assert self.labels is not None
            own = self.labels(tracks.uid[rows])
            plot = self._plot_truth[cols]
            known = np.array([o is not None and p is not None for o, p in zip(own, plot, strict=True)], bool)
            k = np.flatnonzero(known)
            if self.bound == "truth":
                cost[known & (own != plot)] = np.inf
            elif self.bound == "other-radar":
                aided = self.other_radar_d2(tracks, rows[k], own[k], meas, cols[k])
                cost[k] = np.where(np.isnan(aided), cost[k], aided)
            else:
                cost[k] = self.reference_d2(tracks.uid[rows[k]], own[k], meas, cols[k])
        return assign(rows, cols, cost, gate)  # (a cost beyond the gate: never this track's plot)

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
            ecef, _ = peer.track_at(i, meas.time_s[cols[k]])
            seen = self.truth.apparent(frame.unbiased(ecef))
            y = meas.enu_m[cols[k]] - self.site.ecef_to_enu(seen)[0]
            out[k] = float(y @ np.linalg.solve(meas.covariance[cols[k]], y))
        return out

    def track_at(self, i: int, t: float) -> tuple[FloatArray, FloatArray]:
        """This tracker's track ``i`` moved to data time ``t`` on its velocity: its ECEF position
        and ECEF velocity, ``(1, 3)`` each."""
        pt = self._tracks
        ecef = np.atleast_2d(self.site.enu_to_ecef(pt.x[i, :3] + pt.x[i, 3:] * (t - pt.t[i])))
        vel = np.atleast_2d(self.site.enu_to_ecef(pt.x[i, 3:]) - self.site.enu_to_ecef(np.zeros(3)))
        return ecef, vel

    def paired_d2(self, tracks: Any, rows: IntArray, meas: Measurements, cols: IntArray) -> FloatArray:
        """Each candidate's ``d^2`` (module docstring, ``paired``) from the most precise track
        the engine pairs with the candidate's track (its confirmed pairs; only a track more
        precise than this one), brought to the plot's time on its velocity and into this
        radar's view by the registration: the engine's five terms of each radar (``/biases``),
        or (``paired-true-biases``) the radars' true biases.  NaN where there is none."""
        out = np.full(cols.shape[0], np.nan)
        if self.engine is None or self.engine.engine is None or cols.shape[0] == 0:
            return out
        state = self.engine.state(float(np.min(meas.time_s[cols])))
        if state is None:
            return out
        partners = state.partners.get(self.radar_id, {})
        terms = state.terms
        by_radar = {p.radar_id: p for p in self.peers}
        own_spread = np.trace(tracks.P[rows, :2, :2], axis1=1, axis2=2)
        for k, track_id in enumerate(tracks.ids[rows]):
            t = meas.time_s[cols[k]]
            best: tuple[float, BoundedTracker, int, FloatArray, FloatArray] | None = None
            for other, tid in partners.get(str(track_id), ()):
                peer = by_radar.get(other)
                if peer is None:
                    continue
                at = np.flatnonzero(peer._tracks.ids == tid)
                if at.shape[0] == 0:
                    continue
                i = int(at[0])
                ref, ref_cov = np.zeros(3), np.zeros((3, 3))
                if self.bound == "paired-covariance":
                    got = self._reference(peer, i, t, state)
                    if got is None:
                        continue
                    ref, ref_cov = got
                    spread = float(np.trace(ref_cov[:2, :2]))
                else:
                    spread = float(np.trace(peer._tracks.P[i, :2, :2]))
                if spread < own_spread[k] and (best is None or spread < best[0]):
                    best = (spread, peer, i, ref, ref_cov)
            if best is None:
                continue
            _, peer, i, ref, ref_cov = best
            if self.bound == "paired-covariance":
                y = meas.enu_m[cols[k]] - ref
                out[k] = float(y @ np.linalg.solve(meas.covariance[cols[k]] + ref_cov, y))
                continue
            ecef, vel = peer.track_at(i, t)
            if self.bound == "paired-true-biases" and self.truth is not None and peer.truth is not None:
                seen = self.truth.apparent(peer.truth.unbiased(ecef))
            else:
                theirs, own = (terms.get(r, np.zeros(5)) for r in (peer.radar_id, self.radar_id))
                seen = into_view(peer.site, self.site, ecef, vel, theirs, own)
            y = meas.enu_m[cols[k]] - self.site.ecef_to_enu(seen)[0]
            out[k] = float(y @ np.linalg.solve(meas.covariance[cols[k]], y))
        return out

    def _reference(
        self, peer: BoundedTracker, i: int, t: float, state: AidState
    ) -> tuple[FloatArray, FloatArray] | None:
        """``paired-covariance``: ``peer``'s track ``i`` at time ``t`` in this radar's view (ENU)
        by the two radars' pair correlator's own registration, and its covariance: the track's
        and the registration's (its relative covariance through the transform's Jacobian, by
        finite differences); None while the pair is not registered."""
        reg = self._registration(peer.radar_id, state)
        if reg is None:
            return None
        own, theirs, cov = reg
        ecef, vel = peer.track_at(i, t)

        def seen(a: FloatArray, b: FloatArray) -> FloatArray:
            return np.asarray(self.site.ecef_to_enu(into_view(peer.site, self.site, ecef, vel, b, a))[0])

        base = seen(own, theirs)
        steps = np.array([1.0, 1e-6, 1e-6, 1.0, 0.01])
        jac = np.empty((3, 10))
        for j in range(10):
            d = np.zeros(10)
            d[j] = steps[j % 5]
            jac[:, j] = (seen(own + d[:5], theirs + d[5:]) - base) / d[j]
        turn = self.site.rotation.T @ peer.site.rotation
        registration = jac @ cov @ jac.T
        if np.sqrt(max(float(np.trace(registration[:2, :2])), 0.0)) > REGISTRATION_SIGMA_M:
            return None
        return base, turn @ peer._tracks.P[i, :3, :3] @ turn.T + registration

    def _registration(self, other: str, state: AidState) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """The pair correlator of this radar and ``other``: its own registration's terms of this
        radar and of ``other`` and their joint relative covariance (10 x 10); None: not
        registered."""
        got = state.registrations.get(frozenset((self.radar_id, other)))
        if got is None:
            return None
        ids, terms, relative = got
        at = [ids.index(r) for r in (self.radar_id, other)]
        cols = np.concatenate([np.arange(5 * j, 5 * j + 5) for j in at])
        cov = np.array(relative[np.ix_(cols, cols)])
        held = np.flatnonzero(np.concatenate([terms[at[0]], terms[at[1]]]) == 0.0)
        cov[held, :] = 0.0  # (a term held at zero, a range gain the data do not show: no error)
        cov[:, held] = 0.0
        return terms[at[0]], terms[at[1]], cov


def registered_terms(b: dict[str, Any]) -> FloatArray:
    """A ``BiasEstimate``'s five terms in :func:`~service.correlation.registration.remove_bias`'s
    units (m, rad, rad, ppm, s)."""
    return np.array(
        [
            b["range_bias_m"],
            np.radians(b["azimuth_bias_deg"]),
            np.radians(b["elevation_bias_deg"]),
            b.get("range_gain_ppm") or 0.0,
            b.get("time_bias_s") or 0.0,
        ]
    )


class EngineRef:
    """The engine a ``paired`` bound's trackers read (set once the engine is made), and what
    its correlation said (:class:`AidState`) as its outputs grew complete through each data
    time, ``lag_s`` back: the aid a tracker in another process than the correlation could have
    had deterministically, by waiting for the correlation's answers up to ``lag_s`` before its
    batch."""

    def __init__(self, lag_s: float = 0.0) -> None:
        self.engine: Any = None
        self.lag_s = lag_s
        self._states: deque[tuple[float, AidState]] = deque()

    def set(self, engine: Any) -> None:
        self.engine = engine

    def state(self, time_s: float) -> AidState | None:
        """The correlation's pairs and registrations as of data time ``time_s - lag_s`` (the
        newest captured with outputs complete through at most that; None: none yet)."""
        through = self.engine.snapshot().outputs_time_s  # (the correlation's answers so far)
        if through is not None and (not self._states or self._states[-1][0] < through):
            self._states.append((float(through), AidState.of(self.engine)))
        if not self._states:
            return None
        while len(self._states) > 1 and self._states[1][0] <= time_s - self.lag_s:
            self._states.popleft()
        first_s, first = self._states[0]
        return first if first_s <= time_s - self.lag_s else None


@dataclass(frozen=True)
class AidState:
    """What the correlation says at one moment: each radar's confirmed partners (track id ->
    ``(other radar, its track id)``), each radar's five registered terms (``/biases``), and each
    registered pair correlator's own registration (``{radar, other}`` -> radar ids, their
    terms, the relative covariance)."""

    partners: dict[str, dict[str, list[tuple[str, str]]]]
    terms: dict[str, FloatArray]
    registrations: dict[frozenset[str], tuple[tuple[str, ...], FloatArray, FloatArray]]

    @staticmethod
    def of(engine: Any) -> AidState:
        snap = engine.snapshot()
        partners: dict[str, dict[str, list[tuple[str, str]]]] = {}
        for v in snap.pair_views:
            on = np.asarray(v.columns["confirmed"], bool)
            for a, b in zip(v.columns["track_a"][on], v.columns["track_b"][on], strict=True):
                partners.setdefault(v.radar_a, {}).setdefault(str(a), []).append((v.radar_b, str(b)))
                partners.setdefault(v.radar_b, {}).setdefault(str(b), []).append((v.radar_a, str(a)))
        registrations = {}
        for corr in engine.pair_correlators():
            sol = corr.solution
            if corr.site_b is None or sol is None or not corr.registered:
                continue
            if sol.terms is None or sol.relative_covariance is None:
                continue
            key = frozenset((corr.site_a.site_id, corr.site_b.site_id))
            registrations[key] = (
                tuple(sol.radar_ids),
                np.array(sol.terms),
                np.array(sol.relative_covariance),
            )
        return AidState(partners, {b["radar_id"]: registered_terms(b) for b in snap.biases()}, registrations)


def bounded_factory(
    config: EngineConfig,
    bound: str,
    truth_for: Callable[[str, Site], RadarTruth],
    offset_m: float = 0.0,
    seed: int = 0,
    engine: EngineRef | None = None,
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
        inner.engine, inner.radar_id = engine, radar_id
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
    p.add_argument(
        "--bound",
        action="append",
        choices=(*BOUNDS, "aided"),
        help="only these bounds (default every one); aided: the service's own aid (tracking.aid, "
        "on by default; the tracker of every other row is the default with it off)",
    )
    p.add_argument("--offset-m", type=float, default=0.0, help="true-position: each track's reference error")
    p.add_argument("--no-hold", action="store_true", help="the correlation's hold of contested pairs off")
    p.add_argument(
        "--aid-lag-s",
        type=float,
        default=0.0,
        help="paired* and aided: the correlation's answers this far back (s; aided: 0 is its default)",
    )
    p.add_argument("--duration", type=float, help="data seconds per run (default the study's)")
    p.add_argument("--targets", type=int, help="aircraft (default the scenario's 30)")
    p.add_argument("--workers", type=int, help="processes (default up to 2)")
    args = p.parse_args(argv)
    if args.offset_m < 0 or args.aid_lag_s < 0:
        p.error("--offset-m and --aid-lag-s must be >= 0")
    points = [x for x in formation.POINTS if not args.point or x.label in args.point]
    # the tracker alone is the default without the aid; the service's aid is the default
    variants = ("unaided", *("now" if b == "aided" else b for b in args.bound or BOUNDS))
    jobs = [
        replace(j, offset_m=args.offset_m, hold=not args.no_hold, aid_lag_s=args.aid_lag_s)
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
            label = {"unaided": "tracker", "now": "aided"}.get(v, name)
            rows.append((point.label, label, formation.summarize(runs)))
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
