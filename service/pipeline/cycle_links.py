"""The cycle step's chains (:mod:`service.correlation.cycles`) on a data-time grid, the same
for one worker and for N partitioned ones.

An update of radar pair X-Y at data time ``t`` joins the other pairs' books as they were at the
latest release that crossed a multiple of the links' grid (:mod:`.system_stage`) at or before
``t - lag_s`` (``CycleParams.lag_s``), not as they are now.  Every worker releases the same
tables in the same order (:mod:`.merger`), so that release is the same everywhere; the books
of the pairs a worker does not own come from their owners' links, which each owner sends at
every crossing (``{prefix}/links/{a}/{b}``).  A partitioned worker's merge releases a table of
time ``t`` only once every other live worker has correlated through ``t - lag_s``
(:meth:`.peers.Peers.cap`), so it then holds those links: the chains, and so every pair
update, are one worker's, whichever worker owns which pair of a triangle.

Cost: at each crossing the strong subset of the links of each pair updated since the one
before (a few small numpy calls a pair); each update then joins the two books of each third
radar.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Collection, Iterable

from service.correlation.cycles import CycleParams, Implied, implied_from
from service.correlation.pairs import StrongPairs
from service.fusion.members import Links
from service.pipeline.shared_links import Key, LinksHistory, Position, SharedLinks


class CycleLinks:
    """Every radar pair's links at the grid's crossings, and the chains they give."""

    def __init__(self, params: CycleParams) -> None:
        self.params = params
        self.history = LinksHistory()
        #: Crossings not taken yet, each with the radars whose tables the stage held then.
        self._crossings: deque[tuple[Position, frozenset[str]]] = deque()
        #: The strong confirmed pairs of every radar pair at the crossing taken last.
        self._books: dict[Key, tuple[str, StrongPairs]] = {}
        #: Each pair's latest links and their strong pairs: a pair updates about once a scan,
        #: less often than the grid's crossings, and keeps them until it does.
        self._strong: dict[Key, tuple[Links, tuple[str, StrongPairs]]] = {}

    def crossed(self, position: Position, own: Iterable[SharedLinks], radars: Collection[str]) -> None:
        """A release crossed a multiple of the grid at ``position``: the links of the owned
        pairs updated since the previous crossing (``own``, as they are now) are recorded."""
        for shared in own:
            self.history.record(shared)
        self._crossings.append((position, frozenset(radars)))
        self._take(position[0])

    def mirror(self, shared: SharedLinks) -> None:
        """Another worker's pair's links (in the order its owner updated it)."""
        self.history.record(shared)

    def forget(self, source_id: str) -> None:
        self.history.forget(source_id)
        for held in (self._books, self._strong):
            for key in [k for k in held if source_id in k]:
                del held[key]

    def implied(self, key: Key, time_s: float) -> Implied:
        """The pairs of radar pair ``key`` (``key[0]``'s tracks first) the chains imply for an
        update at ``time_s``."""
        self._take(time_s)
        return implied_from(key, self._books)

    def _take(self, time_s: float) -> None:
        """Move to the latest crossing at or before ``time_s - lag_s`` (never back)."""
        taken = None
        while self._crossings and self._crossings[0][0][0] + self.params.lag_s <= time_s:
            taken = self._crossings.popleft()
        if taken is None:
            return
        position, radars = taken
        self._books = {
            key: self._strong_of(key, links)
            for key, links in self.history.at(position).items()
            if key[0] in radars and key[1] in radars
        }

    def _strong_of(self, key: Key, links: Links) -> tuple[str, StrongPairs]:
        """A pair's A side and its strong confirmed pairs in ``links``."""
        held = self._strong.get(key)
        if held is None or held[0] is not links:
            keep = links.score >= self.params.min_strength
            strong = StrongPairs.of(links.track_a[keep], links.track_b[keep], links.score[keep])
            held = self._strong[key] = (links, (links.source_a, strong))
        return held[1]
