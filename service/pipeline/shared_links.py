"""Pair books' links (their confirmed pairs) as they were after an update, read back at a
release's place in one worker's order.

A correlating worker keeps the links of its own pairs and those other workers send it
(``{prefix}/links/{a}/{b}``) at the releases that cross a multiple of the links' grid
(:mod:`.system_stage`); worker 1 draws the system tracks from them and every worker takes the
cycle step's chains from them (:mod:`.cycle_links`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import orjson

from service.fusion.members import Links
from service.pipeline.decode import list_of
from service.pipeline.errors import RejectionError
from service.wire.models import MAX_TIME_S, MAX_TRACKS
from service.wire.vocabulary import is_source_id

Key = tuple[str, str]
#: A release's place in one worker's order: its data time, then the radar released.
Position = tuple[float, str]


@dataclass(frozen=True)
class SharedLinks:
    """A pair's links after one of its updates (``PairLinks`` on the wire)."""

    key: Key
    time_s: float  # the data time of the release the update followed ...
    release: str  # ... and the radar released
    links: Links

    @property
    def position(self) -> Position:
        return (self.time_s, self.release)


class LinksHistory:
    """Each pair's links after its updates, oldest first (a pair's owner sends them in the
    order it updated it), read at positions that only move on."""

    def __init__(self) -> None:
        self._queues: dict[Key, deque[SharedLinks]] = {}

    def record(self, shared: SharedLinks) -> None:
        self._queues.setdefault(shared.key, deque()).append(shared)

    def at(self, position: Position) -> dict[Key, Links]:
        """Every pair's latest links at or before ``position`` (none yet: left out); the older
        ones are dropped, as no later read needs them."""
        out = {}
        for key, queue in self._queues.items():
            latest = None
            while queue and queue[0].position <= position:
                latest = queue.popleft()
            if latest is not None:
                queue.appendleft(latest)  # the base of the reads to come
                out[key] = latest.links
        return out

    def forget(self, source_id: str) -> None:
        for key in [k for k in self._queues if source_id in k]:
            del self._queues[key]


def links_body(shared: SharedLinks) -> dict[str, Any]:
    """The ``PairLinks`` payload of a pair's links."""
    links = shared.links
    return {
        "source_a": links.source_a,
        "source_b": links.source_b,
        "time_s": shared.time_s,
        "release": shared.release,
        "track_a": links.track_a.tolist(),
        "track_b": links.track_b.tolist(),
        "score": links.score.tolist(),
    }


def decode_links(payload: bytes, key: Key) -> SharedLinks:
    """Parse and check a ``PairLinks`` of the pair ``key`` (its key's two sources) with the
    rules of its model (:class:`service.wire.models.PairLinks`): every worker takes every other
    worker's links, a dozen a data second on a national network, and the model's validation of
    each id and score costs three times this.  ``tests/test_partition.py`` holds the two to the
    same verdicts."""
    source_id = key[0]

    def fail(reason: str, detail: str) -> RejectionError:
        return RejectionError(reason, f"links: {detail}", source_id)  # type: ignore[arg-type]

    try:
        body = orjson.loads(payload)
    except orjson.JSONDecodeError as exc:
        raise fail("malformed_json", str(exc)) from None
    if not isinstance(body, dict):
        raise fail("schema", "not an object")
    fields: list[Any] = [body.get(n) for n in ("source_a", "source_b", "release", "time_s")]
    a, b, release, time_s = fields
    if not all(isinstance(x, str) and is_source_id(x) for x in (a, b, release)):
        raise fail("schema", "source_a, source_b and release must be source ids")
    if type(time_s) not in (int, float):
        raise fail("schema", "time_s must be a number")
    if not 0 <= time_s <= MAX_TIME_S:  # (orjson reads no NaN or infinity)
        raise fail("out_of_range", "time_s")
    columns: list[Any] = [body.get(n) for n in ("track_a", "track_b", "score")]
    track_a, track_b, score = columns
    for name, ids in (("track_a", track_a), ("track_b", track_b)):
        if not list_of(ids, str) or len(ids) > MAX_TRACKS:
            raise fail("schema", f"{name} must be a list of track ids")
    # (numbers; the model's lax floats take true and false as 1 and 0 too)
    if not list_of(score, int, float, bool):
        raise fail("schema", "score must be a list of numbers")
    if not len(track_a) == len(track_b) == len(score):
        raise fail("schema", "track_a, track_b and score differ in length")
    scores = np.asarray(score, dtype=float)
    if np.any(scores < 0.0) or np.any(scores > 1.0):
        raise fail("out_of_range", "score must be in [0, 1]")
    if sorted((a, b)) != sorted(key):
        raise fail("schema", f"sources {a}, {b} != key {key}")
    links = Links(a, b, np.asarray(track_a, dtype=str), np.asarray(track_b, dtype=str), scores)
    return SharedLinks(key, float(time_s), release, links)
