"""Per-radar tracking (pure numpy/scipy): measurement model, CV Kalman filter, M-of-N track
manager, and the initiators of the Hough paper (see ``docs/references.md`` §2).

Public API used by the engine::

    tracker = make_tracker(site, window_s=None, initiator="logic", id_prefix="A")
    tracker.update(plots, time_s)      # one accepted batch
    tracker.tracks()                   # TrackTable of all live tracks (ECEF)
    tracker.window_plots               # plots held in the sliding window
    tracker.window_evicted             # plots evicted because the window was full

Memory and work per update are bounded whatever a batch holds (``TrackerParams.bounds``).
"""

from __future__ import annotations

from service.geo import Site
from service.tracking.base import PlotColumns, Tracker, TrackTable, first_number
from service.tracking.initiators import INITIATORS, get_initiator
from service.tracking.manager import TrackManager
from service.tracking.params import TrackerParams
from service.tracking.window import DEFAULT_WINDOW_S, window_for

__all__ = [
    "DEFAULT_WINDOW_S",
    "INITIATORS",
    "PlotColumns",
    "TrackManager",
    "TrackTable",
    "Tracker",
    "TrackerParams",
    "make_tracker",
]


def make_tracker(
    site: Site,
    window_s: float | None = None,
    initiator: str = "logic",
    id_prefix: str = "T",
    params: TrackerParams | None = None,
    epoch: int = 0,
    kind: type[TrackManager] = TrackManager,
) -> TrackManager:
    """A tracker for one radar.

    ``window_s`` None: ``max(DEFAULT_WINDOW_S, 3 * site.scan_period_s)`` so that the window
    always spans three looks, of the site's scan period as it is updated (``Tracker.follow``).
    ``initiator`` is one of :data:`INITIATORS` (``ValueError`` naming them otherwise).  Track
    ids are ``f"{id_prefix}-{n}"``, ``n`` from ``first_number(epoch)`` (1 in epoch 0), never
    reused: ``epoch`` counts the service's starts with one state directory
    (``service.state``), so ids are not reused across restarts either.  ``kind``: the class
    made (a subclass of :class:`TrackManager`; the lab's bounds on association).
    """
    get_initiator(initiator)  # fail early with the list of names
    return kind(
        site,
        window_for(site, window_s),
        initiator=initiator,
        id_prefix=id_prefix,
        params=params,
        first_number=first_number(epoch),
        window_follows_site=window_s is None,
    )
