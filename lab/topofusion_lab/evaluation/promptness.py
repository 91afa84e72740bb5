"""Promptness and consistency of the published outputs, as a subscriber sees them.

:class:`OutputMonitor` takes the service's outputs in the order they were published (each
``TrackBatch``, ``PairSet`` and ``SystemTrackBatch`` with its key, as a client on Zenoh hears
them, or as :meth:`service.engine.Engine.ingest` returns them) and measures two things a user
checks from outside:

* **Time to pair** (data time, in scans of the slower radar of the pair).  For each aircraft
  held by confirmed tracks on two radars that the service correlates: from the later of the
  two radars' first confirmed ``TrackBatch`` holding it to the first ``PairSet`` that holds a
  confirmed pair of two of its tracks.  An aircraft common to two radars for at least
  ``settle_scans`` scans and still unpaired at the end is *never paired*.
* **Dangling references.**  After every single output, every confirmed or tentative pair of
  the latest ``PairSet`` of each radar pair, and every member of the latest system tracks,
  must name a track that the latest ``TrackBatch`` of its radar holds.  Each output that
  leaves such a reference counts, with the number of references it leaves.

Which aircraft a track follows is the simulator's ``truth_id`` on the ``TrackBatch``:
evaluation only, no algorithm reads it.  Pair keys of reference sources (AIS, ADS-B) are
left out: they have no ``TrackBatch``.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.engine import Engine


@dataclass
class Dangling:
    """Outputs that left a reference to a track the latest tables do not hold."""

    outputs: int = 0  # outputs after which at least one reference dangled
    references: int = 0  # the dangling references, summed over those outputs
    worst: int = 0  # most at once
    examples: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class PromptnessReport:
    """What :meth:`OutputMonitor.report` measured."""

    #: Time to pair of every paired common aircraft (scans of the slower radar of its pair).
    scans: np.ndarray
    #: Common aircraft (radar pair, aircraft) that were never paired (common for at least
    #: ``settle_scans`` scans before the end).
    never_paired: int
    #: Common aircraft counted (paired or not, common for at least ``settle_scans`` scans).
    common: int
    #: At the end: common aircraft with a right confirmed pair, among those held by both radars.
    paired_at_end: int
    common_at_end: int
    #: At the end: confirmed pairs of two tracks of different aircraft, and all confirmed pairs.
    false_at_end: int
    confirmed_at_end: int
    dangling: Dangling
    outputs: int
    #: Of each time in ``scans``: whether the aircraft became common within ``start_s`` of the
    #: first confirmed track of the run (a service's start: every aircraft new at once, no
    #: radar pair registered yet), to tell the start from the steady state.
    at_start: np.ndarray
    start_s: float

    @property
    def median(self) -> float:
        return float(np.median(self.scans)) if self.scans.size else float("nan")

    @property
    def p95(self) -> float:
        return float(np.percentile(self.scans, 95)) if self.scans.size else float("nan")

    def split(self) -> str:
        """The time to pair of the aircraft common from the start and of those common later."""
        parts = []
        for name, sel in (
            (f"common within {self.start_s:.0f} s of the first track", self.at_start),
            ("common later", ~self.at_start),
        ):
            x = self.scans[sel]
            if x.size:
                parts.append(
                    f"{name}: {x.size}, median {np.median(x):.2f}, p95 {np.percentile(x, 95):.2f}, "
                    f"more than a scan {np.mean(x > 1.0):.1%}"
                )
        return "time to pair by when the aircraft became common: " + ("; ".join(parts) or "none")

    def lines(self) -> list[str]:
        end = self.paired_at_end / self.common_at_end if self.common_at_end else float("nan")
        false = self.false_at_end / self.confirmed_at_end if self.confirmed_at_end else float("nan")
        d = self.dangling
        return [
            f"time to pair (data time, scans of the slower radar): median {self.median:.2f}, "
            f"p95 {self.p95:.2f}, max {float(self.scans.max(initial=0.0)):.2f} over "
            f"{self.scans.size} paired common aircraft; never paired {self.never_paired} of {self.common}",
            self.split(),
            f"at the end: {self.paired_at_end}/{self.common_at_end} ({end:.4f}) of the common aircraft "
            f"paired right; false {self.false_at_end}/{self.confirmed_at_end} ({false:.4f}) of the "
            "confirmed pairs",
            f"dangling references: {d.references} in {d.outputs} of {self.outputs} outputs "
            f"(at most {d.worst} at once)" + (f"; e.g. {', '.join(d.examples[:3])}" if d.examples else ""),
        ]


class OutputMonitor:
    """Feed it every output in publish order (:meth:`feed`), then :meth:`report`."""

    def __init__(self, scan_period_s: dict[str, float], settle_scans: float = 2.0) -> None:
        self.scan = dict(scan_period_s)
        self.settle_scans = settle_scans
        #: Latest TrackBatch per radar: track id -> (confirmed, truth id).
        self.tables: dict[str, dict[str, tuple[bool, str | None]]] = {}
        self.table_time: dict[str, float] = {}
        #: Latest PairSet per radar pair: list of (track_a, track_b, confirmed).
        self.pairs: dict[tuple[str, str], list[tuple[str, str, bool]]] = {}
        #: Latest system tracks' radar members: (radar id, track id).
        self.members: list[tuple[str, str]] = []
        #: (radar, aircraft) -> first data time a confirmed track of it was published.
        self.first_held: dict[tuple[str, str], float] = {}
        #: (radar_a, radar_b, aircraft) -> first data time a right confirmed pair was published.
        self.first_paired: dict[tuple[str, str, str], float] = {}
        self.correlated: set[tuple[str, str]] = set()
        self.last_time_s = -np.inf
        self.dangling = Dangling()
        self.outputs = 0
        self._pairs_of: dict[str, set[tuple[str, str]]] = defaultdict(set)

    # -- input --------------------------------------------------------------------------------
    def feed(self, key: str, body: dict[str, Any]) -> None:
        parts = key.split("/")
        if len(parts) >= 4 and parts[-3] == "radar" and parts[-1] == "tracks":
            self._tracks(parts[-2], body)
        elif len(parts) >= 3 and parts[-3] == "pairs":
            self._pair_set((parts[-2], parts[-1]), body)
        elif key.endswith("/system/tracks"):
            self.members = [
                (m["radar_id"], m["track_id"])
                for t in body["system_tracks"]
                for m in t["members"]
                if m["radar_id"] in self.scan
            ]
            self._check(self._all_references())
        else:
            return
        self.outputs += 1

    def _tracks(self, radar_id: str, body: dict[str, Any]) -> None:
        t = float(body["time_s"])
        self.last_time_s = max(self.last_time_s, t)
        table = {tr["track_id"]: (tr["status"] == "confirmed", tr.get("truth_id")) for tr in body["tracks"]}
        self.tables[radar_id] = table
        self.table_time[radar_id] = t
        for confirmed, truth in table.values():
            if confirmed and truth is not None:
                self.first_held.setdefault((radar_id, truth), t)
        refs = [
            (rid, tid)
            for key in self._pairs_of[radar_id]
            for ta, tb, _ in self.pairs[key]
            for rid, tid in ((key[0], ta), (key[1], tb))
            if rid == radar_id
        ]
        refs += [(rid, tid) for rid, tid in self.members if rid == radar_id]
        self._check(refs)

    def _pair_set(self, key: tuple[str, str], body: dict[str, Any]) -> None:
        a, b = key
        if a not in self.scan or b not in self.scan:
            return  # a reference source: no TrackBatch to check against
        t = float(body["time_s"])
        self.correlated.add(key)
        rows = [(p["track_a"], p["track_b"], p["status"] == "confirmed") for p in body["pairs"]]
        self.pairs[key] = rows
        self._pairs_of[a].add(key)
        self._pairs_of[b].add(key)
        ta_, tb_ = self.tables.get(a, {}), self.tables.get(b, {})
        for ta, tb, confirmed in rows:
            if not confirmed:
                continue
            xa, xb = ta_.get(ta, (False, None))[1], tb_.get(tb, (False, None))[1]
            if xa is not None and xa == xb:
                self.first_paired.setdefault((a, b, xa), t)
        self._check([(rid, tid) for ta, tb, _ in rows for rid, tid in ((a, ta), (b, tb))])

    def _all_references(self) -> list[tuple[str, str]]:
        refs = [
            (rid, tid)
            for (a, b), rows in self.pairs.items()
            for ta, tb, _ in rows
            for rid, tid in ((a, ta), (b, tb))
        ]
        return refs + self.members

    def _check(self, refs: list[tuple[str, str]]) -> None:
        """Count the references among ``refs`` to tracks the latest tables do not hold (a
        radar with no TrackBatch yet holds none)."""
        bad = [(rid, tid) for rid, tid in refs if tid not in self.tables.get(rid, {})]
        if bad:
            d = self.dangling
            d.outputs += 1
            d.references += len(bad)
            d.worst = max(d.worst, len(bad))
            if len(d.examples) < 5:
                d.examples.append(f"{bad[0][0]}:{bad[0][1]}")

    # -- result -------------------------------------------------------------------------------
    def report(self, start_s: float = 60.0) -> PromptnessReport:
        """``start_s``: aircraft common within this much data time of the run's first confirmed
        track count as the start's (:attr:`PromptnessReport.at_start`)."""
        scans: list[float] = []
        at_start: list[bool] = []
        first = min(self.first_held.values(), default=0.0)
        never = common = 0
        end = self.last_time_s
        for a, b in sorted(self.correlated):
            period = max(self.scan[a], self.scan[b])
            aircraft = {x for (r, x) in self.first_held if r == a} & {
                x for (r, x) in self.first_held if r == b
            }
            for x in sorted(aircraft):
                start = max(self.first_held[(a, x)], self.first_held[(b, x)])
                paired = self.first_paired.get((a, b, x))
                if paired is not None:
                    scans.append(max(0.0, paired - start) / period)
                    at_start.append(start - first <= start_s)
                    common += 1
                elif end - start >= self.settle_scans * period:
                    never += 1
                    common += 1
        paired_end = common_end = false_end = confirmed_end = 0
        for (a, b), rows in self.pairs.items():
            ta_, tb_ = self.tables.get(a, {}), self.tables.get(b, {})
            held_a = {x for c, x in ta_.values() if c and x is not None}
            held_b = {x for c, x in tb_.values() if c and x is not None}
            right = set()
            for ta, tb, confirmed in rows:
                if not confirmed:
                    continue
                confirmed_end += 1
                xa, xb = ta_.get(ta, (False, None))[1], tb_.get(tb, (False, None))[1]
                if xa is not None and xa == xb:
                    right.add(xa)
                else:
                    false_end += 1
            both = held_a & held_b
            common_end += len(both)
            paired_end += len(both & right)
        return PromptnessReport(
            scans=np.asarray(scans),
            never_paired=never,
            common=common,
            paired_at_end=paired_end,
            common_at_end=common_end,
            false_at_end=false_end,
            confirmed_at_end=confirmed_end,
            dangling=self.dangling,
            outputs=self.outputs,
            at_start=np.asarray(at_start, dtype=bool),
            start_s=start_s,
        )


def watch_engine(
    engine: Engine, stream: Iterable[tuple[str, bytes]], monitor: OutputMonitor
) -> PromptnessReport:
    """Feed ``stream`` (key, payload) through ``engine`` in this process and every output it
    returns, then those of its ``flush``, to ``monitor`` in publish order (as a subscriber to
    every key hears them); the engine is closed after.  ``monitor``'s report."""
    try:
        for key, payload in stream:
            for out in engine.ingest(key, payload, receive_time_s=0.0):
                monitor.feed(out.key, out.body())
        for out in engine.flush():
            monitor.feed(out.key, out.body())
    finally:
        engine.close()
    return monitor.report()
