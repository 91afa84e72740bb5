"""The tracking stage: every radar's site and tracker, one update per released batch.

A site message that moves a radar by less than ``move_tolerance_m`` is not a move: the radar
keeps the position it has (so that repeated small "changes" cannot walk it away, nor reset its
pairs), and only its error sigmas and scan period are taken.  A real move replaces the
geometry of new plots and is reported, so the correlation stage re-registers that radar's pairs
(and only those).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from service.geo import Site
from service.tracking.aid import PartnerReferences
from service.tracking.base import PlotColumns, Tracker, TrackTable
from service.wire.models import RadarSite

#: Makes a radar's tracker from its site and id (the engine's builds it from its configuration).
TrackerFactory = Callable[[Site, str], Tracker]


def tracker_for(config: Any, epoch: Callable[[], int] = lambda: 0) -> TrackerFactory:
    """The tracker of each radar: the configured initiator, window and parameters, its track
    ids numbered from the id epoch ``epoch()`` gives when the tracker is made (at the radar's
    first batch; :meth:`Engine.restore_state`)."""
    from service.evaluation.truth import TruthLabelledTracker
    from service.tracking import make_tracker

    make_tracker(Site("check", 0.0, 0.0), config.window_s, config.initiator, "check", config.tracking)

    def factory(site: Site, radar_id: str) -> Tracker:
        # TrackBatch.truth_id (evaluation only) is tallied outside the tracker
        tracker = make_tracker(
            site, config.window_s, config.initiator, radar_id, config.tracking, epoch=epoch()
        )
        return TruthLabelledTracker(tracker)

    return factory


@dataclass(frozen=True)
class SiteParams:
    """How site messages are taken."""

    #: A site whose position differs from the held one by less than this (m, ECEF distance)
    #: is the same site: survey noise or a re-sent message, not a move.  Ten metres is far
    #: below a radar's range error (hundreds of metres) and far above re-rounded coordinates.
    move_tolerance_m: float = 10.0


class SiteChange(Enum):
    SAME = "same"
    NEW = "new"
    UPDATED = "updated"  # sigmas or scan period, same position
    MOVED = "moved"


def to_geometry(site: RadarSite) -> Site:
    return Site(
        site_id=site.radar_id,
        latitude_deg=site.latitude_deg,
        longitude_deg=site.longitude_deg,
        altitude_m=site.altitude_m,
        range_sigma_m=site.range_sigma_m,
        azimuth_sigma_deg=site.azimuth_sigma_deg,
        elevation_sigma_deg=site.elevation_sigma_deg,
        scan_period_s=site.scan_period_s,
    )


@dataclass
class TrackedRadar:
    """One radar: its site, its tracker (made at its first batch) and its latest tracks."""

    site: RadarSite
    geometry: Site
    tracker: Tracker | None = None
    table: TrackTable = field(default_factory=TrackTable.empty)
    time_s: float = 0.0

    @property
    def confirmed(self) -> int:
        return int(np.count_nonzero(self.table.confirmed))


class TrackingStage:
    def __init__(self, tracker_factory: TrackerFactory, params: SiteParams | None = None) -> None:
        self.params = params or SiteParams()
        self.factory = tracker_factory
        self.tracked: dict[str, TrackedRadar] = {}

    def set_site(self, site: RadarSite) -> SiteChange:
        """Take a site message (see module docstring for what counts as a move)."""
        held = self.tracked.get(site.radar_id)
        if held is None:
            self.tracked[site.radar_id] = TrackedRadar(site, to_geometry(site))
            return SiteChange.NEW
        if held.site == site:
            return SiteChange.SAME
        new = to_geometry(site)
        moved = (
            float(np.linalg.norm(new.origin_ecef - held.geometry.origin_ecef)) >= self.params.move_tolerance_m
        )
        if not moved:  # keep the held position, take the rest
            site = site.model_copy(
                update={
                    "latitude_deg": held.site.latitude_deg,
                    "longitude_deg": held.site.longitude_deg,
                    "altitude_m": held.site.altitude_m,
                }
            )
            if site == held.site:
                return SiteChange.SAME
            new = to_geometry(site)
        held.site, held.geometry = site, new
        if held.tracker is not None:  # same tracks, new geometry (and window) for new plots
            held.tracker.follow(new)
        return SiteChange.MOVED if moved else SiteChange.UPDATED

    def update(
        self, radar_id: str, plots: PlotColumns, time_s: float, aid: PartnerReferences | None = None
    ) -> TrackTable:
        """One batch of a radar, applied whole (the tracker's update is all or nothing);
        ``aid``: the references of its tracks' partners (:mod:`~service.tracking.aid`)."""
        radar = self.tracked[radar_id]
        if radar.tracker is None:
            radar.tracker = self.factory(radar.geometry, radar_id)
        radar.tracker.take_aid(aid)
        radar.tracker.update(plots, time_s)
        radar.table = radar.tracker.tracks()
        radar.time_s = time_s
        return radar.table

    def wants_aid(self, radar_id: str, time_s: float) -> bool:
        """Whether the radar's batch at ``time_s`` may ask for the aid of association (its
        tracker's :meth:`~service.tracking.base.Tracker.wants_aid`; none before its first)."""
        tracker = self.tracked[radar_id].tracker
        return tracker is not None and tracker.wants_aid(time_s)

    def expire(self, radar_id: str, time_s: float) -> bool:
        """A silent radar (expired in data time, or on the wall clock while the data clock
        stood still): data time moves on without plots (its window empties by time) and its
        tracks are gone, so no output holds them any longer.

        False if the radar has no tracker (it never reported): nothing to do.
        """
        radar = self.tracked.get(radar_id)
        if radar is None or radar.tracker is None:
            return False
        self.update(radar_id, PlotColumns.empty(), time_s)
        self.clear(radar_id)
        return True

    def clear(self, radar_id: str) -> None:
        """A radar forgotten after a long silence: its tracks and window go; its site and its
        tracker's id numbering stay (its track ids go on where they were when it comes back)."""
        radar = self.tracked.get(radar_id)
        if radar is not None and radar.tracker is not None:
            radar.tracker.drop_tracks()
            radar.table = radar.tracker.tracks()

    def drop(self, radar_id: str) -> None:
        self.tracked.pop(radar_id, None)

    def window_plots(self, radar_id: str) -> int:
        tracker = self.tracked[radar_id].tracker
        return tracker.window_plots if tracker is not None else 0

    def window_evicted(self, radar_id: str) -> int:
        tracker = self.tracked[radar_id].tracker
        return int(getattr(tracker, "window_evicted", 0)) if tracker is not None else 0

    def plots_coincident(self, radar_id: str) -> int:
        tracker = self.tracked[radar_id].tracker
        return int(getattr(tracker, "plots_coincident", 0)) if tracker is not None else 0

    def scan_period_observed(self, radar_id: str) -> float | None:
        tracker = self.tracked[radar_id].tracker
        return tracker.scan_period_observed_s if tracker is not None else None

    def aided_associations(self, radar_id: str) -> int:
        tracker = self.tracked[radar_id].tracker
        return tracker.aided_associations if tracker is not None else 0

    def sigma_scale(self, radar_id: str) -> float:
        tracker = self.tracked[radar_id].tracker
        return tracker.measurement_sigma_scale if tracker is not None else 1.0

    def detection(self, radar_id: str) -> tuple[float | None, int | None]:
        """The radar's measured Pd and the misses that delete an established track."""
        tracker = self.tracked[radar_id].tracker
        return (tracker.pd_measured, tracker.misses_to_delete) if tracker is not None else (None, None)
