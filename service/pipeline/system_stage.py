"""When the system tracks are rebuilt, and from which links: one worker, or N partitioned ones.

One worker rebuilds the system tracks (:mod:`service.fusion`) once per ``system_interval_s``
of data time, at the release whose clock crosses a multiple of it: every radar's latest table,
the references, the joint bias estimate and every pair book's confirmed pairs (the *links*) as
they are after that release's pair updates.

Partitioned (``--partition K/N``), worker 1 builds the one picture of the whole network, the
one a single worker would build, from the same inputs at the same releases:

* its merge releases every radar's tables in one worker's order (:mod:`.merger`), so at the
  release that crosses a multiple it holds the same tables, references and joint estimate; it
  takes them then (a :class:`Picture`), with the links of the pairs it correlates;
* every other worker sends, at the release that crosses a multiple (it merges the same
  releases in the same order), the links of each pair it updated since the previous one, as
  they were after the pair's latest update and tagged with that update's release
  (``{prefix}/links/{a}/{b}``, ``PairLinks``: :meth:`SystemStage.take_links`): a picture reads
  only a pair's latest links at or before its release, so the links of an update that another
  update of the pair follows before the next picture are never sent (a pair updates about once
  a scan, a picture is taken every ``system_interval_s``);
* once every other live worker says it has correlated past the picture's data time
  (``correlated_s`` of ``{prefix}/workers/{k}/progress``, sent after the links it covers),
  worker 1 holds every pair's links up to that release and draws the picture: for each other
  worker's pair, its latest links at or before the release (:meth:`SystemStage.through`).

The picture is then late by how far the slowest other worker is behind worker 1 (in a
replay at full speed a few scans of data time, live a few network round trips); at most
:data:`MAX_PENDING_PICTURES` wait, beyond which the oldest is drawn with the links known
(counted in ``forced``).  Worker 1 puts the picture on ``{prefix}/system/tracks`` and answers
its queryable; the other workers' ``GET /system-tracks`` ask it (contract §6).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.correlation.cycles import CycleParams, Implied
from service.correlation.prediction import PredictionParams
from service.correlation.registration import BiasSolution
from service.fusion.members import Links, members_and_links
from service.fusion.system_tracks import SystemTracker, SystemTrackParams
from service.geo import Site
from service.pipeline.cycle_links import CycleLinks
from service.pipeline.partition import Partition
from service.pipeline.read_model import SystemTrackView
from service.pipeline.shared_links import Crossing, Key, LinksHistory, PairRegistration, SharedLinks
from service.tracking.base import TrackTable

Registration = PairRegistration | None
#: A release after every radar's at its data time (the end of the input).
LAST = "\U0010ffff"
#: Pictures taken and waiting for the other workers' links; beyond, the oldest is drawn with
#: the links known (at one picture per ``system_interval_s`` of 2 s: a minute of data time).
MAX_PENDING_PICTURES = 30
#: The links' grid when no system tracks are drawn (``system_interval_s`` 0) and the cycle step
#: needs one (data s).
LINKS_GRID_S = 2.0


def links_grid_s(interval_s: float) -> float:
    """The links' grid (data s): the picture's ``system_interval_s``, or :data:`LINKS_GRID_S`."""
    return interval_s if interval_s > 0 else LINKS_GRID_S


log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Picture:
    """The inputs of one rebuild, taken at the release that crossed its time."""

    time_s: float
    release: str
    radars: dict[str, tuple[Site, TrackTable]]
    references: dict[str, TrackTable]
    joint: BiasSolution | None
    own: dict[Key, Links]  # the links of the pairs this worker correlates


class SystemStage:
    """The system tracks' schedule and inputs, and the links' grid (see module docstring)."""

    def __init__(
        self,
        interval_s: float,
        partition: Partition,
        cycles: CycleParams | None = None,
        aid: bool = False,
    ) -> None:
        self.interval_s = interval_s
        self.partition = partition
        #: The cycle step's chains on the links' grid (None: the step is off).
        self.cycles = CycleLinks(cycles) if cycles is not None and cycles.enabled else None
        #: The aid of association reads every pair's links and registration at the crossings
        #: (:meth:`take_crossings`: the tracking stage's, :mod:`.partner_aid`).
        self.aid = aid
        self.grid_s = links_grid_s(interval_s)
        #: This worker draws the picture: the only worker, or worker 1 of N.
        self.draws = interval_s > 0 and (partition.whole or partition.solves_biases)
        #: This worker sends its pairs' links: to worker 1, and to every worker for the cycles
        #: and the aid.
        self.shares = not partition.whole and (
            (interval_s > 0 and not self.draws) or self.cycles is not None or aid
        )
        self._crossings_out: list[Crossing] = []
        self.forced = 0
        self._next_s = -np.inf
        self._out: list[Drawing] = []
        self._links_out: list[SharedLinks] = []
        #: Owned pairs updated since the last crossing: their latest update's release, and its
        #: links and registration as they are (read at the crossing).
        self._updated: dict[Key, tuple[float, str, Callable[[], Links], Callable[[], Registration]]] = {}
        self._pending: deque[Picture] = deque()
        #: The picture taken by the current :meth:`due` (drawn at once unless it must wait).
        self._taking: Picture | None = None
        #: Every other worker's pairs: their links, oldest first (a base and what came after).
        self._mirrored = LinksHistory()
        #: Data time every other live worker has correlated through (alone: no one to wait for).
        self._others_s = np.inf if partition.whole else -np.inf

    # -- every worker ------------------------------------------------------------------------
    def updated(
        self,
        key: Key,
        links: Callable[[], Links],
        time_s: float,
        release: str,
        registration: Callable[[], Registration] = lambda: None,
    ) -> None:
        """An owned pair's book changed at the release ``(time_s, release)``: its links as they
        are at the next crossing (:meth:`due`; the book changes only by its updates) go out
        then and feed the cycle step, and the aid with its ``registration`` then."""
        if self.shares or self.cycles is not None or self.aid:
            self._updated[key] = (time_s, release, links, registration)

    def take_links(self) -> list[SharedLinks]:
        out, self._links_out = self._links_out, []
        return out

    def take_crossings(self) -> list[Crossing]:
        """The crossings since the last call, oldest first, with the owned pairs' links and
        registrations (the aid on; none otherwise)."""
        out, self._crossings_out = self._crossings_out, []
        return out

    def take_drawings(self) -> list[Drawing]:
        """The pictures ready to draw since the last call, oldest first (:class:`SystemDrawer`)."""
        out, self._out = self._out, []
        return out

    def implied(self, key: Key, time_s: float) -> Implied | None:
        """The pairs the cycle step's chains imply for radar pair ``key``'s update at
        ``time_s`` (None: the step is off)."""
        return None if self.cycles is None else self.cycles.implied(key, time_s)

    # -- the worker that draws -------------------------------------------------------------------
    def mirror(self, shared: SharedLinks) -> None:
        """Another worker's pair's links (in the order its owner updated it)."""
        if self.draws:
            self._mirrored.record(shared)
        if self.cycles is not None:
            self.cycles.mirror(shared)

    def forget(self, source_id: str) -> None:
        self._mirrored.forget(source_id)
        if self.cycles is not None:
            self.cycles.forget(source_id)
        for key in [k for k in self._updated if source_id in k]:
            del self._updated[key]

    def due(
        self, clock_s: float, release: str, take: Callable[[float, str], Picture], radars: Collection[str]
    ) -> None:
        """A release at ``clock_s`` of radar ``release``, after its pair updates: if it crosses a
        multiple of the grid, the links of the owned pairs updated since the previous crossing
        go out (sharing) and to the cycle step (with ``radars``, whose tables the stage holds),
        and the worker that draws takes the picture's inputs (``take``) and draws what may be
        drawn."""
        if not (self.draws or self.shares or self.cycles is not None or self.aid):
            return
        grid = float(np.floor(clock_s / self.grid_s) * self.grid_s)
        if grid < self._next_s:
            return
        self._next_s = grid + self.grid_s
        own = self._own()
        if self.aid:
            self._crossings_out.append(Crossing((clock_s, release), tuple(own)))
        if self.cycles is not None:
            self.cycles.crossed((clock_s, release), own, radars)
        if self.draws:
            self._taking = take(clock_s, release)
            self._pending.append(self._taking)
            self._draw()
            self._taking = None

    def _own(self) -> list[SharedLinks]:
        """The owned pairs updated since the previous crossing, with their links now (sent
        when sharing)."""
        own = [
            SharedLinks(k, t, r, links(), registration() if self.aid else None)
            for k, (t, r, links, registration) in sorted(self._updated.items())
        ]
        self._updated = {}
        if self.shares:
            self._links_out.extend(own)
        return own

    def through(self, others_s: float) -> None:
        """Every other live worker has correlated (and sent its links) through ``others_s``."""
        self._others_s = others_s
        self._draw()

    def finish(self, picture: Picture | None) -> None:
        """End of the input: every picture waiting, then one of now (``picture``); a sharing
        worker sends the links of the pairs updated since the last picture."""
        self._own()
        self._others_s = np.inf
        self._draw()
        if picture is not None and self.draws:
            self._taking = picture
            self._build(picture)
            self._taking = None

    def _draw(self) -> None:
        while self._pending and (
            self._pending[0].time_s <= self._others_s or len(self._pending) > MAX_PENDING_PICTURES
        ):
            picture = self._pending.popleft()
            if picture.time_s > self._others_s:
                self.forced += 1
            self._build(picture)

    def _links_at(self, picture: Picture) -> dict[Key, Links]:
        """Every pair's links as they were after the picture's release."""
        return {**picture.own, **self._mirrored.at((picture.time_s, picture.release))}

    def _build(self, picture: Picture) -> None:
        """Hand out the picture's :class:`Drawing` (:meth:`take_drawings`): its links now."""
        links = self._links_at(picture)
        self._out.append(
            Drawing(
                picture.time_s,
                picture.radars,
                picture.references,
                picture.joint,
                [links[k] for k in sorted(links)],  # one worker's order: by pair
                picture is self._taking,
            )
        )


@dataclass(frozen=True)
class Drawing:
    """Everything one rebuild of the system tracks reads: a :class:`Picture`'s tables and joint
    estimate with every pair's links as they were after its release, in one worker's order."""

    time_s: float
    #: Every radar's site and table (None only between the two processes of
    #: :mod:`.correlation_process`, when ``taken_now``: the engine's own copy fills it in).
    radars: dict[str, tuple[Site, TrackTable]] | None
    references: dict[str, TrackTable]
    joint: BiasSolution | None
    links: list[Links]
    #: The picture was taken by the same call that hands it out (not one that waited for the
    #: other workers' links): its radars' tables are those the stage's inputs so far left.
    taken_now: bool = False


class SystemDrawer:
    """Draws the system tracks (:mod:`service.fusion`) of each :class:`Drawing`, in order.

    It runs where the engine takes the correlation's answers, not in the correlation stage:
    with the stage in a child process (:mod:`.correlation_process`) the rebuilds, a tenth of
    the stage's work on the national network, run on the engine's core beside the next pair
    updates instead of after them, and the system tracks' numbers outlive a child started
    afresh.  The drawings come in the order the stage made them, so the tracks are the same
    wherever the stage runs."""

    def __init__(self, prediction: PredictionParams, params: SystemTrackParams | None = None) -> None:
        self.prediction = prediction
        self.tracker = SystemTracker(params)
        #: CPU seconds the rebuilds took (this thread's).
        self.cpu_s = 0.0

    def draw(self, drawing: Drawing) -> SystemTrackView | None:
        """The system tracks of ``drawing`` (None: the rebuild failed, the old view stays)."""
        started = time.thread_time()
        try:
            assert drawing.radars is not None
            members, la, lb, score = members_and_links(
                drawing.time_s,
                drawing.radars,
                drawing.references,
                drawing.links,
                drawing.joint,
                self.prediction,
            )
            tracks = self.tracker.update(members, la, lb, score, drawing.time_s)
            return SystemTrackView.of(drawing.time_s, tracks, members)
        except Exception:  # a bug here must not cost the pair updates
            log.exception("system tracks: rebuild at %.3f failed", drawing.time_s)
            return None
        finally:
            self.cpu_s += time.thread_time() - started

    def restart(self, epoch: int) -> None:
        """Number new system tracks from ``epoch``'s first number (a start with state)."""
        self.tracker = SystemTracker(self.tracker.params, epoch)


def take_picture(
    time_s: float,
    release: str,
    radars: Mapping[str, tuple[Site, TrackTable]],
    references: Mapping[str, Any],
    silent: set[str],
    joint: BiasSolution | None,
    own: Mapping[Key, Links],
) -> Picture:
    """A :class:`Picture` of the stage's state now (``references``: each source's
    :class:`~service.reference.ReferenceTracks`; the silent ones are left out)."""
    refs = {sid: ref.table(time_s) for sid, ref in references.items() if sid not in silent}
    return Picture(time_s, release, dict(radars), refs, joint, dict(own))
