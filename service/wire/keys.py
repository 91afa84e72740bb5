"""Zenoh key expressions of the contract (docs/contract.md §1): built and parsed in one place.

One grammar serves the service (which inputs it takes), the recorder and the replay (what a
recorded key is): :func:`classify_key` names the kind of any concrete key under a prefix.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

from pydantic import BaseModel

from service.wire.models import (
    AdsbBatch,
    AisBatch,
    BiasSet,
    PairLinks,
    PairSet,
    PlotBatch,
    RadarPerformance,
    RadarSite,
    RegistrationRows,
    Rejection,
    Status,
    SystemTrackBatch,
    TrackBatch,
    TrackStates,
    WorkerClock,
)
from service.wire.vocabulary import ID_REGEX

KeyKind = Literal[
    "site",
    "plots",
    "ais",
    "adsb",
    "tracks",
    "pairs",
    "system_tracks",
    "errors",
    "status",
    "track_states",
    "registration",
    "links",
    "biases",
    "worker_status",
    "worker_clock",
    "worker_progress",
    "performance",
    "other",
]

#: Kinds the service consumes: replay republishes only these unless told to include all keys.
INPUT_KINDS: frozenset[KeyKind] = frozenset({"site", "plots", "ais", "adsb"})
#: Input kinds of bias-free reference sources (their reports are reference tracks).
REFERENCE_KINDS: frozenset[KeyKind] = frozenset({"ais", "adsb"})

#: Kinds partitioned workers publish for each other (and take from each other).
PEER_KINDS: frozenset[KeyKind] = frozenset(
    {"track_states", "registration", "links", "biases", "worker_status", "worker_clock", "worker_progress"}
)
#: Peer kinds a worker takes ahead of its inputs (node.py): they only move the correlation on.
#: A worker's radar clocks (``worker_clock``) stay in arrival order with the inputs: taken
#: early, they would make this worker's own radars look behind the network.
PRIORITY_KINDS: frozenset[KeyKind] = frozenset(
    {"track_states", "registration", "links", "biases", "worker_progress"}
)

#: Payload model per key kind (contract §1 table).
MODEL_BY_KIND: dict[KeyKind, type[BaseModel]] = {
    "site": RadarSite,
    "plots": PlotBatch,
    "ais": AisBatch,
    "adsb": AdsbBatch,
    "tracks": TrackBatch,
    "pairs": PairSet,
    "system_tracks": SystemTrackBatch,
    "errors": Rejection,
    "status": Status,
    "track_states": TrackStates,
    "registration": RegistrationRows,
    "links": PairLinks,
    "biases": BiasSet,
    "worker_status": Status,
    "worker_clock": WorkerClock,
    "worker_progress": WorkerClock,
    "performance": RadarPerformance,
}

#: Each kind's key after ``{prefix}/``, its ids captured.
_SHAPES: tuple[tuple[KeyKind, str], ...] = (
    ("site", rf"radar/({ID_REGEX})/site"),
    ("plots", rf"radar/({ID_REGEX})/plots"),
    ("tracks", rf"radar/({ID_REGEX})/tracks"),
    ("performance", rf"radar/({ID_REGEX})/performance"),
    ("ais", rf"ais/({ID_REGEX})/reports"),
    ("adsb", rf"adsb/({ID_REGEX})/reports"),
    ("pairs", rf"pairs/({ID_REGEX})/({ID_REGEX})"),
    ("system_tracks", r"system/tracks"),
    ("errors", r"errors"),
    ("status", r"status"),
    ("track_states", rf"radar/({ID_REGEX})/track-states"),
    ("registration", rf"registration/({ID_REGEX})/({ID_REGEX})"),
    ("links", rf"links/({ID_REGEX})/({ID_REGEX})"),
    ("biases", r"biases"),
    ("worker_status", r"workers/([0-9]{1,6})/status"),
    ("worker_clock", r"workers/([0-9]{1,6})/clock"),
    ("worker_progress", r"workers/([0-9]{1,6})/progress"),
)


@lru_cache(maxsize=64)
def _patterns(prefix: str) -> tuple[tuple[KeyKind, re.Pattern[str]], ...]:
    head = re.escape(prefix.strip("/"))
    return tuple((kind, re.compile(rf"^{head}/{shape}$")) for kind, shape in _SHAPES)


def parse_key(key: str, prefix: str) -> tuple[KeyKind, tuple[str, ...]]:
    """The contract kind of a concrete key under ``prefix`` and its ids; ``("other", ())``."""
    for kind, pattern in _patterns(prefix):
        m = pattern.match(key)
        if m:
            return kind, m.groups()
    return "other", ()


def classify_key(key: str, prefix: str) -> KeyKind:
    """The contract kind of a concrete key under ``prefix``, ``"other"`` when it has none."""
    return parse_key(key, prefix)[0]


@dataclass(frozen=True)
class Keys:
    """The keys of one prefix."""

    prefix: str = "fusion"

    def site(self, radar_id: str) -> str:
        return f"{self.prefix}/radar/{radar_id}/site"

    def plots(self, radar_id: str) -> str:
        return f"{self.prefix}/radar/{radar_id}/plots"

    def ais(self, source_id: str) -> str:
        return f"{self.prefix}/ais/{source_id}/reports"

    def adsb(self, source_id: str) -> str:
        return f"{self.prefix}/adsb/{source_id}/reports"

    def tracks(self, radar_id: str) -> str:
        return f"{self.prefix}/radar/{radar_id}/tracks"

    def pairs(self, radar_a: str, radar_b: str) -> str:
        return f"{self.prefix}/pairs/{radar_a}/{radar_b}"

    def track_states(self, radar_id: str) -> str:
        return f"{self.prefix}/radar/{radar_id}/track-states"

    def registration(self, source_a: str, source_b: str) -> str:
        """Rows of the pair ``source_a``, ``source_b`` (in string order in the key)."""
        a, b = sorted((source_a, source_b))
        return f"{self.prefix}/registration/{a}/{b}"

    def links(self, source_a: str, source_b: str) -> str:
        """Links of the pair ``source_a``, ``source_b`` (in string order in the key)."""
        a, b = sorted((source_a, source_b))
        return f"{self.prefix}/links/{a}/{b}"

    def worker(self, index: int) -> str:
        """A partitioned worker's liveliness token."""
        return f"{self.prefix}/workers/{index}"

    def worker_status(self, index: int) -> str:
        return f"{self.prefix}/workers/{index}/status"

    def worker_clock(self, index: int) -> str:
        return f"{self.prefix}/workers/{index}/clock"

    def worker_progress(self, index: int) -> str:
        return f"{self.prefix}/workers/{index}/progress"

    def input(self, kind: str, source_id: str) -> str:
        """The input key of ``kind`` (``site``, ``plots``, ``ais`` or ``adsb``) for a source."""
        return {"site": self.site, "plots": self.plots, "ais": self.ais, "adsb": self.adsb}[kind](source_id)

    @property
    def errors(self) -> str:
        return f"{self.prefix}/errors"

    @property
    def status(self) -> str:
        return f"{self.prefix}/status"

    @property
    def system_tracks(self) -> str:
        return f"{self.prefix}/system/tracks"

    @property
    def pairs_all(self) -> str:
        return f"{self.prefix}/pairs/**"

    def performance(self, radar_id: str) -> str:
        """A radar's ``RadarPerformance`` (contract §5.3; queryable only)."""
        return f"{self.prefix}/radar/{radar_id}/performance"

    @property
    def performance_all(self) -> str:
        """Every radar's performance key: what the queryable is declared on."""
        return f"{self.prefix}/radar/*/performance"

    @property
    def biases(self) -> str:
        return f"{self.prefix}/biases"

    @property
    def workers(self) -> str:
        """Every worker's liveliness token."""
        return f"{self.prefix}/workers/*"

    @property
    def worker_statuses(self) -> str:
        return f"{self.prefix}/workers/*/status"

    @property
    def registration_inputs(self) -> str:
        """Every pair's registration rows (the bias worker alone takes them)."""
        return f"{self.prefix}/registration/*/*"

    @property
    def peer_inputs(self) -> tuple[str, ...]:
        """What partitioned workers' engines take from each other (in arrival order with the
        inputs; the workers' statuses are the transport's own)."""
        return (
            f"{self.prefix}/radar/*/track-states",
            self.registration_inputs,
            f"{self.prefix}/links/*/*",
            self.biases,
            f"{self.prefix}/workers/*/clock",
            f"{self.prefix}/workers/*/progress",
        )

    @property
    def ais_inputs(self) -> str:
        return f"{self.prefix}/ais/*/reports"

    @property
    def adsb_inputs(self) -> str:
        return f"{self.prefix}/adsb/*/reports"

    def classify(self, key: str) -> tuple[str, str] | None:
        """``("site"|"plots"|"ais"|"adsb", id)`` for an input key of this prefix, else ``None``."""
        kind, ids = parse_key(key, self.prefix)
        return (kind, ids[0]) if kind in INPUT_KINDS else None

    def classify_peer(self, key: str) -> tuple[KeyKind, tuple[str, ...]] | None:
        """The kind and ids of a key partitioned workers exchange, else ``None``."""
        kind, ids = parse_key(key, self.prefix)
        return (kind, ids) if kind in PEER_KINDS else None
