"""Partitioned workers: who is alive, and the whole network's ``/status``, ``/radars`` and
``/pairs`` from one worker's own and the others' (contract §4.6: every worker's HTTP port
answers for the network).

:class:`PeerWorkers` follows the other workers (their liveliness tokens ``{prefix}/workers/{k}``
and latest statuses ``{prefix}/workers/{k}/status``, Zenoh callbacks); the merging itself is
pure functions of the statuses.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import orjson
import zenoh

from service.engine import Snapshot
from service.pipeline.partition import BIAS_WORKER, Partition
from service.pipeline.read_model import selects
from service.transport.session import json_replies
from service.wire.keys import Keys, parse_key

log = logging.getLogger(__name__)

#: What ``/status`` ``partition.workers`` says of one worker: the age of its status (s, None:
#: never heard), its radars, its pair sets.
Worker = tuple[float | None, list[str], int]


def partition_section(partition: Partition, alive: set[int], workers: dict[int, Worker]) -> dict[str, Any]:
    """``/status`` ``partition``: who owns what, who is alive, which partitions are missing."""
    n = partition.count
    return {
        "partition": str(partition),
        "count": n,
        "bias_worker": BIAS_WORKER,
        "salt": partition.salt,
        "workers": [
            {
                "partition": f"{k}/{n}",
                "alive": k in alive,
                "radars": workers[k][1] if k in workers else [],
                "pair_sets": workers[k][2] if k in workers else 0,
                "status_age_s": _age(workers.get(k)),
            }
            for k in range(1, n + 1)
        ],
        "missing": [k for k in range(1, n + 1) if k not in alive],
    }


def _age(worker: Worker | None) -> float | None:
    return round(worker[0], 3) if worker is not None and worker[0] is not None else None


def merge_statuses(
    own: dict[str, Any], peers: dict[int, tuple[float, dict[str, Any]]], partition: Partition, alive: set[int]
) -> dict[str, Any]:
    """The network's status from this worker's (``own``, changed in place and returned) and
    the live workers' latest (``peers``: worker -> (age s, status)): every radar once, pairs,
    rejections, correlation updates and pending messages summed (the update time histogram
    too, its quantiles the worst worker's), outputs complete through the earliest worker's
    ``outputs_time_s``.  A malformed peer status is passed over (logged at debug level)."""
    radars = {r["radar_id"]: r for r in own["radars"]}
    rejected = dict(own["rejected"])
    corr = dict(own["correlation"])
    workers: dict[int, Worker] = {
        partition.index: (0.0, sorted(radars), own["partition"]["workers"][partition.index - 1]["pair_sets"])
    }
    for k, (age, st) in sorted(peers.items()):
        try:
            for r in st["radars"]:
                radars.setdefault(r["radar_id"], r)
            own["pairs_confirmed"] += int(st["pairs_confirmed"])
            own["pairs_tentative"] += int(st["pairs_tentative"])
            own["pairs_held"] += int(st.get("pairs_held", 0))  # (a peer of an older version: none)
            for reason, count in st["rejected"].items():
                rejected[reason] = rejected.get(reason, 0) + int(count)
            c = st["correlation"]
            corr["updates"] += int(c["updates"])
            corr["p50_ms"] = max(corr["p50_ms"], float(c["p50_ms"]))
            corr["p99_ms"] = max(corr["p99_ms"], float(c["p99_ms"]))
            theirs = c.get("duration_buckets", {})
            corr["duration_buckets"] = {
                le: n + int(theirs.get(le, 0)) for le, n in corr["duration_buckets"].items()
            }
            corr["duration_sum_s"] += float(c.get("duration_sum_s", 0.0))
            corr["pending"] = int(corr.get("pending", 0)) + int(c.get("pending", 0))
            # complete through: the network's outputs are only as complete as its slowest worker's
            theirs_s, mine_s = st.get("outputs_time_s"), own.get("outputs_time_s")
            own["outputs_time_s"] = (
                None if theirs_s is None or mine_s is None else min(mine_s, float(theirs_s))
            )
            mine = st["partition"]["workers"][k - 1]
            workers[k] = (age, list(mine["radars"]), int(mine["pair_sets"]))
        except (KeyError, TypeError, ValueError, IndexError):
            log.debug("malformed status of worker %d", k)
    own["radars"] = [radars[k] for k in sorted(radars)]
    own["rejected"] = dict(sorted(rejected.items()))
    own["correlation"] = corr
    progress = own["partition"]["progress"]
    own["partition"] = partition_section(partition, alive, workers)
    own["partition"]["progress"] = progress
    return own


class PeerWorkers:
    """The other workers of a partitioned network, as this worker hears of them (wall clock:
    this is operations, not data)."""

    def __init__(self, keys: Keys, partition: Partition, grace_s: float) -> None:
        self.keys = keys
        self.partition = partition
        #: A worker whose token left is still waited for this long (s; ``peer_grace_s``).
        self.grace_s = grace_s
        #: The other workers' latest statuses (when heard, raw), by K, and who is alive.
        self.statuses: dict[int, tuple[float, bytes]] = {}
        self.alive: set[int] = set()
        #: Workers whose token left, and when (monotonic): waited for until ``grace_s``.
        self.gone_at: dict[int, float] = {}
        #: Workers whose leaving was logged: their token's return is logged too.
        self._said_left: set[int] = set()
        self._waited: set[int] | None = None
        # Zenoh's threads change the tokens while the worker and HTTP threads read them: a set
        # or dict changed during an iteration raises, and the worker thread must not die of it.
        self._lock = threading.Lock()

    def declare(self, session: zenoh.Session) -> list[Any]:
        """At the session's start: follow the others' statuses and tokens, declare this
        worker's token; a worker not seen yet is waited for as one that just left."""
        now = time.monotonic()
        with self._lock:
            self.gone_at = {k: now for k in range(1, self.partition.count + 1) if k != self.partition.index}
        return [
            session.declare_subscriber(
                self.keys.worker_statuses, zenoh.handlers.Callback(self.on_status, indirect=False)
            ),
            session.liveliness().declare_subscriber(self.keys.workers, self.on_token, history=True),
            session.liveliness().declare_token(self.keys.worker(self.partition.index)),
        ]

    def on_status(self, sample: zenoh.Sample) -> None:
        kind, ids = parse_key(str(sample.key_expr), self.keys.prefix)
        if kind == "worker_status" and int(ids[0]) != self.partition.index:
            self.statuses[int(ids[0])] = (time.monotonic(), sample.payload.to_bytes())

    def on_token(self, sample: zenoh.Sample) -> None:
        index = str(sample.key_expr).rsplit("/", 1)[-1]
        if not index.isdigit():
            return
        k = int(index)
        with self._lock:
            back = k in self._said_left
            if sample.kind == zenoh.SampleKind.PUT:
                self._said_left.discard(k)
                self.alive.add(k)
                self.gone_at.pop(k, None)
            else:
                self.alive.discard(k)
                self.gone_at[k] = time.monotonic()
                self._said_left.add(k)
        if k == self.partition.index:
            return
        if sample.kind != zenoh.SampleKind.PUT:
            log.warning("worker %s/%d left (its radars and pairs are missing)", index, self.partition.count)
        elif back:  # (the line that ends the one above: an operator reading the log sees both)
            log.warning("worker %s/%d is back", index, self.partition.count)

    def waited_changed(self) -> set[int] | None:
        """The workers the merger waits for, when they changed (else None): those alive, and
        those whose token left less than ``grace_s`` ago.  A token that leaves and comes back
        (a session that lost its router for a moment under load) must not make the others stop
        waiting: they would correlate without its tables and take them late, out of order."""
        now = time.monotonic()
        with self._lock:
            waited = set(self.alive) | {k for k, t in self.gone_at.items() if now - t < self.grace_s}
        if waited == self._waited:
            return None
        self._waited = waited
        return waited

    def own_section(self, radars: list[str], pair_sets: int, progress: Any) -> dict[str, Any]:
        """This worker's ``partition`` section of its own status."""
        with self._lock:
            alive = self.alive | {self.partition.index}
        section = partition_section(
            self.partition,
            alive,
            {self.partition.index: (0.0, radars, pair_sets)},
        )
        section["progress"] = progress
        return section

    def network_status(self, own: dict[str, Any]) -> dict[str, Any]:
        """The network's status from this worker's (changed in place) and every live worker's
        latest."""
        now = time.monotonic()
        with self._lock:
            alive = self.alive | {self.partition.index}
        peers: dict[int, tuple[float, dict[str, Any]]] = {}
        for k, (seen, raw) in list(self.statuses.items()):
            if k in alive:
                try:
                    peers[k] = (now - seen, orjson.loads(raw))
                except orjson.JSONDecodeError:
                    continue
        return merge_statuses(own, peers, self.partition, alive)


def network_radars(
    own: list[dict[str, Any]], sites: dict[str, Any], counters: dict[str, dict[str, Any]]
) -> list[dict[str, Any]]:
    """``GET /radars`` of a partitioned worker: its own radars (``own``), and every other radar
    it knows the site of with its owner's counters (from the network's status)."""
    seen = {r["radar_id"] for r in own}
    keys = ("batches", "plots", "rejected", "lost_batches", "last_time_s")
    others = []
    for rid, site in sorted(sites.items()):
        if rid not in seen:
            c = counters.get(rid, {})
            others.append(
                {**site.model_dump(), **{k: c.get(k, 0 if k != "last_time_s" else None) for k in keys}}
            )
    return sorted(own + others, key=lambda r: str(r["radar_id"]))


def network_pair_sets(
    session: zenoh.Session,
    keys: Keys,
    snapshot: Snapshot,
    own: list[dict[str, Any]],
    radars: tuple[str | None, str | None],
    status: str,
    timeout_s: float,
) -> list[dict[str, Any]]:
    """``GET /pairs`` of a partitioned worker: its own pair sets (``own``, of ``snapshot``),
    and the other workers' (a Zenoh ``get``) between radars including those of ``radars``."""
    have = {(p["radar_a"], p["radar_b"]) for p in snapshot.pair_sets(radars[0], radars[1], "all")}
    out = list(own)
    replies = session.get(keys.pairs_all, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s)
    for body in json_replies(replies):
        try:
            key = (body["radar_a"], body["radar_b"])
        except KeyError:
            continue
        if key in have or not selects(radars, key):
            continue
        have.add(key)
        if status != "all":
            body = {**body, "pairs": [p for p in body.get("pairs", []) if p.get("status") == status]}
        out.append(body)
    return sorted(out, key=lambda p: (p["radar_a"], p["radar_b"]))


def network_performance(
    session: zenoh.Session, keys: Keys, radar_id: str, timeout_s: float
) -> dict[str, Any] | None:
    """``GET /radars/{id}/performance`` of a partitioned worker that does not own the radar:
    its owner's (the one worker with its plots; a Zenoh ``get``); None while it does not answer."""
    replies = session.get(
        keys.performance(radar_id), consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s
    )
    for body in json_replies(replies):
        if body.get("radar_id") == radar_id:
            return body
    return None


def network_system_tracks(
    session: zenoh.Session, keys: Keys, status: str, timeout_s: float
) -> dict[str, Any] | None:
    """``GET /system-tracks`` of a partitioned worker other than 1: worker 1's, the one that
    draws them (a Zenoh ``get``); None while it does not answer (no picture is not an empty
    sky)."""
    selector = f"{keys.system_tracks}?status={status}"
    replies = session.get(selector, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s)
    for body in json_replies(replies):
        if isinstance(body.get("system_tracks"), list):
            return body
    return None
